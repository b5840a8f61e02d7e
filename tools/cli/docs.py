"""`aero docs reference [--write | --check] [--out DIR]`: the generated reference pages
(docs/reference/: keys, schemas, parameters, command line), made by tools/reference.py from the
code, so the docs cannot drift from it.

`--write` writes the pages that changed, `--check` exits 1 naming the pages that differ from
what the code says (tests/unit/test_docs.py does the same); with neither, the pages are printed.
`aero docs keys` is the same for the key page alone (its older name, kept for scripts).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from aeroperception.tools import reference
from aeroperception.tools.common import CliError

DEFAULT_OUT = Path(__file__).resolve().parents[2] / "docs" / "reference"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("docs", help="generated documentation")
    dsub = p.add_subparsers(dest="docs_cmd", required=True)
    r = dsub.add_parser("reference", help="docs/reference/{keys,schemas,parameters,cli}.md, from the code")
    _add_options(r)
    r.set_defaults(func=docs_reference, pages=None)
    k = dsub.add_parser("keys", help="docs/reference/keys.md alone, from services/*/contract.py")
    _add_options(k)
    k.set_defaults(func=docs_reference, pages=["keys.md"])


def _add_options(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", action="store_true", help="write the pages that changed")
    g.add_argument("--check", action="store_true", help="exit 1 if a page is out of date")
    # The default is shown as text: the absolute path would differ between checkouts (and in cli.md).
    p.add_argument("--out", metavar="DIR", help="directory of the pages (default: the checkout's docs/reference)")


def stale_pages(out: Path, names=None) -> dict[str, str]:
    """{file name: wanted text} of the pages under `out` that are missing or differ from the code."""
    wanted = reference.pages(names)
    return {n: text for n, text in wanted.items()
            if not (out / n).is_file() or (out / n).read_text(encoding="utf-8") != text}


def docs_reference(args) -> int:
    if not (args.write or args.check):
        sys.stdout.write("\n".join(reference.pages(args.pages).values()))
        return 0
    out = Path(args.out) if args.out else DEFAULT_OUT
    stale = stale_pages(out, args.pages)
    if args.check:
        for name in stale:
            print(f"aero: {out / name} is out of date; run `{reference.COMMAND}`", file=sys.stderr)
        return 1 if stale else 0
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, text in stale.items():
            (out / name).write_text(text, encoding="utf-8")
    except OSError as e:
        raise CliError(f"cannot write to {out}: {e.strerror or e}") from None
    for name in args.pages or reference.PAGES:
        print(f"{out / name}: {'updated' if name in stale else 'up to date'}", file=sys.stderr)
    return 0
