"""`aero mission fly|load|command|status`: fly a mission file from the shell.

`fly` reads like a pre-flight checklist: load, arm, take off, start, then show progress
(waypoint i/n, distance, state) until the vehicle has landed and is idle again. Ctrl-C sends
HOLD, then LAND, and waits for the landing.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import zenoh

from aeroperception.schemas import (
    LoadMissionReply, LoadMissionRequest, MissionCommand, MissionStatus, Reply, SchemaError,
    decode, load_mission_file,
)

from .cmd_topic import call_or_fail
from .common import CliError, add_session_arguments, full_key, open_client


def register(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("mission", help="load and fly missions, send mission commands")
    msub = m.add_subparsers(dest="mission_cmd", required=True)
    p = msub.add_parser("fly", help="load FILE, arm, take off, fly it, land; Ctrl-C = HOLD then LAND")
    add_session_arguments(p)
    p.add_argument("file", help="mission JSON/YAML (seed 000 §5.1 format), e.g. examples/missions/survey_01.json")
    p.add_argument("--timeout", type=float, default=600.0, help="give up after this many seconds")
    p.add_argument("--quiet", action="store_true", help="only print state changes")
    p.set_defaults(func=fly)
    p = msub.add_parser("load", help="validate and load a mission file")
    add_session_arguments(p)
    p.add_argument("file")
    p.set_defaults(func=load)
    p = msub.add_parser("command", help="ARM, DISARM, TAKEOFF, START, HOLD, LAND or RTL")
    add_session_arguments(p)
    p.add_argument("command", type=str.upper, choices=["ARM", "DISARM", "TAKEOFF", "START", "HOLD", "LAND", "RTL"])
    p.set_defaults(func=command)


def _read(path: str) -> str:
    p = Path(path)
    try:
        load_mission_file(p)  # validate locally first: the error names the file and field
    except FileNotFoundError:
        raise CliError(f"{p}: no such file") from None
    except SchemaError as e:
        raise CliError(f"{p}: {e}") from None
    return p.read_text()


def _load(session, args, text: str) -> LoadMissionReply:
    reply = call_or_fail(session, full_key(args, "mission/srv/load"), LoadMissionRequest(mission_json=text),
                         LoadMissionReply, 5.0)
    if not reply.success:
        raise CliError(f"mission rejected: {reply.message}")
    return reply


def _command(session, args, cmd: str, timeout_s: float = 15.0) -> Reply:
    reply = call_or_fail(session, full_key(args, "mission/srv/command"), MissionCommand(command=cmd), Reply, timeout_s)
    if not reply.success:
        raise CliError(f"{cmd} refused: {reply.message}")
    return reply


def load(args) -> int:
    text = _read(args.file)
    session = open_client(args)
    try:
        r = _load(session, args, text)
    finally:
        session.close()
    print(f"loaded: {r.message}")
    return 0


def command(args) -> int:
    session = open_client(args)
    try:
        r = _command(session, args, args.command)
    finally:
        session.close()
    print(r.message)
    return 0


def fly(args) -> int:
    text = _read(args.file)
    session = open_client(args)
    latest: list[MissionStatus] = []
    changed = threading.Event()

    def on_status(s: zenoh.Sample) -> None:
        try:
            latest.append(decode(s.payload.to_bytes(), MissionStatus))
            changed.set()
        except SchemaError:
            pass

    sub = session.declare_subscriber(full_key(args, "mission/status"), on_status)
    try:
        r = _load(session, args, text)
        print(f"1/4 loaded: {r.message}", flush=True)
        print("2/4 takeoff: arming and climbing", flush=True)
        _command(session, args, "TAKEOFF")
        print("3/4 start: mission starts when takeoff altitude is reached", flush=True)
        _command(session, args, "START")
        return _follow(session, args, latest, changed)
    except KeyboardInterrupt:
        print("\ninterrupted: HOLD, then LAND", flush=True)
        for cmd in ("HOLD", "LAND"):
            try:
                _command(session, args, cmd)
            except CliError as e:
                print(f"  {cmd}: {e}", file=sys.stderr)
        _follow(session, args, latest, changed, quiet=True, interrupted=True)
        return 130
    finally:
        sub.undeclare()
        session.close()


def _follow(session, args, latest, changed, quiet: bool = False, interrupted: bool = False) -> int:
    """Print progress until the vehicle is back in IDLE after having flown."""
    deadline = time.monotonic() + args.timeout
    flew = False
    last_state = None
    seen = []
    while time.monotonic() < deadline:
        changed.wait(1.0)
        changed.clear()
        if not latest:
            continue
        st = latest[-1]
        if st.state != last_state:
            seen.append(st.state)
            print(f"   state {st.state}: {st.message}", flush=True)
            last_state = st.state
        elif not (args.quiet or quiet):
            dist = f"{st.distance_to_goal_m:6.2f} m" if st.distance_to_goal_m is not None else "   -   "
            print(f"   waypoint {st.active_waypoint + 1}/{st.total_waypoints}  distance {dist}  "
                  f"elapsed {st.elapsed_time_s:6.1f} s", flush=True)
        if st.state != "IDLE":
            flew = True
        elif not flew and "failed" in st.message:
            raise CliError(f"mission could not start: {st.message}")
        elif flew:
            done = "landed after the interruption" if interrupted else "4/4 done: landed"
            print(f"{done} and disarmed; states {' -> '.join(seen)}", flush=True)
            return 0
    raise CliError(f"mission did not finish within {args.timeout:.0f} s (last state {last_state})")
