"""`aero param list|get|set SERVICE ...`: live parameters through config/<service>/@params|@set."""
from __future__ import annotations

import argparse
import sys

from aeroperception.schemas import ParamList, ParamSet, ParamSetReply

from .topic import call_once
from aeroperception.tools.common import add_session_arguments, parse_data


def register(sub: argparse._SubParsersAction) -> None:
    param = sub.add_parser("param", help="list, get and set a service's live parameters")
    psub = param.add_subparsers(dest="param_cmd", required=True)
    p = psub.add_parser("list", help="every declared parameter with value, unit and limits")
    add_session_arguments(p)
    p.add_argument("service")
    p.set_defaults(func=param_list)
    p = psub.add_parser("get", help="one parameter's value")
    add_session_arguments(p)
    p.add_argument("service")
    p.add_argument("name")
    p.set_defaults(func=param_get)
    p = psub.add_parser("set", help="set a parameter; the service validates it against its declaration")
    add_session_arguments(p)
    p.add_argument("service")
    p.add_argument("name")
    p.add_argument("value")
    p.set_defaults(func=param_set)


def _list(args) -> ParamList:
    return call_once(args, f"config/{args.service}/@params", None, ParamList)


def param_list(args) -> int:
    plist = _list(args)
    print(f"{'NAME':<28} {'VALUE':>12} {'UNIT':<8} {'RANGE':<20} DESCRIPTION")
    for p in plist.params:
        rng = "" if p.min is None and p.max is None else f"[{p.min}, {p.max}]"
        if p.choices:
            rng = "|".join(map(str, p.choices))
        note = "(start only) " if p.start_only else ""
        print(f"{p.name:<28} {str(p.value):>12} {p.unit:<8} {rng:<20} {note}{p.description}")
    return 0


def param_get(args) -> int:
    for p in _list(args).params:
        if p.name == args.name:
            print(p.value)
            return 0
    print(f"aero: {args.service} has no parameter {args.name!r}", file=sys.stderr)
    return 2


def param_set(args) -> int:
    reply = call_once(args, f"config/{args.service}/@set", ParamSet(name=args.name, value=parse_value(args.value)),
                      ParamSetReply)
    if not reply.success:
        print(f"aero: rejected: {reply.message}", file=sys.stderr)
        return 1
    print(f"{reply.name} = {reply.value}")
    return 0


def parse_value(text: str):
    """A number as a number ("1e9" too, which YAML 1.1 reads as a string), else YAML/JSON."""
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return parse_data(text)
