"""The `aero` command: bring the stack up, run services, inspect and inject keys, benchmark.

Every sub-command module exposes `register(subparsers)`; handlers return an exit code. A
CliError (or a schema/config error) is printed as one line, exit code 2, never a traceback.
When the reader of stdout goes away (`aero topic echo KEY | head -1`) the command stops quietly
with exit code 141 (128 + SIGPIPE), like coreutils.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from aeroperception.schemas import SchemaError

from aeroperception.tools.common import EXIT_BROKEN_PIPE, CliError, silence_stdout, stdout_closed

COMMANDS = ["up", "router", "run", "topic", "schema", "param", "plugin", "mission", "bench",
            "eval", "snapshot", "docs", "chaos", "certs", "viz", "record", "play", "fc", "doctor"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="aero", description="AeroPerception drone autonomy stack")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"aeroperception.tools.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["run"] and argv[1:2] not in (["-h"], ["--help"]):  # the service parses its own flags
        from .run import run_service

        return _guard(lambda: run_service(argv[1:]))
    return _guard(lambda: _dispatch(argv))


def _dispatch(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


def _guard(fn) -> int:
    try:
        code = int(fn() or 0)
    except (CliError, SchemaError) as e:
        print(f"aero: {e}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        code = 130
    except BrokenPipeError:  # stdout's reader left (`| head`): nothing more to say
        silence_stdout()
    return EXIT_BROKEN_PIPE if stdout_closed.is_set() else code


if __name__ == "__main__":
    sys.exit(main())
