"""The safety service as a real process.

- Standalone (`aero up --only safety`) fed by test nodes that are real Zenoh nodes named like the
  required services (their liveliness tokens and 1 Hz diagnostics come from the runtime): battery
  levels in the air -> WARN / RTH / LAND, the same on the ground -> WARN only; FC link silence;
  GCS loss, perception FAILED, a service gone and a service alive without diagnostics (hung); a
  refused geofence polygon; the emergency stop refused without confirm or reason, and not
  executed without fmu.
- On the sim stack (sim, fmu, planner, mission, diagnostics, safety; no sensors; MAVLink on free
  UDP ports): a planner killed with SIGKILL is listed dead within 1.5 s and the status returns to
  nominal after `aero up` restarts it; the sim's battery drained through its live parameters is
  seen through fmu; in the air a small geofence -> VIOLATION + the configured action (hold, then
  land), a dead planner -> HOLD; the emergency stop (last: the sim latches termination until reboot) stops
  the motors: disarmed, on the ground per sim/truth.
"""
from __future__ import annotations

import os
import signal
import threading
import time

import msgspec
import pytest

from aerotest import free_udp_port, is_service_process, wait_for_message, wait_until
from aeroperception.schemas import (
    BatteryState, EmergencyStopReply, EmergencyStopRequest, GcsLink, GoalStatus, GoToPositionGoal, LandedState, LandGoal, MissionStatus,
    ParamSet, ParamSetReply, PerceptionHealth, SafetyStatus, TakeoffGoal, Vector3, VehicleState, decode,
)
from aeroperception.services.runtime import ActionClient, Node
from aeroperception.services.runtime.node import call

S = SafetyStatus
STACK = ["sim", "fmu", "planner", "mission", "diagnostics", "safety"]


def safety_status(st, pred=None, timeout_s: float = 5.0) -> SafetyStatus:
    return wait_for_message(st.session, "safety/status", SafetyStatus, pred, timeout_s)


class StatusWatch:
    """Every safety/status from now on, with its arrival time, so a change published at once is
    not missed between an input and the wait for its effect."""

    def __init__(self, st):
        self.cond = threading.Condition()
        self.seen: list[tuple[float, SafetyStatus]] = []
        self.sub = st.session.declare_subscriber("safety/status", self._on_sample)
        # Live only once a status arrived (1 Hz): a change published at once right after the
        # declaration could otherwise pass the router before it knows this subscriber (seen once
        # in a full run: the first case's status came with the next tick, 1.1 s later).
        self.wait(lambda m: True, time.monotonic() - 10.0, 3.0)

    def _on_sample(self, sample) -> None:
        msg = decode(sample.payload.to_bytes(), SafetyStatus)
        with self.cond:
            self.seen.append((time.monotonic(), msg))
            self.cond.notify_all()

    def wait(self, pred, since: float, timeout_s: float = 5.0) -> tuple[SafetyStatus, float]:
        """The first status after `since` matching pred, and its delay after `since`."""
        def match():
            return next(((t, m) for t, m in self.seen if t >= since and pred(m)), None)
        with self.cond:
            found = self.cond.wait_for(match, timeout_s)
        assert found, f"no matching safety/status within {timeout_s} s; last: {self.seen[-1:]}"
        return found[1], found[0] - since

    def close(self) -> None:
        self.sub.undeclare()


def set_param(st, service: str, name: str, value) -> ParamSetReply:
    return call(st.session, f"config/{service}/@set", ParamSet(name=name, value=value), ParamSetReply, 5.0)


def estop(st, confirm: bool, reason: str, timeout_s: float = 8.0) -> EmergencyStopReply:
    return call(st.session, "safety/srv/emergency_stop", EmergencyStopRequest(confirm=confirm, reason=reason),
                EmergencyStopReply, timeout_s)


# ---------------------------------------------------------------- standalone safety, test inputs


@pytest.fixture
def lone_safety(stack):
    """safety alone under `aero up`, plus nodes named fmu/planner/mission on its router; the "fmu"
    node publishes state/vehicle at 20 Hz from `vehicle["state"]` (replace it to change it)."""
    st = stack(["safety"])
    nodes = []
    for name in ("fmu", "planner", "mission"):
        node = Node(name, connect=st.endpoint)
        assert node.connect(max_wait_s=5.0)
        nodes.append(node)
    fmu = nodes[0]
    vehicle = {"state": VehicleState(armed=True, landed_state=LandedState.IN_AIR, connected=True,
                                     position_m=Vector3(z=5.0))}
    pub_state = fmu.publisher("state/vehicle", VehicleState)
    pub_battery = fmu.publisher("fmu/out/battery_status", BatteryState)
    fmu.every(0.05, lambda: pub_state.publish(vehicle["state"]), name="state")
    try:
        yield st, vehicle, pub_battery, nodes
    finally:
        for n in nodes:
            n.close()


def test_battery_levels_recommend_warn_rth_land_in_the_air_and_only_warn_on_the_ground(lone_safety):
    st, vehicle, pub_battery, _nodes = lone_safety
    s = safety_status(st, lambda m: m.heartbeats_alive == 3 and m.px4_connected, 10)
    assert (s.safety_level, s.recommended_action, s.battery_status) == (S.LEVEL_WARNING, S.ACTION_WARN, S.BATTERY_OK)
    assert s.active_warnings == ["battery state unknown"]
    cases = [(0.80, S.LEVEL_NOMINAL, S.ACTION_NONE, S.BATTERY_OK),
             (0.25, S.LEVEL_WARNING, S.ACTION_WARN, S.BATTERY_WARNING),
             (0.12, S.LEVEL_CAUTION, S.ACTION_RTH, S.BATTERY_CRITICAL),
             (0.05, S.LEVEL_EMERGENCY, S.ACTION_LAND, S.BATTERY_CRITICAL)]
    watch = StatusWatch(st)
    for remaining, level, action, battery in cases:
        t0 = time.monotonic()
        pub_battery.publish(BatteryState(voltage_v=15.0, remaining_fraction=remaining))
        s, latency = watch.wait(lambda m: m.battery_remaining == remaining, t0, 3)
        assert (s.safety_level, s.recommended_action, s.battery_status) == (level, action, battery), s
        assert latency < 0.5, f"status for battery {remaining} after {latency:.2f} s (expected at once)"
    watch.close()
    assert s.active_errors == ["battery emergency -> LAND"]
    # The same battery on the ground: reported, no motion recommended.
    vehicle["state"] = VehicleState(armed=False, landed_state=LandedState.ON_GROUND, connected=True)
    pub_battery.publish(BatteryState(voltage_v=15.0, remaining_fraction=0.05))
    s = safety_status(st, lambda m: m.recommended_action == S.ACTION_WARN, 3)
    assert s.safety_level == S.LEVEL_WARNING and s.active_warnings == ["battery emergency"]


def test_flight_controller_silence_is_an_emergency_without_action_and_a_bad_polygon_is_refused(lone_safety):
    st, vehicle, pub_battery, _nodes = lone_safety
    pub_battery.publish(BatteryState(voltage_v=15.0, remaining_fraction=0.9))
    safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 10)
    reply = set_param(st, "safety", "geofence_polygon", "1,2;3")
    assert not reply.success and "at least 3" in reply.message and reply.value == ""
    vehicle["state"] = msgspec.structs.replace(vehicle["state"], connected=False)
    s = safety_status(st, lambda m: not m.px4_connected, 3)
    assert (s.safety_level, s.recommended_action) == (S.LEVEL_EMERGENCY, S.ACTION_NONE)
    assert s.active_errors == ["flight controller link lost: its own failsafe flies the vehicle"]


def test_emergency_stop_refused_without_confirm_or_reason_and_not_executed_without_fmu(lone_safety):
    st, _vehicle, _pub, _nodes = lone_safety
    r = estop(st, confirm=False, reason="test")
    assert not r.success and "confirm=true" in r.message
    r = estop(st, confirm=True, reason="   ")
    assert not r.success and "reason" in r.message
    s = safety_status(st)
    assert s.recommended_action != S.ACTION_EMERGENCY_STOP   # refused requests change nothing
    # Our "fmu" node serves no fmu/srv/emergency_stop: the reply says so, and the status shows it.
    r = estop(st, confirm=True, reason="integration test")
    assert not r.success and r.message.startswith("not executed: ") and "fmu/srv/emergency_stop" in r.message
    s = safety_status(st, lambda m: m.recommended_action == S.ACTION_EMERGENCY_STOP, 3)
    assert s.safety_level == S.LEVEL_EMERGENCY
    assert s.active_errors[0].startswith("emergency stop NOT executed (integration test)")


def test_gcs_loss_perception_and_a_hung_service_are_reported(lone_safety):
    st, _vehicle, pub_battery, nodes = lone_safety
    pub_battery.publish(BatteryState(voltage_v=15.0, remaining_fraction=0.9))
    safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 10)
    pub_gcs = nodes[0].publisher("gcs/link", GcsLink)
    pub_perception = nodes[0].publisher("perception/health", PerceptionHealth)
    watch = StatusWatch(st)
    try:
        t0 = time.monotonic()
        pub_gcs.publish(GcsLink(connected=True))
        s, _ = watch.wait(lambda m: m.gcs_connected, t0, 3)
        assert s.safety_level == S.LEVEL_NOMINAL
        t0 = time.monotonic()
        pub_gcs.publish(GcsLink(connected=False))
        s, _ = watch.wait(lambda m: not m.gcs_connected, t0, 3)
        assert (s.recommended_action, s.active_warnings) == (S.ACTION_WARN, ["ground station link lost"])
        t0 = time.monotonic()
        pub_perception.publish(PerceptionHealth(vio_status=PerceptionHealth.FAILED, overall_healthy=False))
        s, _ = watch.wait(lambda m: len(m.active_warnings) == 2, t0, 3)
        assert s.active_warnings[1] == "perception not healthy (VIO FAILED)"
        # mission's process goes away: dead at once; a token without diagnostics: hung after 3 s.
        t0 = time.monotonic()
        nodes[2].close()
        s, _ = watch.wait(lambda m: m.dead_heartbeats == ["mission"], t0, 3)
        assert (s.safety_level, s.recommended_action) == (S.LEVEL_CAUTION, S.ACTION_HOLD)
        token = st.session.liveliness().declare_token("aero/alive/default/mission")
        try:
            t0 = time.monotonic()
            watch.wait(lambda m: m.dead_heartbeats == [], t0, 3)
            s, hung_after = watch.wait(lambda m: m.dead_heartbeats == ["mission"], t0, 6)
            assert 2.5 < hung_after < 4.5 and "mission hung: no diagnostics for over 3 s -> HOLD" in s.active_errors
        finally:
            token.undeclare()
    finally:
        watch.close()


# ---------------------------------------------------------------- on the sim stack


@pytest.fixture(scope="module")
def sim_stack(stack_module):
    fcu, sim_bind = free_udp_port(), free_udp_port()
    st = stack_module(STACK, extra_args=[
        "--fcu-url", f"udpin:127.0.0.1:{fcu}", "--arg", f"sim:--target=127.0.0.1:{fcu}",
        "--arg", f"sim:--bind=127.0.0.1:{sim_bind}", "--sensors", "none"], timeout_s=40)
    try:
        safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 20)
    except AssertionError:
        print(st.describe())
        raise
    return st


def service_pid(st, name: str) -> int:
    pid = st.pids().get(name)
    assert pid is not None and is_service_process(pid, name), f"no running {name} process in pids.json"
    return pid


def kill_planner_and_time_it(st) -> tuple[SafetyStatus, float]:
    """SIGKILL the planner by pid; the first status listing it dead (within 1.5 s) and the delay."""
    pid = service_pid(st, "planner")
    watch = StatusWatch(st)
    try:
        t0 = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        s, elapsed = watch.wait(lambda m: "planner" in m.dead_heartbeats, t0, 3)
    finally:
        watch.close()
    print(f"planner SIGKILL -> safety/status lists it dead after {elapsed * 1000:.0f} ms")
    assert elapsed < 1.5
    wait_until(lambda: st.pids().get("planner") not in (None, pid), 20, "aero up restarted the planner")
    return s, elapsed


def test_killed_planner_is_listed_dead_at_once_and_nominal_after_restart(sim_stack):
    st = sim_stack
    s, _ = kill_planner_and_time_it(st)
    # On the ground: reported, no motion.
    assert (s.heartbeats_alive, s.heartbeats_total) == (2, 3) and not s.trajectory_healthy
    assert (s.safety_level, s.recommended_action) == (S.LEVEL_WARNING, S.ACTION_WARN)
    assert "planner not alive" in s.active_warnings
    s = safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 20)
    assert (s.dead_heartbeats, s.heartbeats_alive, s.trajectory_healthy) == ([], 3, True)


def test_sim_battery_drained_through_its_live_params_is_reported(sim_stack):
    st = sim_stack
    try:
        assert set_param(st, "sim", "SIM_BAT_CAP", 100.0).success       # a tiny pack...
        assert set_param(st, "sim", "SIM_BAT_DRAIN", 1000.0).success    # ...drained fast
        s = safety_status(st, lambda m: m.battery_status == S.BATTERY_CRITICAL, 30)
        assert s.battery_remaining < 0.15 and s.battery_voltage_v > 0
        assert s.recommended_action == S.ACTION_WARN   # on the ground: reported only
        assert any(w.startswith(("battery critical", "battery emergency")) for w in s.active_warnings)
    finally:
        set_param(st, "sim", "SIM_BAT_DRAIN", 1.0)
        set_param(st, "sim", "SIM_BAT_CAP", 100000.0)                   # full again
    safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 10)


def land_and_wait(st) -> None:
    """Land through the mission (if it is not landing already, e.g. after an RTL) and wait for
    the true vehicle to be on the ground, disarmed."""
    land = ActionClient(st.session, "mission/action/land")
    try:
        land.send_goal(LandGoal())
    finally:
        land.close()
    wait_for_message(st.session, "sim/truth/state", VehicleState,
                     lambda m: m.position_m.z < 0.2 and not m.armed, 60)
    # The FSM leaves LAND when fmu reports the landing, a beat after the truth: the next test's
    # TAKEOFF is refused until then ("TAKEOFF only from IDLE (now LAND)" failed CI once).
    wait_for_message(st.session, "mission/status", MissionStatus,
                     lambda m: m.state == MissionStatus.STATE_IDLE, 15)


def test_in_the_air_geofence_breach_holds_and_a_dead_planner_holds(sim_stack):
    st = sim_stack
    takeoff = ActionClient(st.session, "mission/action/takeoff")
    goto = ActionClient(st.session, "mission/action/goto")
    try:
        g = takeoff.send_goal(TakeoffGoal(target_altitude_m=3.0))
        assert g.success, g.message
        res = takeoff.result(g.goal_id, 40)
        assert res.status == GoalStatus.SUCCEEDED, res.message
        s = safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 10)
        assert s.distance_to_geofence_m == pytest.approx(117.0, abs=0.5)   # 120 m ceiling - 3 m

        # Airborne: a killed planner -> HOLD.
        s, _ = kill_planner_and_time_it(st)
        assert (s.safety_level, s.recommended_action) == (S.LEVEL_CAUTION, S.ACTION_HOLD)
        assert "planner not alive -> HOLD" in s.active_errors
        safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 20)

        # A 5 m fence (hover at its centre: inside the 5 m warning margin) and a goto 8 m East:
        # VIOLATION, and the configured action (default 2: hold; then 5: land).
        assert set_param(st, "safety", "geofence_radius_m", 5.0).success
        s = safety_status(st, lambda m: m.geofence_status == S.GEOFENCE_WARNING, 3)
        assert s.active_warnings[0] == "near the geofence boundary"
        g = goto.send_goal(GoToPositionGoal(position_m=Vector3(x=8.0, z=3.0)))
        assert g.success, g.message
        s = safety_status(st, lambda m: m.geofence_status == S.GEOFENCE_VIOLATION, 20)
        assert s.distance_to_geofence_m < 0
        assert (s.safety_level, s.recommended_action) == (S.LEVEL_CAUTION, S.ACTION_HOLD)
        assert s.active_errors[0] == "outside the geofence (geofence_action 2: hold) -> HOLD"
        assert not set_param(st, "safety", "geofence_action", 4).success   # terminate is not offered
        # 5: land (not 3, return: a mission acting on it would fly PX4's RTL, a 60 m climb first).
        assert set_param(st, "safety", "geofence_action", 5).success
        s = safety_status(st, lambda m: m.recommended_action == S.ACTION_LAND, 3)
        assert s.safety_level == S.LEVEL_EMERGENCY
        assert s.active_errors[0] == "outside the geofence (geofence_action 5: land) -> LAND"
    finally:
        set_param(st, "safety", "geofence_action", 2)
        set_param(st, "safety", "geofence_radius_m", 500.0)
        for c in (takeoff, goto):
            c.close()
        land_and_wait(st)
    safety_status(st, lambda m: m.safety_level == S.LEVEL_NOMINAL, 10)


def test_emergency_stop_terminates_the_flight(sim_stack):
    """Last on the stack: the sim latches flight termination until it reboots."""
    st = sim_stack
    takeoff = ActionClient(st.session, "mission/action/takeoff")
    try:
        g = takeoff.send_goal(TakeoffGoal(target_altitude_m=2.0))
        assert g.success, g.message
        assert takeoff.result(g.goal_id, 40).status == GoalStatus.SUCCEEDED
    finally:
        takeoff.close()
    r = estop(st, confirm=False, reason="not confirmed")
    assert not r.success
    assert wait_for_message(st.session, "sim/truth/state", VehicleState, timeout_s=3).armed   # refused: flying on
    r = estop(st, confirm=True, reason="integration test: stop the motors")
    assert r.success, r.message
    s = safety_status(st, lambda m: m.recommended_action == S.ACTION_EMERGENCY_STOP, 3)
    assert s.safety_level == S.LEVEL_EMERGENCY
    assert s.active_errors[0] == "emergency stop executed (integration test: stop the motors)"
    truth = wait_for_message(st.session, "sim/truth/state", VehicleState,
                             lambda m: m.position_m.z < 0.2 and abs(m.velocity_mps.z) < 0.05, 10)
    assert not truth.armed
    s = safety_status(st, timeout_s=3)
    assert s.recommended_action == S.ACTION_EMERGENCY_STOP   # still shown afterwards, on the ground
