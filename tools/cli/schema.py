"""`aero schema`: look at the message schemas without reading Python.

    aero schema list                  every registered schema: name@version, field count, summary
    aero schema show VehicleState     its fields (type, default), array shapes, enum constants
    aero schema export --out DIR      one JSON Schema file per schema, for non-Python consumers

Handlers return an exit code; a user error prints one line to stderr and returns 2.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

import msgspec

from aeroperception.schemas import REGISTRY, NDArray, SchemaError, get_schema, schema_id

__all__ = ["register"]

DEFAULT_EXPORT_DIR = "schema-export"


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add the `schema` command (with list/show/export) to an argparse subparsers object."""
    p = subparsers.add_parser("schema", help="list, show and export message schemas",
                              description="Inspect the msgpack message schemas.")
    p.set_defaults(func=lambda args: _usage(p))
    sub = p.add_subparsers(dest="schema_command", metavar="{list,show,export}")

    p_list = sub.add_parser("list", help="every schema: name@version, field count, summary")
    p_list.set_defaults(func=cmd_list)

    p_show = sub.add_parser("show", help="fields, types, defaults and constants of one schema")
    p_show.add_argument("name", help="schema name, e.g. VehicleState (or VehicleState@1)")
    p_show.set_defaults(func=cmd_show)

    p_exp = sub.add_parser("export", help="write one JSON Schema file per schema")
    p_exp.add_argument("--out", default=DEFAULT_EXPORT_DIR, metavar="DIR",
                       help=f"output directory (default: ./{DEFAULT_EXPORT_DIR})")
    p_exp.set_defaults(func=cmd_export)
    return p


def _fail(msg: str) -> int:
    print(f"aero schema: error: {msg}", file=sys.stderr)
    return 2


def _usage(p: argparse.ArgumentParser) -> int:
    p.print_usage(sys.stderr)
    print("aero schema: error: choose a sub-command: list, show NAME, export [--out DIR]", file=sys.stderr)
    return 2


def _summary(cls: type, width: int = 100) -> str:
    """First sentence of the docstring, on one line."""
    para = " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split())
    m = re.search(r"(?<!e\.g)(?<!i\.e)\.(?:\s|$)", para)
    first = para[: m.start() + 1] if m else para
    return first if len(first) <= width else first[: width - 3].rstrip() + "..."


def cmd_list(args: argparse.Namespace) -> int:
    rows = [(schema_id(cls), str(len(msgspec.structs.fields(cls))), _summary(cls))
            for _, cls in sorted(REGISTRY.items())]
    w0 = max(len("SCHEMA"), *(len(r[0]) for r in rows))
    print(f"{'SCHEMA':<{w0}}  FIELDS  SUMMARY")
    for sid, n, doc in rows:
        print(f"{sid:<{w0}}  {n:>6}  {doc}")
    return 0


_QUALIFIED = re.compile(r"\b(?:[A-Za-z_]\w*\.)+([A-Za-z_]\w*)")


def type_name(t: Any) -> str:
    """A field type as written in the schema ("Vector3 | None"), module paths stripped."""
    if isinstance(t, type) and not getattr(t, "__args__", None):
        return t.__name__
    return _QUALIFIED.sub(r"\1", str(t)).replace("NoneType", "None")


def default_text(f: msgspec.structs.FieldInfo) -> str:
    """A field's default as a reader wants it: "(required)", a value, or "zeros (6, 6) float64"."""
    if f.required:
        return "(required)"
    if f.default is not msgspec.NODEFAULT:
        return repr(f.default)
    value = f.default_factory()
    if isinstance(value, NDArray):
        return f"zeros {value.shape} {value.dtype}" if not any(value.to_numpy().flat) else f"{value.shape} {value.dtype}"
    if isinstance(value, msgspec.Struct) and value == type(value)():
        return f"{type(value).__name__}()"
    return repr(value)


def constants(cls: type) -> list[tuple[str, Any]]:
    """The UPPER_CASE class constants (enum values), the base classes' first."""
    seen: dict[str, Any] = {}
    for klass in reversed(cls.__mro__):
        for name, value in vars(klass).items():
            if name.isupper() and not name.startswith("_") and isinstance(value, (int, str, tuple)) \
                    and not isinstance(value, bool):
                seen[name] = value
    return list(seen.items())


def _resolve(name: str) -> type:
    try:
        return get_schema(name)
    except SchemaError:
        base = name.partition("@")[0].lower()
        matches = [cls for n, cls in REGISTRY.items() if n.lower() == base]
        if len(matches) == 1:
            return matches[0]
        raise


def cmd_show(args: argparse.Namespace) -> int:
    try:
        cls = _resolve(args.name)
    except (SchemaError, ValueError) as e:
        return _fail(str(e))
    print(f"{schema_id(cls)}  ({cls.__module__.replace('aeroperception.', '')}.{cls.__name__})")
    doc = (cls.__doc__ or "").strip()
    if doc:
        print()
        for line in doc.splitlines():
            print(f"  {line.strip()}")
    fields = msgspec.structs.fields(cls)
    try:
        rows = [(f.encode_name, type_name(f.type), default_text(f)) for f in fields]
    except Exception as e:  # a broken default factory is a bug, but `show` should still explain
        return _fail(f"cannot describe {cls.__name__}: {e}")
    w0 = max(len("FIELD"), *(len(r[0]) for r in rows))
    w1 = max(len("TYPE"), *(len(r[1]) for r in rows))
    print(f"\n{'FIELD':<{w0}}  {'TYPE':<{w1}}  DEFAULT")
    for name, typ, default in rows:
        print(f"{name:<{w0}}  {typ:<{w1}}  {default}")
    shapes = getattr(cls, "__shapes__", {})
    if shapes:
        print("\nARRAY SHAPES (-1 = any)")
        for name, shape in shapes.items():
            print(f"  {name}: {list(shape)}")
    consts = constants(cls)
    if consts:
        print("\nCONSTANTS")
        for name, value in consts:
            print(f"  {name} = {value!r}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, cls in sorted(REGISTRY.items()):
            doc = msgspec.json.schema(cls)
            doc = {
                "$schema": "https://json-schema.org/draft/2020-12/schema",
                "$id": schema_id(cls),
                "description": f"msgpack map on the wire (bytes fields are msgpack bin, not base64); "
                               f"Zenoh encoding application/msgpack;{schema_id(cls)}",
                **doc,
            }
            (out / f"{name}.json").write_text(json.dumps(doc, indent=2, sort_keys=False) + "\n")
    except OSError as e:
        return _fail(f"cannot write to {out}: {e.strerror or e}")
    print(f"wrote {len(REGISTRY)} JSON Schema files to {out}")
    return 0
