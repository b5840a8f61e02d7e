"""Running rows on a stack: fly, inject, observe, judge by the truth, leave the stack on the ground
(restarted when a row broke it); and the figures table."""
from __future__ import annotations

import time

from aeroperception.schemas import DiagnosticStatus, GcsLink, Imu, MissionStatus, TrajectoryStatus, VehicleState
from aeroperception.tools.harness import FlightStack, poll_until

from .judging import RowResult, judge_safety, still_mps
from .row import Ctx, Row

RECORDED = dict(truth=("sim/truth/state", VehicleState), status=("mission/status", MissionStatus),
                state=("state/vehicle", VehicleState), fmu_diag=("diagnostics/fmu", DiagnosticStatus),
                gcs_link=("gcs/link", GcsLink), imu=("fmu/out/sensor_combined", Imu),
                planner=("planner/status", TrajectoryStatus))


def run_row(st: FlightStack, row: Row, mission_json: str, inject_after_s: float = 2.5) -> RowResult:
    """Fly, inject, observe, judge. Leaves the stack on the ground (restarted if it had to be)."""
    res = RowResult(row.name, row.injected, row.expected)
    t_start = time.monotonic()
    if st.sensors != row.sensors:
        st.sensors = row.sensors
        st.restart()
    elif not st.ensure_ground():
        st.restart()
    rec = st.capture(**RECORDED)
    ctx = Ctx(st, rec)
    t_unsafe = time.monotonic()
    try:
        row.prepare(ctx)
        why = _start(st, mission_json) if row.airborne else None
        if why:   # a previous row may have left the stack odd: once more on a fresh one
            _cleanup(row, ctx)
            rec.close()
            st.restart()
            rec = st.capture(**RECORDED)   # on the new stack's session
            ctx = Ctx(st, rec)
            row.prepare(ctx)
            why = _start(st, mission_json)
        if why:
            res.observed = f"could not start the mission: {why}"
        else:
            if row.airborne:   # mid-leg: past the first waypoint, above the take-off point (PX4 settles
                # into it for up to 7 s, where a row's 'progressing' would see a vehicle at rest)
                poll_until(lambda: getattr(ctx.rec.last("status"), "active_waypoint", 0) >= 1, 20.0, 0.1)
                time.sleep(inject_after_s)
            ctx.t_inject = time.monotonic()
            row.inject(ctx)
            res.passed, res.observed, res.detect_s = row.observe(ctx)
    except Exception as e:  # noqa: BLE001 - one broken row must not stop the table
        res.observed = f"harness error: {type(e).__name__}: {e}"
        res.passed = False
    finally:
        _cleanup(row, ctx)
        t_from = ctx.t_inject or t_unsafe
        track = rec.since("truth", t_from)
        if st.tap and (not track or track[-1][0] < time.monotonic() - 2.0):   # Zenoh gone: the FC's view
            track = st.tap.fc_track_since(t_from)
            res.details["safety_from"] = "FC LOCAL_POSITION_NED (no ground truth over Zenoh)"
        status = rec.last("status")
        res.safe, res.safe_why = judge_safety(track, st.tap.unsafe_since(t_unsafe) if st.tap else [], st.fence,
                                              status.state if status else "?", still_mps(st.profile))
        if "safety_from" in res.details:
            res.safe_why += " (by the FC's own position: no Zenoh)"
        rec.close()
    res.passed = bool(res.passed and res.safe)
    # A failed row leaves the stack in whatever state the fault made (a restarted service that lost
    # its state, a FC in LAND): the next row starts on a fresh stack.
    if row.breaks_stack or not res.passed or not st.ensure_ground():
        st.restart()
    res.duration_s = time.monotonic() - t_start
    return res


def _start(st: FlightStack, mission_json: str) -> str | None:
    """Fly the mission up to EXECUTING; None, else why not. A take-off the mission held on an fmu
    outage (a loaded machine starving it of state/vehicle > 0.5 s: no fault of the row's) is resumed
    with START, as an operator would, before the row's fault is injected."""
    why = st.start_mission(mission_json)
    if why and st.mission_state() == "HOLDING" and st.command("START").success:
        if poll_until(lambda: st.mission_state() == "EXECUTING", 20.0, 0.2):
            return None
    return why


def _cleanup(row: Row, ctx: Ctx) -> None:
    try:
        row.cleanup(ctx)
    except Exception:  # noqa: BLE001 - the stack restarts after a row that cannot clean up
        pass


def format_table(results: list[RowResult]) -> str:
    head = ["row", "injected", "expected outcome", "observed", "detect/react s", "vehicle safe (truth)", "result"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        det = f"{r.detect_s:.2f}" if r.detect_s is not None else "-"
        safe = ("yes" if r.safe else "NO") + (f": {r.safe_why}" if r.safe_why else "")
        lines.append("| " + " | ".join([r.row, r.injected, r.expected, r.observed, det, safe, r.verdict]) + " |")
    return "\n".join(lines)


