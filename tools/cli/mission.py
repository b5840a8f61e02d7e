"""`aero mission fly|load|command|status`: fly a mission file from the shell.

`fly` reads like a pre-flight checklist: load, arm, take off, start, then show progress
(waypoint i/n 1-based, distance, state; "landing") until the vehicle itself (state/vehicle)
is on the ground and disarmed: never judged from the mission FSM's label, which a restarted
mission service resets. Ctrl-C sends HOLD, then LAND, and waits for the landing.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import msgspec
import zenoh

from aeroperception.schemas import (
    LandedState, LoadMissionReply, LoadMissionRequest, MissionCommand, MissionStatus, MissionTrajectory, ParamList,
    Reply, SchemaError, TrajectoryStatus, VehicleState, WaypointReached, decode, load_mission_file, parse_mission,
)
from aeroperception.schemas.mission import TRAJECTORY_GENERATORS

from .topic import call_or_fail
from aeroperception.tools.common import CliError, add_session_arguments, full_key, open_client


def register(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("mission", help="load and fly missions, send mission commands")
    msub = m.add_subparsers(dest="mission_cmd", required=True)
    p = msub.add_parser("fly", help="load FILE, arm, take off, fly it, land; Ctrl-C = HOLD then LAND")
    add_session_arguments(p)
    p.add_argument("file", help="mission file, JSON or YAML, e.g. examples/missions/survey_01.json")
    p.add_argument("--timeout", type=float, default=600.0, help="give up after this many seconds")
    p.add_argument("--quiet", action="store_true", help="only print state changes")
    _trajectory_argument(p)
    p.set_defaults(func=fly)
    p = msub.add_parser("load", help="validate and load a mission file (JSON or YAML)")
    add_session_arguments(p)
    p.add_argument("file")
    _trajectory_argument(p)
    p.set_defaults(func=load)
    p = msub.add_parser("command", help="ARM, DISARM, TAKEOFF, START, HOLD, LAND or RTL")
    add_session_arguments(p)
    p.add_argument("command", type=str.upper, choices=["ARM", "DISARM", "TAKEOFF", "START", "HOLD", "LAND", "RTL"])
    p.set_defaults(func=command)


def _trajectory_argument(p) -> None:
    p.add_argument("--trajectory", choices=TRAJECTORY_GENERATORS, default=None, metavar="NAME",
                   help="how to fly the waypoints this time: waypoint (goal by goal) or smooth (one jerk-limited "
                        "trajectory); default: the file's trajectory section, else the mission service's parameter")


def _read(path: str, trajectory: str | None = None) -> str:
    """The file's text, validated locally first (the error names the file and the field); the
    service parses it again, JSON or YAML alike. `trajectory` replaces the file's generator."""
    p = Path(path)
    if not p.is_file():
        raise CliError(f"{p}: no such file")
    try:
        mission = load_mission_file(p)
    except SchemaError as e:
        raise CliError(f"{p}: {e}") from None
    if trajectory is not None:   # this flight's generator; the file's limits stay
        spec = mission.trajectory or MissionTrajectory()
        mission.trajectory = msgspec.structs.replace(spec, generator=trajectory)
        return mission.to_json()
    return p.read_text()


def check_limits(session, args, text: str) -> None:
    """A mission file's trajectory limits above the planner's own are refused before loading,
    naming the field (the planner would refuse the trajectory in the air: the vehicle would hold)."""
    spec = parse_mission(text).trajectory
    given = spec.given() if spec is not None else {}
    if not given:
        return
    plist = call_or_fail(session, full_key(args, "config/planner/@params"), None, ParamList)
    own = {p.name: p.value for p in plist.params}
    for name, value in given.items():
        if name in own and value > own[name]:
            raise CliError(f"mission rejected: trajectory.{name} {value:g} is above the planner's {name} {own[name]:g} "
                           f"(lower it, or `aero param set planner {name} ...`)")


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
    text = _read(args.file, args.trajectory)
    session = open_client(args)
    try:
        check_limits(session, args, text)
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


class Progress:
    """What `fly` knows, from four subscriptions: mission/status (the FSM), state/vehicle (the
    vehicle itself: "landed" is judged from it, never from the FSM label, which a restarted
    mission service resets), mission/waypoint_reached (so a waypoint passed between two 2 Hz
    status samples is still shown) and planner/status (progress along the trajectory or leg,
    time left)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.changed = threading.Event()
        self.status: MissionStatus | None = None
        self.vehicle: VehicleState | None = None
        self.reached: list[WaypointReached] = []
        self.planner: TrajectoryStatus | None = None

    def subscribe(self, session, args) -> list:
        def sub(key, cls, store):
            def on_sample(s: zenoh.Sample) -> None:
                try:
                    msg = decode(s.payload.to_bytes(), cls)
                except SchemaError:
                    return
                with self.lock:
                    store(msg)
                self.changed.set()
            return session.declare_subscriber(full_key(args, key), on_sample)
        return [sub("mission/status", MissionStatus, lambda m: setattr(self, "status", m)),
                sub("state/vehicle", VehicleState, lambda m: setattr(self, "vehicle", m)),
                sub("mission/waypoint_reached", WaypointReached, self.reached.append),
                sub("planner/status", TrajectoryStatus, lambda m: setattr(self, "planner", m))]

    def on_ground_disarmed(self) -> bool:
        v = self.vehicle
        return v is not None and v.connected and not v.armed and v.landed_state == LandedState.ON_GROUND


def planner_part(planner: TrajectoryStatus | None) -> str:
    """The planner's progress: along the trajectory it flies (its id), or along the leg to the
    current goal (goal by goal), and the time it says is left."""
    if planner is None or planner.status != TrajectoryStatus.STATUS_EXECUTING:
        return ""
    what = "leg" if planner.trajectory_id.startswith("goal-") else "trajectory"
    return f"  {what} {planner.progress_percent:3.0f} % ({planner.remaining_time_s:5.1f} s left)"


def progress_line(st: MissionStatus, vehicle: VehicleState | None = None,
                  planner: TrajectoryStatus | None = None) -> str | None:
    """One progress line for the mission's state, waypoints 1-based (1/4 .. 4/4), None in IDLE."""
    alt = f"  altitude {vehicle.position_m.z:5.2f} m" if vehicle is not None else ""
    if st.state == MissionStatus.STATE_EXECUTING and 0 <= st.active_waypoint < st.total_waypoints:
        dist = f"{st.distance_to_goal_m:6.2f} m" if st.distance_to_goal_m is not None else "   -   "
        return (f"waypoint {st.active_waypoint + 1}/{st.total_waypoints}  distance {dist}  "
                f"elapsed {st.elapsed_time_s:6.1f} s{planner_part(planner)}")
    if st.state == MissionStatus.STATE_EXECUTING:
        return f"going to the goal  distance {st.distance_to_goal_m or 0.0:6.2f} m{planner_part(planner)}"
    if st.state == MissionStatus.STATE_LAND:
        return f"landing{alt}"
    if st.state == MissionStatus.STATE_TAKEOFF:
        return f"taking off{alt}"
    if st.state == MissionStatus.STATE_HOLDING:
        return f"holding{alt}: {st.message}"
    return None


def reached_line(ev: WaypointReached, total: int) -> str:
    return f"reached waypoint {ev.index + 1}/{total}"


def fly(args) -> int:
    text = _read(args.file, args.trajectory)
    session = open_client(args)
    prog = Progress()
    subs = prog.subscribe(session, args)
    try:
        check_limits(session, args, text)
        r = _load(session, args, text)
        total = r.num_waypoints
        print(f"1/4 loaded: {r.message}", flush=True)
        print("2/4 takeoff: arming and climbing", flush=True)
        _command(session, args, "TAKEOFF")
        print("3/4 start: mission starts when takeoff altitude is reached", flush=True)
        _command(session, args, "START")
        return _follow(args, prog, total)
    except KeyboardInterrupt:
        print("\ninterrupted: HOLD, then LAND", flush=True)
        for cmd in ("HOLD", "LAND"):
            try:
                _command(session, args, cmd)
            except CliError as e:
                print(f"  {cmd}: {e}", file=sys.stderr)
        _follow(args, prog, 0, quiet=True, interrupted=True)
        return 130
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()


def _follow(args, prog: Progress, total: int, quiet: bool = False, interrupted: bool = False) -> int:
    """Print progress until the vehicle itself is on the ground and disarmed after having flown
    (state/vehicle, not the FSM label). After an interruption the vehicle only has to be down."""
    deadline = time.monotonic() + args.timeout
    flew = interrupted
    last_state = None
    seen: list[str] = []
    shown_reached = len(prog.reached)
    last_line_s = 0.0
    while time.monotonic() < deadline:
        prog.changed.wait(0.5)
        prog.changed.clear()
        with prog.lock:
            st, vehicle, reached, planner = prog.status, prog.vehicle, list(prog.reached), prog.planner
            down = prog.on_ground_disarmed()
        for ev in reached[shown_reached:]:
            print(f"   {reached_line(ev, total or (st.total_waypoints if st else 0))}", flush=True)
        shown_reached = len(reached)
        if vehicle is not None and vehicle.armed:
            flew = True
        if st is not None and st.state != last_state:
            seen.append(st.state)
            print(f"   state {st.state}: {st.message}", flush=True)
            last_state = st.state
        elif st is not None and not (args.quiet or quiet) and time.monotonic() - last_line_s >= 1.0:
            line = progress_line(st, vehicle, planner)
            if line:
                print(f"   {line}", flush=True)
                last_line_s = time.monotonic()
        if st is not None and st.state == "IDLE" and not flew and "failed" in st.message:
            raise CliError(f"mission could not start: {st.message}")
        if flew and down and not interrupted and set(seen) <= {MissionStatus.STATE_IDLE}:
            # Armed and disarmed again while the FSM never left IDLE: the FC's pre-flight auto-disarm
            # after a TAKEOFF the mission never acted on (seen across a router link) — not a flight.
            raise CliError(f"the vehicle armed and disarmed on the ground but the mission never left IDLE "
                           f"({st.message if st else 'no mission/status'}): check `aero topic echo mission/status`")
        if flew and down:
            n = len({ev.index for ev in reached})
            done = "landed after the interruption" if interrupted else \
                f"{n}/{total or (st.total_waypoints if st else n)} done: landed"
            print(f"{done} and disarmed (vehicle on the ground); states {' -> '.join(seen)}", flush=True)
            return 0
    where = "no vehicle state" if prog.vehicle is None else (
        f"vehicle {'armed' if prog.vehicle.armed else 'disarmed'}, {LandedState.name(prog.vehicle.landed_state)}")
    raise CliError(f"mission did not finish within {args.timeout:.0f} s (last state {last_state}, {where})")
