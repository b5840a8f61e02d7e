"""The stack flying real PX4: `aero up --profile px4` runs PX4 SITL (SIH quadrotor, physics inside
PX4) from the `px4_build` fixture as a supervised process beside fmu, planner, mission and
diagnostics. One PX4 + stack serve the module (each test starts from the ground, disarmed).

What happened is judged by PX4: its position estimate (state/vehicle, what fmu reads from PX4's
LOCAL_POSITION_NED) and SIH's ground truth (HIL_STATE_QUATERNION on its display link, UDP
19410+N), never by the mission's own account.

- extended: survey_01 by `aero mission fly`: every waypoint reached (reports and PX4's track), landed
  and disarmed, landing error vs the take-off point (by default the hops of test_px4_gps_denied.py
  and test_px4_sensors.py fly PX4 to a waypoint and a landing, judged by SIH truth).
- a pilot switches PX4 to HOLD mid-mission (`px4-commander mode auto:loiter`): mission HOLDING
  with the reason, the vehicle stays put; START resumes the survey to its landing.
- fmu kill -9 mid-mission: the vehicle stays in the air near where it was (PX4's offboard-loss
  failsafe RTL, cleared into OFFBOARD again once the restarted fmu streams), held where PX4 gave
  OFFBOARD back (not flown back to where it was), the mission HOLDING until told; LAND lands it.
- PX4 supervised like a service: restarted after kill -9, stopped by SIGINT with the stack, and
  stopped by the kernel when `aero up` itself is killed -9.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from contextlib import contextmanager

import numpy as np
import pytest

from aerotest import Capture, SihTruth, aero_argv, clean_env, is_service_process, wait_until
from aeroperception.schemas import (
    MissionCommand, MissionStatus, Reply, TrajectoryStatus, VehicleState, WaypointReached, load_mission_file,
)
from aeroperception.services.runtime.node import call
from aeroperception.tools.cli import px4_sitl
from aeroperception.tools.eval.trajectory import TrajectoryEval
from aeroperception.tools.harness.px4_stack import SIH_DISPLAY_PORT, px4_command
from test_flight import SURVEY

pytestmark = [pytest.mark.px4, pytest.mark.slow]

SERVICES = ["px4", "fmu", "planner", "mission", "diagnostics"]


@contextmanager
def px4_up(stack_module, px4_build, services: list[str], extra_args: list[str], truth_cls=SihTruth):
    """PX4 SITL on a free instance with `services` (profile px4) and SIH's truth (`st.truth`), the
    truth receiver closed on the way out. Not waited for: a GPS-denied PX4 is ready only once it
    sees vision, which the caller starts first (then wait_px4_ready)."""
    instance = px4_sitl.free_instance(1)
    assert instance is not None, "no free PX4 instance in 1..9"
    truth = truth_cls(SIH_DISPLAY_PORT + instance)
    try:
        st = stack_module(services, profile="px4", timeout_s=60, extra_args=[
            "--px4", str(px4_build), "--px4-instance", str(instance), *extra_args])
        st.px4_instance, st.px4_bin, st.truth = instance, px4_build / "bin", truth
        yield st
    finally:
        truth.close()


@pytest.fixture(scope="module")
def px4(stack_module, px4_build, tmp_path_factory):
    state_dir = tmp_path_factory.mktemp("mission-state")
    with px4_up(stack_module, px4_build, SERVICES, ["--arg", f"mission:--param=state_dir={state_dir}"]) as st:
        wait_px4_ready(st)
        yield st


def fly_file(st, path, timeout_s: float, landed_s: float = 10.0) -> subprocess.CompletedProcess:
    """`aero mission fly PATH --quiet` against the PX4 stack, then PX4 on the ground and disarmed."""
    r = subprocess.run(aero_argv() + ["mission", "fly", str(path), "--quiet", "--timeout", f"{timeout_s:g}"],
                       env=clean_env(st.endpoint), capture_output=True, text=True, timeout=timeout_s + 20,
                       stdin=subprocess.DEVNULL)
    wait_until(lambda: st.landed(), landed_s, "on the ground, disarmed (PX4)")
    return r


def wait_px4_ready(st) -> None:
    """PX4 ready for takeoff, fmu connected to it, the mission up (the stack described on failure)."""
    try:
            wait_until(lambda: "Ready for takeoff" in st.service_log("px4"), 60, "PX4: Ready for takeoff")
            wait_until(lambda: state(st, lambda m: m.connected), 20, "state/vehicle connected (fmu <-> PX4)")
            wait_until(lambda: mission_status(st), 15, "mission/status")
    except BaseException:
        print(st.describe())
        raise


# ---------------------------------------------------------------- helpers


def state(st, pred=None) -> VehicleState | None:
    return st.latest("state/vehicle", VehicleState, 2.0, pred)


def mission_status(st, pred=None) -> MissionStatus | None:
    return st.latest("mission/status", MissionStatus, 2.0, pred)


def px4_shell(st, *args: str) -> str:
    """A PX4 shell command against the stack's instance (`bin/px4-commander --instance N mode ...`)."""
    return px4_command(st.px4_bin.parent, st.px4_instance, *args)


def start_survey(st) -> None:
    st.ensure_landed()
    text = SURVEY.read_text()
    r = call(st.session, "mission/srv/command", MissionCommand(command="LOAD", mission_json=text), Reply, 5.0)
    assert r.success, r.message
    for cmd in ("TAKEOFF", "START"):
        r = st.command(cmd)
        assert r.success, f"{cmd}: {r.message}"
    wait_until(lambda: mission_status(st, lambda m: m.state == "EXECUTING"), 40, "mission EXECUTING")


def kill9(st, name: str) -> int:
    pid = st.pids().get(name)
    assert pid is not None and is_service_process(pid, name), f"no running {name} in pids.json"
    os.kill(pid, signal.SIGKILL)
    return pid


# ---------------------------------------------------------------- supervision


def test_px4_is_supervised_like_a_service_restarted_stopped_and_gone_with_aero_up(stack, px4_build):
    instance = px4_sitl.free_instance(1)
    assert instance is not None, "no free PX4 instance in 1..9"
    args = ["--px4", str(px4_build), "--px4-instance", str(instance)]

    def px4_gone(pid: int) -> bool:
        return not os.path.exists(f"/proc/{pid}") and px4_sitl.lock_holder(instance) is None

    st = stack(["px4"], profile="px4", extra_args=args, timeout_s=30)   # waits for its token
    first = st.pids()["px4"]
    assert px4_sitl.lock_holder(instance) == first
    os.kill(first, signal.SIGKILL)                                      # PX4 crashes: aero up restarts it
    wait_until(lambda: st.pids().get("px4") not in (None, first), 10, "aero up restarted px4")
    wait_until(lambda: st.alive("px4"), 20, "the restarted PX4 booted (its token)")
    second = st.pids()["px4"]
    st.stop()                                                           # SIGINT to aero up: PX4 stops cleanly
    wait_until(lambda: px4_gone(second), 5, "PX4 stopped with the stack")
    assert "PX4 Exiting" in st.service_log("px4")

    st = stack(["px4"], profile="px4", extra_args=args, timeout_s=30)
    pid = st.pids()["px4"]
    st.proc.kill()                                                      # aero up killed -9: the kernel tells PX4
    wait_until(lambda: px4_gone(pid), 5, "PX4 stopped after aero up was killed -9")


# ---------------------------------------------------------------- (a) survey_01


@pytest.mark.extended   # ~47 s: by default PX4 flies missions by `aero mission fly` to their landing, the waypoint
#   and the landing judged by SIH truth, in test_px4_gps_denied.py's hop (on vision) and test_px4_sensors.py's
#   VIO hop; survey_01 itself is judged end to end in the sim by test_recorder.py; PX4's disarm into OFFBOARD
#   read as a landing: tests/unit/test_mission_fc_authority.py
def test_px4_flies_survey_01_to_landing_reaching_every_waypoint(px4):
    st = px4
    st.ensure_landed()
    pad = st.truth.now()
    home = state(st).position_m.to_array()
    rec = Capture(st.session, {"state": ("state/vehicle", VehicleState), "status": ("mission/status", MissionStatus),
                                "reached": ("mission/waypoint_reached", WaypointReached)})
    t0 = time.monotonic()
    try:
        r = fly_file(st, SURVEY, 150)
    finally:
        rec.close()
    flight_s = time.monotonic() - t0
    assert r.returncode == 0, r.stdout + r.stderr
    assert "landed and disarmed" in r.stdout, r.stdout
    # Disarmed, PX4 switches to the last mode it can arm in (OFFBOARD; LAND prevents arming) in the
    # disarm's own heartbeat: a landing to the mission, not a takeover (the sim does the same).
    wait_until(lambda: state(st, lambda m: m.flight_mode == "OFFBOARD" and not m.armed), 5, "PX4 in OFFBOARD, disarmed")
    s = mission_status(st)
    assert s.state == "IDLE" and s.message == "landed and disarmed", s
    waypoints = [np.array([w.x, w.y, w.z]) for w in load_mission_file(SURVEY).waypoints]
    reached = [m.index for m in rec.get("reached")]
    assert reached == list(range(len(waypoints))), f"waypoints reached {reached}"
    track = np.array([m.position_m.to_array() for m in rec.get("state")])
    closest = [float(np.min(np.linalg.norm(track - w, axis=1))) for w in waypoints]
    end = state(st).position_m.to_array()
    error_est = float(np.linalg.norm((end - home)[:2]))
    error_truth = float(np.linalg.norm((st.truth.now() - pad)[:2]))
    t_land = next(t for t, m in rec.since("status") if m.state == "LAND")
    at_land = next(m for t, m in rec.since("state", t_land))
    land_from = float(np.linalg.norm((at_land.position_m.to_array() - home)[:2]))
    land_speed = float(np.linalg.norm(at_land.velocity_mps.to_array()[:2]))
    print(f"PX4 survey_01: {flight_s:.1f} s; closest approach per waypoint (PX4 estimate) "
          f"{', '.join(f'{d:.2f}' for d in closest)} m; landing error vs take-off point "
          f"{error_est:.2f} m (PX4 estimate), {error_truth:.2f} m (SIH truth); LAND began {land_from:.2f} m "
          f"from it at {land_speed:.2f} m/s")
    assert max(closest) < 0.5 + 0.3, closest          # the survey's acceptance radius + tracking
    # LAND starts inside the 0.5 m acceptance radius of the last waypoint, at speed, and PX4 brakes and
    # lands about there: 0.3-2.0 m measured on a loaded machine; another waypoint would be >= 10 m.
    assert error_est < 2.5 and error_truth < 2.5, (error_est, error_truth)


@pytest.mark.extended   # one more survey (~45 s on PX4): the flight itself is covered as the survey above says
def test_px4_flies_survey_01_smooth_on_its_reference_and_its_legs(px4):
    """The smooth trajectory on PX4 with the px4 profile's feed-forward (drag_per_s, ff_lead_s,
    fc_xy_vel_d), speed governor (fc_xy_gain_per_s) and EKF2's IMU noise matched to SIH's (px4_sitl):
    without it the SIH quad trailed the reference 0.7 m (vs reference RMS 0.63-0.74 m, cross-track
    0.16-0.46 m by PX4's estimate, load 12-25); judged by PX4's estimate (how well the stack flies
    what it asks) and by SIH's truth (that plus EKF2's own error)."""
    st = px4
    st.ensure_landed()
    # SIH's truth about the pad, moved into PX4's local frame (the waypoints'): where EKF2 puts the pad
    offset = state(st).position_m.to_array() - st.truth.now()
    truth: list[tuple[float, np.ndarray, np.ndarray]] = []
    on_truth = lambda t, m: truth.append((t, m.position_m.to_array() + offset, m.velocity_mps.to_array()))  # noqa: E731
    st.truth.listeners.append(on_truth)
    rec = Capture(st.session, {"state": ("state/vehicle", VehicleState), "status": ("planner/status", TrajectoryStatus),
                                "reached": ("mission/waypoint_reached", WaypointReached)})
    try:
        r = subprocess.run(aero_argv() + ["mission", "fly", str(SURVEY), "--trajectory", "smooth", "--quiet",
                                          "--timeout", "150"], env=clean_env(st.endpoint), capture_output=True,
                           text=True, timeout=170, stdin=subprocess.DEVNULL)
        wait_until(lambda: st.landed(), 10, "on the ground, disarmed (PX4)")
    finally:
        rec.close()
        st.truth.listeners.remove(on_truth)
    assert r.returncode == 0, r.stdout + r.stderr
    waypoints = np.array([[w.x, w.y, w.z] for w in load_mission_file(SURVEY).waypoints], float)
    ev, by_truth = TrajectoryEval(waypoints), TrajectoryEval(waypoints)
    for t, m in rec.since("state"):
        ev.add_truth(t, m.position_m.to_array(), m.velocity_mps.to_array(), m.header.stamp_ns * 1e-9)
    for t, p, v in truth:
        by_truth.add_truth(t, p, v)
    for t, m in rec.since("reached"):
        ev.add_reached(m.index, t)
        by_truth.add_reached(m.index, t)
    for _, s in rec.since("status"):
        if s.status == TrajectoryStatus.STATUS_EXECUTING and s.trajectory_id.startswith("survey_01@"):
            ev.add_reference_error(s.position_error_m)
    res, real = ev.summary(), by_truth.summary()
    print(f"PX4 survey_01 smooth (PX4's estimate): {res}")
    print(f"PX4 survey_01 smooth (SIH's truth): {real}")
    # with the feed-forward, the governor, PX4's D term paid back and EKF2's IMU noise matched to SIH's
    # (load 5-11, 5 runs): vs reference 0.15-0.24 m (0.25-0.39 before the last two; without any feed-forward
    # 0.63-0.74), cross-track xy 0.10-0.17 m by the estimate, 0.11-0.22 m by the truth (0.24-0.26 before)
    assert res["reference_error_rms_m"] < 0.45, res
    assert res["cross_track_xy_rms_m"] < 0.25, res
    assert real["cross_track_xy_rms_m"] < 0.3, real
    assert res["time_s"] < 26.0, res                  # 22.2-22.7 s planned at 1.8 m/s (20.5-21.4 at 2.0)
    # PX4 flies feed-forward + MPC_XY_P x its position error: without the px4 profile's speed governor
    # (fc_xy_gain_per_s) it caught up after speeding up, commanding 2.57-2.70 m/s at the 2 m/s cap (ULog),
    # 2.20-2.41 by truth; governed it commands <= 2.09 (ULog). What was over the cap then is PX4's velocity
    # loop overshooting its setpoint and EKF2's velocity error (p95 0.20-0.30 m/s): peaks 2.06-2.28 by the
    # truth. The profile's fc_velocity_error_mps 0.2 plans 1.8: 3 surveys at load 4-9 peaked 1.89-1.93 m/s by
    # the estimate, 1.94-1.99 by the truth (22.2-22.7 s, cross-track xy 0.10-0.13 m by the truth)
    assert res["peak_xy_speed_mps"] < 2.0 * 1.1, res
    assert real["peak_xy_speed_mps"] < 2.0 * 1.1, real


# ---------------------------------------------------------------- (b) pilot HOLD -> resume


@pytest.mark.extended   # ~54 s: PX4's HOLD by a pilot is the default chaos row pilot_hold (tests/faults/test_chaos_px4.py),
#                         the mission's START resume after an FC HOLD is test_mission_faults' fc_switched_to_hold (default)
def test_px4_switched_to_hold_by_a_pilot_holds_the_mission_and_start_resumes(px4):
    st = px4
    start_survey(st)
    rec = Capture(st.session, {"reached": ("mission/waypoint_reached", WaypointReached)})
    try:
        wait_until(lambda: mission_status(st, lambda m: m.state == "EXECUTING" and m.active_waypoint == 1
                                          and (m.distance_to_goal_m or 0) > 4.0), 40, "flying to waypoint 1")
        px4_shell(st, "commander", "mode", "auto:loiter")
        t_pilot = time.monotonic()
        s = wait_until(lambda: mission_status(st, lambda m: m.state == "HOLDING"), 5, "mission HOLDING")
        print(f"mission HOLDING {time.monotonic() - t_pilot:.2f} s after `commander mode auto:loiter`: {s.message}")
        assert "flight controller switched to HOLD" in s.message, s.message
        wait_until(lambda: state(st, lambda m: m.flight_mode == "HOLD"), 3, "PX4 reports HOLD")
        held = st.truth.at_rest(10)            # PX4 brakes to its hold point
        n_reached = len(rec.get("reached"))
        time.sleep(3.0)
        drift = float(np.linalg.norm(st.truth.now() - held))
        print(f"while PX4 holds: moved {drift:.2f} m in 3 s (SIH truth)")
        # 0.26-0.79 m measured (PX4's position hold on its GPS/EKF2 estimate); flying on would be > 5 m
        assert drift < 1.0, f"vehicle moved {drift:.2f} m while HOLDING"
        assert len(rec.get("reached")) == n_reached and mission_status(st).state == "HOLDING"

        r = st.command("START")
        assert r.success, r.message
        wait_until(lambda: state(st, lambda m: m.flight_mode == "OFFBOARD"), 10, "PX4 back in OFFBOARD")
        wait_until(lambda: mission_status(st, lambda m: m.state in ("LAND", "IDLE")), 90, "survey complete")
        wait_until(lambda: st.landed(), 60, "landed and disarmed (PX4)")
        reached = [m.index for m in rec.get("reached")]
    finally:
        rec.close()
    assert reached[-3:] == [1, 2, 3], f"waypoints reached {reached}"


# ---------------------------------------------------------------- (c) fmu kill -9


def test_px4_fmu_killed_mid_mission_the_vehicle_stays_safe_and_holds(px4):
    st = px4
    start_survey(st)
    wait_until(lambda: mission_status(st, lambda m: m.state == "EXECUTING" and m.active_waypoint == 1), 40,
               "flying to waypoint 1")
    at_kill = st.truth.now()
    old = kill9(st, "fmu")
    t_kill = time.monotonic()
    s = wait_until(lambda: mission_status(st, lambda m: m.state == "HOLDING"), 5, "mission HOLDING")
    assert "fmu" in s.message and "outage" in s.message, s.message
    wait_until(lambda: st.pids().get("fmu") not in (None, old), 20, "aero up restarted fmu")
    back = wait_until(lambda: state(st, lambda m: m.connected), 20, "fmu back, PX4 connected")
    t_back = time.monotonic()
    at_back = st.truth.now()
    print(f"fmu back {t_back - t_kill:.1f} s after kill -9; PX4 in {back.flight_mode}")
    time.sleep(5.0)
    track = st.truth.since(t_kill)
    end = st.truth.now()
    s = mission_status(st)
    away = float(np.max(np.linalg.norm(track[:, :2] - at_kill[:2], axis=1)))
    print(f"after fmu kill -9: lowest {track[:, 2].min():.2f} m, farthest {away:.2f} m from the kill point, "
          f"at {end.round(2).tolist()} (SIH truth); mission {s.state}: {s.message}; PX4 {state(st).flight_mode}")
    assert track[:, 2].min() > 2.0, "the vehicle came down after the fmu was killed"
    assert s.state == "HOLDING", s
    # PX4's offboard-loss failsafe (RTL without RC) clears when the restarted fmu streams again: back
    # in OFFBOARD, which the built-in sim imitates (COM_OBL_ACT 2, SIM_OF_RESUME).
    wait_until(lambda: state(st, lambda m: m.flight_mode == "OFFBOARD"), 10, "PX4 back in OFFBOARD")
    rest = st.truth.at_rest(10, within_m=0.3)     # holding still, not flying on
    back_m = float(np.linalg.norm((rest - at_back)[:2]))
    print(f"held {back_m:.2f} m from where fmu came back (SIH truth)")
    # Held where PX4 gave OFFBOARD back, not flown back to a hold point from before PX4's RTL (that
    # was 3 m at 1.6 m/s: PX4 coasts COM_OF_LOSS_T on its last velocity setpoint); RTL may carry it
    # on up to one heartbeat (1 s) before OFFBOARD is back.
    assert back_m < 1.5, f"flew {back_m:.2f} m after fmu came back"
    st.ensure_landed()
