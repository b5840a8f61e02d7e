"""`aero fc params show|apply SET`: the flight-controller parameter sets of tools/cli/fc_params.py.

`show` prints a set with every value's reason; `apply` sets it on a connected flight controller over
MAVLink (as a ground station would: PARAM_SET, then PARAM_REQUEST_READ) and prints, per parameter,
the value wanted and the value read back. Exit 0 when every read-back matches, 1 otherwise.
"""
from __future__ import annotations

import argparse
import time

from . import fc_params
from .up import check_fcu_url
from aeroperception.tools.common import CliError, emit

SOURCE_SYSTEM, SOURCE_COMPONENT = 255, 190    # a ground station's ids: not fmu's (1/191) on the same FC


def register(sub: argparse._SubParsersAction) -> None:
    fc = sub.add_parser("fc", help="flight-controller set-up: parameter sets for GPS-denied flight")
    fsub = fc.add_subparsers(dest="fc_cmd", required=True)
    params = fsub.add_parser("params", help="the parameter sets the stack needs on PX4")
    psub = params.add_subparsers(dest="params_cmd", required=True)
    p = psub.add_parser("show", help="a set's parameters, values and reasons")
    p.add_argument("set", choices=list(fc_params.SETS))
    p.set_defaults(func=params_show)
    p = psub.add_parser("apply", help="set a set on a connected flight controller and read each value back")
    p.add_argument("set", choices=list(fc_params.SETS))
    p.add_argument("--fcu-url", required=True,
                   help="pymavlink URL of the FC, e.g. /dev/ttyACM0,921600, udpin:0.0.0.0:14550 or, for PX4 SITL "
                        "instance N, its GCS link udpout:127.0.0.1:<18570+N> (fmu keeps its own link)")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the FC's HEARTBEAT")
    p.set_defaults(func=params_apply)


def params_show(args) -> int:
    emit(f"{'PARAMETER':<18} {'VALUE':>8}  WHY")
    for p in fc_params.SETS[args.set]:
        emit(f"{p.name:<18} {p.text:>8}  {p.why}")
    return 0


def params_apply(args) -> int:
    check_fcu_url(args.fcu_url)
    conn = _connect(args.fcu_url, args.timeout)
    try:
        rows = fc_params.apply(conn, conn.target_system, fc_params.SETS[args.set])
    finally:
        conn.close()
    emit(f"{'PARAMETER':<18} {'WANTED':>8} {'READ BACK':>10}")
    for r in rows:
        read = "(no answer)" if r.read_back is None else fc_params.FcParam(r.param.name, r.read_back, "").text
        emit(f"{r.param.name:<18} {r.param.text:>8} {read:>10}{'' if r.ok else '  MISMATCH'}")
    bad = [r.param.name for r in rows if not r.ok]
    emit(f"{len(rows) - len(bad)}/{len(rows)} set" + (f"; not as wanted: {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0


def _connect(url: str, timeout_s: float):
    """A link to the FC, locked onto the first autopilot HEARTBEAT (not a ground station's or ours)."""
    from pymavlink import mavutil

    try:
        conn = mavutil.mavlink_connection(url, source_system=SOURCE_SYSTEM, source_component=SOURCE_COMPONENT,
                                          autoreconnect=False)
    except Exception as e:   # serial/socket errors arrive as many types: say which, in one line
        raise CliError(f"--fcu-url {url}: cannot open it ({e})") from None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
        if m is not None and m.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID:
            conn.target_system = m.get_srcSystem()
            return conn
    conn.close()
    raise CliError(f"no flight controller HEARTBEAT on {url} within {timeout_s:g} s: is it connected and "
                   "sending on that link? (PX4 SITL instance N: udpout:127.0.0.1:<18570+N>)")
