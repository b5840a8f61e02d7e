"""The fault table: one `Row` per fault (kill -9 of each service, router kill, FC link cut, ground-station
loss, SIGSTOP hangs, clock jump, FC reboot, LiDAR loss), each with how it is injected, what the
stack must do (its expected outcome) and how that is observed."""
from __future__ import annotations

import math
import os
import signal
import time

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import Clock, DiagnosticStatus, GcsLink, Header, encode
from aeroperception.services.runtime.node import encoding_for
from aeroperception.services.runtime.session import make_config, open_session
from aeroperception.tools.harness import poll_until, speed, token_alive
from aeroperception.tools.harness.mavlink_tap import LOCAL_POSITION_NED

from .ground_station import FakeGcs
from .judging import still_mps
from .row import Ctx, Row, first_hold, flies_on, held_after, kill, mission_states, pause, restarted, resume

OFFBOARD_LOSS_S = 1.0    # COM_OF_LOSS_T: PX4's default (the stack leaves it) and the built-in sim's
# How late after the last setpoint the judge may see the FC's offboard-loss failsafe. PX4 declares the
# offboard signal lost COM_OF_LOSS_T after the last setpoint (its OffboardChecks) and its commander's
# mode fallback (RTL, there being no RC) is neither deferred nor delayed by COM_FAIL_ACT_T (that Hold
# delay is only for failsafes whose user takeover is 'Auto'); but PX4 tells its mode only in its 1 Hz
# HEARTBEAT, so the judge (SIH truth, PX4's heartbeat) sees the switch up to one period later. The
# built-in sim's truth carries its mode at once. Both + 0.5 s of scheduling on a loaded machine.
FAILSAFE_SEEN_S = {"sim": OFFBOARD_LOSS_S + 0.5, "px4": OFFBOARD_LOSS_S + 1.0 + 0.5}


def kill_row(name: str) -> Row:
    def observe(ctx: Ctx):
        back = restarted(ctx, name)
        if back is None:
            return False, f"{name} not restarted within 20 s", None
        if name == "mission":
            return _observe_mission_restart(ctx, back)
        if name in ("fmu", "planner"):
            return _observe_outage(ctx, name, back)
        flying = flies_on(ctx)
        states = mission_states(ctx, ctx.t_inject)
        ok = flying and "HOLDING" not in states
        held = next((m.message for _, m in ctx.rec.since("status", ctx.t_inject) if m.state == "HOLDING"), "")
        return ok, (f"restarted in {back:.1f} s; mission {'->'.join(states)}{f' ({held})' if held else ''}"
                    f"{'' if flying else ', not progressing'}"), back

    expected = {
        "fmu": "FC offboard-loss failsafe meanwhile; fmu restarted; then the vehicle holds until the mission "
               "re-checks it (mission HOLDING, survey not resumed by itself)",
        "planner": "fmu holds at once (liveliness); planner restarted; vehicle holds until the mission re-checks "
                   "(mission HOLDING), never EXECUTING with the vehicle frozen",
        "mission": "mission restarted, rebuilt from the vehicle (not IDLE in the air), accepts LAND; lands+disarms",
    }.get(name, "restarted by aero up; the mission flies on unaffected (no HOLD, no false link verdict)")
    return Row(f"kill_{name}", f"kill -9 {name}", expected, lambda c: kill(c, name), observe)


def _observe_outage(ctx: Ctx, name: str, back: float):
    """After fmu/planner came back: the vehicle must hold, the mission must not carry on by itself."""
    hold = first_hold(ctx, ctx.t_inject) if name == "planner" else None
    ok, obs = held_after(ctx)
    obs = f"restarted in {back:.1f} s; " + obs
    if hold is not None:
        obs = f"fmu hold after {hold:.2f} s; " + obs
    return ok, obs, hold if hold is not None else back


def _observe_mission_restart(ctx: Ctx, back: float):
    time.sleep(2.0)
    t = ctx.rec.last("truth")
    state = ctx.rec.last("status").state if ctx.rec.last("status") else "?"
    airborne = t is not None and t.position_m.z > 1.0
    r = ctx.st.command("LAND")
    landed = r.success and poll_until(ctx.st.landed, 40.0, 0.5)
    ok = airborne and state != "IDLE" and bool(landed)
    return ok, (f"restarted in {back:.1f} s as {state} at {t.position_m.z if t else float('nan'):.1f} m; "
                f"LAND {'accepted' if r.success else 'refused: ' + r.message[:60]}; "
                f"{'landed+disarmed' if landed else 'not landed'}"), back


def _router_kill(ctx: Ctx) -> None:
    """The router: its own process if aero up runs one as a child (<log-dir>/router.pid), else
    the `aero up` process that hosts it."""
    try:
        pid = int((ctx.st.run_dir / "router.pid").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        pid = ctx.st.proc.pid
    ctx.notes["router_pid"] = pid
    ctx.notes["in_supervisor"] = pid == ctx.st.proc.pid
    os.kill(pid, signal.SIGKILL)


def _router_observe(links: str):
    """Router links: an outage, the mission must hold. Direct links (`aero up`'s default): the
    services on the host never lose each other, so the mission flies on, never holding."""

    def observe(ctx: Ctx):
        st = ctx.st

        def reconnected() -> bool:
            s = open_session(make_config(None, st.endpoint, mode="client"), max_wait_s=0.5)
            if s is None:
                return False
            try:
                return all(token_alive(s, n, timeout_s=0.5) for n in st.services)
            finally:
                s.close()

        back = poll_until(reconnected, 25.0, 0.5)
        react = time.monotonic() - ctx.t_inject if back else None
        where = "aero up (router inside it)" if ctx.notes["in_supervisor"] else "router process"
        if not back:
            return False, f"killed {where}; router/services not back within 25 s", None
        head = f"killed {where}; router and every service back in {react:.1f} s; "
        if links == "direct":
            moving = flies_on(ctx, 2.0)
            states = mission_states(ctx, ctx.t_inject)
            ok = moving and "HOLDING" not in states
            return ok, head + f"mission {'->'.join(states)}{'' if moving else ', not progressing'}", react
        held, obs = held_after(ctx)   # the mission re-checks after the outage: no flying on to an old goal
        return held, head + obs, react

    return observe


def _link_cut(ctx: Ctx) -> None:
    ctx.st.tap.cut.set()
    time.sleep(3.0)
    ctx.st.tap.cut.clear()
    ctx.notes["restored"] = time.monotonic()


def _link_observe(ctx: Ctx):
    t0 = ctx.t_inject
    lost = [t for t, m in ctx.rec.since("state", t0) if not m.connected]
    errs = [t for t, m in ctx.rec.since("fmu_diag", t0) if m.level >= DiagnosticStatus.ERROR]
    detect = min(lost[:1] + errs[:1]) - t0 if lost or errs else None
    held, obs = held_after(ctx)
    ok = detect is not None and detect <= 0.6 and held
    return ok, (f"link lost reported after {detect:.2f} s" if detect is not None
                else "link loss never reported") + "; " + obs, detect


def _gcs_prepare(ctx: Ctx) -> None:
    ctx.notes["gcs"] = FakeGcs(ctx.st.gcs_port)
    ok = ctx.st.latest("gcs/link", GcsLink, 8.0, lambda m: m.connected)
    ctx.notes["gcs_up"] = ok is not None


def _gcs_observe(ctx: Ctx):
    if not ctx.notes.get("gcs_up"):
        return False, "gcs/link never reported the fake ground station", None
    t0 = ctx.t_inject
    down = poll_until(lambda: [t for t, m in ctx.rec.since("gcs_link", t0) if not m.connected], 8.0, 0.05)
    hold = poll_until(lambda: [t for t, m in ctx.rec.since("status", t0) if m.state == "HOLDING"], 3.0, 0.05)
    time.sleep(4.0)  # braking into the hold
    states = mission_states(ctx, t0)
    detect = down[0] - t0 if down else None
    ok = bool(down) and bool(hold)
    obs = (f"gcs/link down after {detect:.1f} s" if down else "gcs/link never down") + \
          f"; mission {'->'.join(states)}" + (f" (HOLD {hold[0] - t0:.1f} s after)" if hold else "")
    return ok, obs, (hold[0] - t0) if hold else detect


def _hang_planner_observe(ctx: Ctx):
    t0 = ctx.t_inject
    hold = first_hold(ctx, t0)
    track = [m for t, m in ctx.rec.since("truth", t0) if t <= ctx.notes["resumed"]]
    if len(track) < 10:
        return False, "no truth during the hang", hold
    p = np.array([m.position_m.to_array() for m in track])
    v0 = track[0].velocity_mps.to_array()
    d = v0 / (np.linalg.norm(v0) or 1.0)
    along = (p - p[0]) @ d
    overshoot, flyback = float(along.max()), float(along.max() - along[-1])
    rest = speed(track[-1]) < still_mps(ctx.st.profile)
    back = poll_until(lambda: "streaming" in ctx.st.latest_diag("fmu").values.get("planner", ""), 5.0, 0.2)
    ok = hold is not None and hold <= 0.4 and rest and flyback < 0.3 and bool(back)
    obs = (f"fmu hold after {hold:.2f} s" if hold is not None else "no hold setpoint") + \
          (f"; stopped {overshoot:.2f} m on, flew back {flyback:.2f} m; "
           f"{'at rest' if rest else f'{speed(track[-1]):.1f} m/s'} at SIGCONT; "
           f"planner {'streaming again' if back else 'not back'}")
    return ok, obs, hold


def _hang_fmu_observe(fc: str):
    def observe(ctx: Ctx):
        t0 = ctx.t_inject
        fs = [t for t, m in ctx.rec.since("truth", t0) if m.flight_mode != "OFFBOARD"]
        react = fs[0] - t0 if fs else None
        held, obs = held_after(ctx)
        ok = react is not None and react <= FAILSAFE_SEEN_S[fc] and held
        return ok, (f"FC failsafe after {react:.2f} s" if react is not None else "no FC failsafe") + "; " + obs, react
    return observe


def _clock_jump(ctx: Ctx) -> None:
    """Rogue sim/clock ticks 1 h ahead for 1 s, then 1 h behind for 1 s (100 Hz each)."""
    pub = ctx.st.session.declare_publisher("sim/clock", encoding=encoding_for(Clock))
    try:
        for offset_s in (3600.0, -3600.0):
            for _ in range(100):
                pub.put(encode(Clock(header=Header(stamp_ns=time.time_ns() + int(offset_s * 1e9)), speed_factor=1.0)))
                time.sleep(0.01)
    finally:
        pub.undeclare()


def _clock_observe(ctx: Ctx):
    t0 = ctx.t_inject
    holds0 = ctx.notes.get("holds0", 0)
    stamps = [t for t, _ in ctx.rec.since("state", t0)]
    gaps = np.diff(stamps) if len(stamps) > 1 else np.array([math.inf])
    moving = flies_on(ctx, 2.0)
    holds = int(ctx.st.latest_diag("fmu").values.get("holds_sent", 0)) - holds0
    ok = moving and float(gaps.max()) < 0.2 and holds <= 0
    return ok, (f"state/vehicle max gap {gaps.max() * 1e3:.0f} ms; fmu holds +{holds}; mission "
                f"{'->'.join(mission_states(ctx, t0))}{'' if moving else ', not progressing'}"), None


def _clock_prepare(ctx: Ctx) -> None:
    ctx.notes["holds0"] = int(ctx.st.latest_diag("fmu").values.get("holds_sent", 0))


def _reboot(ctx: Ctx) -> None:
    """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN to the FC, then PX4's default stream rates (the sim keeps
    its rates across a reboot; real PX4 comes back with LOCAL_POSITION_NED at 30 Hz, HIGHRES_IMU 50)."""
    tap, enc = ctx.st.tap, ctx.st.tap.enc
    ctx.notes["rate_before"] = tap.rate_hz(LOCAL_POSITION_NED, time.monotonic() - 3.0, time.monotonic())
    tap.to_fc(enc.command_long_encode(1, 1, mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 1, 0, 0, 0, 0, 0, 0))
    time.sleep(0.2)
    for mid, hz in ((LOCAL_POSITION_NED, 30.0), (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 30.0),
                    (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 50.0)):
        tap.to_fc(enc.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mid, 1e6 / hz, 0, 0, 0, 0, 0))


def _reboot_observe(ctx: Ctx):
    t0 = ctx.t_inject
    tap = ctx.st.tap
    rebooted = poll_until(lambda: [a for a in tap.acks if a[0] >= t0 and a[1] == mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN
                                   and a[2] == mavlink.MAV_RESULT_ACCEPTED], 5.0, 0.1)
    back = poll_until(lambda: tap.rate_hz(LOCAL_POSITION_NED, time.monotonic() - 1.0, time.monotonic()) >= 45.0
                      and time.monotonic() - t0 > 1.5, 10.0, 0.1)
    react = time.monotonic() - t0 if back else None
    t1 = time.monotonic()
    time.sleep(3.0)
    n_state = len(ctx.rec.since("state", t1)) / 3.0
    n_imu = len(ctx.rec.since("imu", t1)) / 3.0
    ok = bool(rebooted) and n_state >= 45.0 and n_imu >= 90.0
    obs = (f"{'rebooted' if rebooted else 'no reboot seen'}; state/vehicle {ctx.notes['rate_before']:.0f} -> "
           f"{n_state:.0f} Hz, fmu/out/sensor_combined {n_imu:.0f} Hz after")
    return ok, obs, react


def _lidar_observe(ctx: Ctx):
    """kill -9 lidar mid-flight: the costmap stops; the planner must not fly on blind. It holds
    (zero horizontal velocity at the FC, planner/status stale_costmap) within costmap_timeout_s,
    and once aero up has restarted lidar and a fresh costmap arrives the mission flies on."""
    t0 = ctx.t_inject
    stale = poll_until(lambda: next((t for t, m in ctx.rec.since("planner", t0) if m.obstacle_state == "stale_costmap"),
                                    None), 5.0)
    back = restarted(ctx, "lidar", 30.0)
    with ctx.st.tap.lock:
        sps = [(t, m) for t, m in ctx.st.tap.setpoints if t >= t0]
    hold = next((t - t0 for t, m in sps if not m.type_mask & mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
                 and m.vx == 0.0 and m.vy == 0.0), None)
    if back is None:
        return False, "lidar not restarted within 30 s", hold
    fresh = poll_until(lambda: any(t > t0 + back and m.obstacle_state != "stale_costmap"
                                   for t, m in ctx.rec.since("planner", t0)), 20.0)
    flying = flies_on(ctx)
    states = mission_states(ctx, t0)
    # While lidar was down, the vehicle slowed to a stop or was stopping (not cruising on).
    down = [m for t, m in ctx.rec.since("truth", t0 + (stale - t0 if stale else 0) + 2.0) if t < t0 + back]
    cruising = any(speed(m) > 1.0 for m in down)
    ok = bool(stale and hold is not None and hold < 1.0 and fresh and flying and not cruising)
    detail = (f"planner stale_costmap after {stale - t0:.2f} s, " if stale else "no stale_costmap verdict, ") + \
        (f"FC zero horizontal velocity after {hold:.2f} s; " if hold is not None else "never a zero-velocity setpoint; ")
    return ok, (detail + f"lidar restarted in {back:.1f} s; costmap {'fresh again' if fresh else 'NOT back'}; "
                f"{'cruised on blind; ' if cruising else ''}mission {'->'.join(states)}"
                f"{'' if flying else ', not progressing'}"), hold


def _pilot_hold(ctx: Ctx) -> None:
    ctx.st.px4_shell("commander", "mode", "auto:loiter")


def _pilot_hold_observe(ctx: Ctx):
    """A pilot switched PX4 to HOLD: the mission holds saying why, the vehicle stays put (truth).
    Timed from PX4's own HEARTBEAT reporting HOLD (the shell command's start-up is not the stack's)."""
    t0 = ctx.t_inject
    fc_hold = poll_until(lambda: next((t for t, m in ctx.rec.since("truth", t0) if m.flight_mode == "HOLD"), None),
                         5.0, 0.05)
    hold = poll_until(lambda: next(((t, m) for t, m in ctx.rec.since("status", t0)
                                    if m.state == "HOLDING" and "switched to HOLD" in m.message), None), 5.0, 0.05)
    time.sleep(4.0)                      # PX4 brakes to its hold point
    t1 = time.monotonic()
    time.sleep(3.0)
    track = [m for _, m in ctx.rec.since("truth", t1)]
    drift = float(np.linalg.norm(track[-1].position_m.to_array() - track[0].position_m.to_array())) if track else math.inf
    states = mission_states(ctx, t0)
    react = hold[0] - fc_hold if hold and fc_hold else None
    ok = react is not None and react <= 1.0 and drift < 1.0 and states[-1:] == ["HOLDING"]
    return ok, ((f"mission HOLDING {react:.2f} s after PX4 reported HOLD ({hold[1].message[:60]})" if react is not None
                 else "PX4 never reported HOLD" if fc_hold is None else "mission never HOLDING for the pilot's switch")
                + f"; moved {drift:.2f} m in 3 s while held; mission {'->'.join(states)}"), react


def _setpoints_stop(ctx: Ctx) -> None:
    """PX4 hears no setpoints for 3 s (the companion -> FC direction only): its offboard-loss failsafe."""
    ctx.st.tap.cut_to_fc.set()
    time.sleep(3.0)
    ctx.st.tap.cut_to_fc.clear()


def _failsafe_rtl_observe(ctx: Ctx):
    """PX4 fails safe to RTL on its own; the mission holds its plan; once setpoints reach PX4 again
    PX4 returns to OFFBOARD by itself (its failsafe clears with the condition) and the vehicle is
    held where it is then (the planner retakes its hold while PX4 flies RTL), never flown back or on."""
    t0 = ctx.t_inject
    rtl = next((t for t, m in ctx.rec.since("truth", t0) if m.flight_mode == "RTL"), None)
    held, obs = held_after(ctx)
    react = rtl - t0 if rtl is not None else None
    ok = react is not None and react <= FAILSAFE_SEEN_S["px4"] and held
    return ok, (f"PX4 RTL after {react:.2f} s" if react is not None else "PX4 never in RTL") + "; " + obs, react


def _gps_failure(ctx: Ctx) -> None:
    """SIH's GPS receiver sees no satellites from now on (SIM_GPS_USED 0: fix type 0, PX4's
    sensor_gps_sim reads it on every parameter update). Not `failure gps off`: in this PX4 only
    simulator_mavlink (Gazebo Classic) handles that command; under SIH nobody acks it."""
    ctx.st.px4_shell("param", "set", "SIM_GPS_USED", "0")


def _gps_failure_observe(ctx: Ctx):
    """GPS lost on PX4: EKF2 dead-reckons, then PX4's position-loss failsafe takes over; the
    mission stops flying its plan; the vehicle comes down without an impact (truth)."""
    t0 = ctx.t_inject
    left = poll_until(lambda: next((t for t, m in ctx.rec.since("truth", t0) if m.flight_mode != "OFFBOARD"), None),
                      30.0, 0.2)
    down = poll_until(ctx.st.landed, 60.0, 1.0)
    modes = [m.flight_mode for _, m in ctx.rec.since("truth", t0)]
    modes = [x for k, x in enumerate(modes) if k == 0 or x != modes[k - 1]]
    states = mission_states(ctx, t0)
    react = left - t0 if left is not None else None
    ok = react is not None and bool(down) and "EXECUTING" not in states[1:]
    return ok, ((f"PX4 left OFFBOARD after {react:.1f} s" if react is not None else "PX4 stayed in OFFBOARD")
                + f"; PX4 modes {'->'.join(modes)}; mission {'->'.join(states)}; "
                + ("landed+disarmed" if down else "not landed within 60 s")), react


SIM_ONLY = ("clock_jump", "fc_reboot")   # sim/clock and the sim's reboot: no such knob on PX4


def px4_rows() -> list[Row]:
    """Faults only a real PX4 answers: a pilot's mode switch, its own failsafes, its failure injection."""
    return [
        Row("pilot_hold", "a pilot switches PX4 to HOLD (commander mode auto:loiter)",
            "mission HOLDING within 1 s of PX4 reporting HOLD, naming the switch; the vehicle stays put (< 1 m in 3 s, truth); "
            "no waypoint flown until START",
            _pilot_hold, _pilot_hold_observe),
        Row("failsafe_rtl", "PX4 hears no setpoints for 3 s (companion -> FC cut)",
            f"PX4's offboard-loss failsafe RTL seen within {FAILSAFE_SEEN_S['px4']:g} s (COM_OF_LOSS_T + its 1 Hz "
            "heartbeat); the mission HOLDING; once setpoints arrive again PX4 takes OFFBOARD back by itself and "
            "the vehicle is held where it is, never flown back or on the mission",
            _setpoints_stop, _failsafe_rtl_observe, cleanup=lambda c: c.st.tap.cut_to_fc.clear()),
        Row("gps_failure", "SIH's GPS sees no satellites (param SIM_GPS_USED 0)",
            "PX4's estimator loses position and its failsafe lands; the mission stops flying its plan; "
            "landed and disarmed, no impact (truth)",
            _gps_failure, _gps_failure_observe, breaks_stack=True),   # a fresh PX4 has its GPS back
    ]


def _safety_row_if_present(services: list[str]) -> list[str]:
    return [s for s in ("fmu", "planner", "mission", "gcs", "diagnostics", "safety") if s in services]


def build_rows(services: list[str], fc: str = "sim", links: str = "direct") -> dict[str, Row]:
    """The rows for a stack of `services` whose flight controller is `fc`: the built-in "sim" or
    "px4" (SITL; rows of the built-in sim's own knobs - clock, reboot, LiDAR - left out), started
    by `aero up` with `links` (`--links`) between them."""
    rows = [kill_row(s) for s in _safety_row_if_present(services)]
    seen_late = " + PX4's 1 Hz heartbeat" if fc == "px4" else ""
    rows += [
        Row("router_kill", "kill -9 the Zenoh router",
            "supervisor detects it and restarts the router; every service reachable through it again; "
            + ("the services' direct links never drop: the mission flies on, never HOLDING" if links == "direct" else
               "every service reconnects; vehicle holds meanwhile and after (mission HOLDING: an outage), never "
               "flies on to the goal it had before"),
            _router_kill, _router_observe(links), breaks_stack=True),
        Row("fc_link_loss", "FC MAVLink cut both ways for 3 s",
            "state/vehicle connected=false or diagnostics/fmu ERROR within 0.5 s; FC offboard-loss failsafe; "
            "mission HOLDING after, no resumption by itself",
            _link_cut, _link_observe, cleanup=lambda c: c.st.tap.cut.clear()),
        Row("gcs_loss", "MAV_TYPE_GCS heartbeats to gcs, then silence",
            "gcs/link connected=false after gcs_timeout_s (3.5 s); mission HOLDING (link-loss policy)",
            lambda c: c.notes["gcs"].stop(), _gcs_observe, prepare=_gcs_prepare,
            cleanup=lambda c: c.notes.get("gcs") and c.notes["gcs"].stop()),
        Row("hang_planner", "SIGSTOP planner 3 s, SIGCONT",
            "fmu brakes within 0.4 s (setpoint_timeout_s 0.3 + a tick), stops without flying back; "
            "planner streams again after SIGCONT",
            pause("planner", 3.0), _hang_planner_observe, cleanup=resume),
        Row("hang_fmu", "SIGSTOP fmu 3 s, SIGCONT",
            f"FC offboard-loss failsafe seen within {FAILSAFE_SEEN_S[fc]:g} s (COM_OF_LOSS_T{seen_late}); after SIGCONT the vehicle holds until the mission "
            "re-checks (mission HOLDING), never flies on in OFFBOARD by itself",
            pause("fmu", 3.0), _hang_fmu_observe(fc), cleanup=resume),
        Row("clock_jump", "rogue sim/clock +1 h then -1 h (1 s each)",
            "no decision changes: timeouts run on monotonic clocks; state/vehicle gaps < 200 ms; no fmu hold; "
            "mission flies on",
            _clock_jump, _clock_observe, prepare=_clock_prepare),
        Row("fc_reboot", "FC reboot on the ground (PX4 default rates after)",
            "fmu detects the reboot and re-requests its rates: state/vehicle >= 45 Hz, IMU >= 90 Hz",
            _reboot, _reboot_observe, airborne=False),
    ]
    if fc == "px4":
        return {r.name: r for r in rows if r.name not in SIM_ONLY} | {r.name: r for r in px4_rows()}
    if "lidar" in services:   # last: it needs a stack rendering the LiDAR (a restart to switch)
        rows.append(Row("kill_lidar", "kill -9 lidar mid-flight (LiDAR rendered)",
                        "planner holds within costmap_timeout_s (0.5 s) + a tick: stale_costmap, zero horizontal "
                        "velocity at the FC, never flies on blind; lidar restarted; the mission flies on once "
                        "the costmap is fresh",
                        lambda c: kill(c, "lidar"), _lidar_observe, sensors="lidar"))
    return {r.name: r for r in rows}


