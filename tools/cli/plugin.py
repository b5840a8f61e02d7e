"""`aero plugin list|set`: the planner's swappable parts (trajectory generator, controller,
estimator). `set ROLE NAME` is SetTrajectoryGenerator / SetController / SetEstimator
(planner/srv/select_plugin): refused while the vehicle moves (switch on the ground or hovering)
and for a name that is not registered, saying which are. `list` shows what runs and what exists
(the planner's parameters of the same names: one value). A switch persists across planner restarts
(planner/plugins.py): `set` the default back to return to it."""
from __future__ import annotations

import argparse
import sys

from aeroperception.schemas import ParamList, SelectPluginReply, SelectPluginRequest
from aeroperception.schemas.services import PLUGIN_ROLES

from .topic import call_once
from aeroperception.tools.common import add_session_arguments

SERVICE = "planner"


def register(sub: argparse._SubParsersAction) -> None:
    plugin = sub.add_parser("plugin", help="the planner's trajectory generator, controller and estimator: list, switch")
    psub = plugin.add_subparsers(dest="plugin_cmd", required=True)
    p = psub.add_parser("list", help="what runs in each slot and what is registered")
    add_session_arguments(p)
    p.set_defaults(func=plugin_list)
    p = psub.add_parser("set", help="switch a slot (on the ground or hovering only; kept across planner restarts)")
    add_session_arguments(p)
    p.add_argument("role", choices=PLUGIN_ROLES, metavar="ROLE", help=" | ".join(PLUGIN_ROLES))
    p.add_argument("name", help="a registered name (aero plugin list)")
    p.set_defaults(func=plugin_set)


def plugin_list(args) -> int:
    plist = call_once(args, f"config/{SERVICE}/@params", None, ParamList)
    slots = {p.name: p for p in plist.params if p.name in PLUGIN_ROLES}
    print(f"{'ROLE':<22} {'ACTIVE':<12} REGISTERED")
    for role in PLUGIN_ROLES:
        p = slots.get(role)
        if p is not None:
            print(f"{role:<22} {str(p.value):<12} {', '.join(map(str, p.choices or []))}")
    return 0


def plugin_set(args) -> int:
    reply = call_once(args, f"{SERVICE}/srv/select_plugin", SelectPluginRequest(role=args.role, name=args.name),
                      SelectPluginReply)
    if not reply.success:
        print(f"aero: refused: {reply.message}", file=sys.stderr)
        return 1
    print(f"{args.role} = {reply.active}")
    return 0
