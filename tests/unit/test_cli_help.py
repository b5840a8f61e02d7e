"""`--help` of every `aero` command and sub-command exits 0 and prints its usage, never a
traceback. The command list is walked from the parser `aero` itself builds (a new sub-command is
covered without editing this file); `aero run SERVICE --help` is each service's own parser.

A help string is a %-format (argparse fills %(default)s): a bare "%" in one ("CPU %") made
`aero bench --help` die with "ValueError: incomplete format".
"""
from __future__ import annotations

import argparse
import contextlib
import io
import subprocess
import sys

import pytest

from aeroperception.tools.cli import aero as cli
from aeroperception.tools.cli.run import available


def command_paths(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every command path of the parser tree, the root (()) included."""
    paths = [path]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                paths += command_paths(child, path + (name,))
    return paths


PATHS = command_paths(cli.build_parser())


def run_help(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(argv)
        except SystemExit as e:
            code = e.code
    return code, out.getvalue(), err.getvalue()


def test_the_walk_finds_the_nested_sub_commands():
    assert ("bench", "record") in PATHS and ("mission", "load") in PATHS and len(PATHS) > 30


@pytest.mark.parametrize("path", PATHS, ids=lambda p: " ".join(p) or "aero")
def test_help_of_every_command_exits_0_with_its_usage(path):
    code, out, err = run_help([*path, "--help"])
    assert code == 0, err
    assert out.startswith("usage: aero" + "".join(" " + p for p in path)), out[:200]
    assert "Traceback" not in out + err


@pytest.mark.parametrize("service", available())
def test_help_of_every_service_under_aero_run_exits_0(service):
    code, out, err = run_help(["run", service, "--help"])
    assert code == 0, err
    assert out.startswith(f"usage: aero run {service}"), out[:200]


def test_aero_bench_help_in_a_real_process_has_no_traceback():
    """The reported command, as a user types it (the console script's process, not an import)."""
    proc = subprocess.run([sys.executable, "-m", "aeroperception.tools.cli", "bench", "--help"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "record" in proc.stdout and "CPU %" in proc.stdout


def test_a_bench_that_cannot_run_says_so_in_one_line(monkeypatch, capsys):
    """A bench whose stack did not come up raised RuntimeError through `aero` as a traceback."""
    from aeroperception.tools.bench import flight

    def no_stack(*_a, **_k):
        raise RuntimeError("stack did not come up (logs: /tmp/x)")

    monkeypatch.setattr(flight, "run", no_stack)
    assert cli.main(["bench", "flight", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert err == "aero: bench flight: stack did not come up (logs: /tmp/x)\n"
