"""fmu under faults, against the real simulated PX4 over MAVLink.

Two set-ups, everything on 127.0.0.1 with free ports:
- `aero up --only sim,fmu,diagnostics` (module-scoped) with the test itself as the planner: it
  follows state/vehicle and publishes fmu/in/trajectory_setpoint stamped with the state it was
  computed from, as the planner does, and can go silent, vanish (liveliness), send garbage or
  replay stale motion. What the flight controller received and did comes from the sim's own
  counters (diagnostics/sim) and sim/truth/state, never from fmu.
- fmu alone as a process on a Zenoh router, with the simulated vehicle in-process and raw UDP
  sockets playing junk senders and link thieves.
Every wait is bounded; processes are stopped through their handles or pids.json.
"""
from __future__ import annotations

import errno
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest
import zenoh
from pymavlink.dialects.v20 import common as M

from aerotest import (
    Capture, clean_env, diag, free_udp_port, interrupt, is_service_process, latest, pos, speed, wait_until,
    zenoh_client,
)
from aeroperception.schemas import (
    ArmReply, ArmRequest, Header, SchemaError, SetModeReply, SetModeRequest,
    TrajectorySetpoint, Vector3, VehicleState, decode, encode,
)
from aeroperception.services.runtime.node import CallError, call, encoding_for
from aeroperception.services.sim.vehicle import MavlinkEndpoint, SimVehicle, SimVehicleRunner

ALT_M = 3.0
GCS = M.MAVLink(None, srcSystem=255, srcComponent=190)


class TestPlanner:
    """Stands in for the planner: at 50 Hz, `law(state)` from the newest state/vehicle (if
    fresher than 0.3 s), stamped with that state's stamp; or `replay` as is (stale motion)."""

    __test__ = False

    def __init__(self, session):
        self.session = session
        self.pub = session.declare_publisher("fmu/in/trajectory_setpoint", encoding=encoding_for(TrajectorySetpoint))
        self.law = None
        self.replay: TrajectorySetpoint | None = None
        self.last_sent: TrajectorySetpoint | None = None
        self.state: VehicleState | None = None
        self.state_rx = 0.0
        self.token = None
        self.sub = session.declare_subscriber("state/vehicle", self._on_state)
        self.stop_ev = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def declare_alive(self) -> None:
        if self.token is None:
            self.token = self.session.liveliness().declare_token("aero/alive/default/planner")

    def vanish(self) -> None:
        if self.token is not None:
            self.token.undeclare()
            self.token = None

    def _on_state(self, sample: zenoh.Sample) -> None:
        try:
            self.state, self.state_rx = decode(sample.payload.to_bytes(), VehicleState), time.monotonic()
        except SchemaError:
            pass

    def _run(self) -> None:
        while not self.stop_ev.wait(0.02):
            sp = self.replay
            if sp is None:
                st, law = self.state, self.law
                if law is None or st is None or time.monotonic() - self.state_rx > 0.3:
                    continue
                sp = law(st)
                sp.header = Header(stamp_ns=st.header.stamp_ns, frame_id="map")
                self.last_sent = sp
            self.pub.put(encode(sp))

    def close(self) -> None:
        self.stop_ev.set()
        self.thread.join(2)
        self.vanish()
        self.sub.undeclare()
        self.pub.undeclare()


def hold_at(p) -> callable:
    p = np.array(p, dtype=float)
    return lambda st: TrajectorySetpoint(position_valid=True, velocity_valid=True, yaw_valid=True,
                                         position_m=Vector3.from_array(p), velocity_mps=Vector3(), yaw_rad=0.0)


def cruise_east(v_mps: float, alt_m: float = ALT_M) -> callable:
    return lambda st: TrajectorySetpoint(velocity_valid=True, yaw_valid=True, yaw_rad=0.0,
                                         velocity_mps=Vector3(x=v_mps, z=1.0 * (alt_m - st.position_m.z)))


def fmu_call(session, key: str, req, reply_cls, timeout_s: float = 6.0):
    try:
        return call(session, key, req, reply_cls, timeout_s)
    except CallError:
        return None


# ---------------------------------------------------------------- the aero up stack


@pytest.fixture(scope="module")
def fst(stack_module):
    fcu, sim_bind = free_udp_port(), free_udp_port()
    st = stack_module(["sim", "fmu", "diagnostics"], extra_args=[
        "--fcu-url", f"udpin:127.0.0.1:{fcu}",
        "--arg", f"sim:--target=127.0.0.1:{fcu}", "--arg", f"sim:--bind=127.0.0.1:{sim_bind}",
        "--arg", "sim:--sensors=none"], timeout_s=30)
    st.sim_address = ("127.0.0.1", sim_bind)
    planner = TestPlanner(st.session)
    planner.declare_alive()
    truth = Capture(st.session, {"truth": ("sim/truth/state", VehicleState)})
    try:
        wait_until(lambda: latest(st.session, "state/vehicle", VehicleState, 1.0, lambda m: m.connected), 15,
                   "state/vehicle connected (fmu <-> sim)")
        yield st, planner, truth
    finally:
        truth.close()
        planner.close()


def wait_at_rest(truth: Capture, timeout_s: float = 20.0, for_s: float = 1.0) -> VehicleState:
    def settled():
        now = time.monotonic()
        recent = truth.get("truth", now - for_s)
        first = truth.since("truth")[:1]
        full = first and first[0][0] <= now - for_s
        return full and len(recent) > 10 and all(speed(m) < 0.15 for m in recent) and recent[-1]
    return wait_until(settled, timeout_s, f"truth at rest for {for_s} s", interval_s=0.1)


def ensure_hovering(st, planner: TestPlanner, truth: Capture) -> VehicleState:
    """In the air at ALT_M, OFFBOARD, fmu following the test planner (hold where we are)."""
    planner.replay = None
    planner.declare_alive()
    t = wait_until(lambda: truth.last("truth"), 3, "sim/truth/state")
    planner.law = hold_at([t.position_m.x, t.position_m.y, ALT_M])
    wait_until(lambda: diag(st.session, "fmu").values.get("planner") == "streaming", 10, "fmu following the test planner")
    if not (t.armed and t.flight_mode == "OFFBOARD"):
        r = wait_until(lambda: (r := fmu_call(st.session, "fmu/srv/set_mode", SetModeRequest(mode="OFFBOARD"),
                                              SetModeReply)) and r.success and r, 10, "OFFBOARD accepted", interval_s=0.3)
        assert r.success
        if not t.armed:
            r = fmu_call(st.session, "fmu/srv/arm", ArmRequest(arm=True), ArmReply)
            assert r is not None and r.success, r
    wait_until(lambda: (m := truth.last("truth")) and m.position_m.z > ALT_M - 0.3, 20, "climbed to the hover altitude")
    rest = wait_at_rest(truth)
    assert rest.flight_mode == "OFFBOARD" and rest.armed
    return rest


def land(st, planner: TestPlanner, truth: Capture) -> None:
    t = truth.last("truth")
    if t is not None and t.armed:
        r = fmu_call(st.session, "fmu/srv/set_mode", SetModeRequest(mode="LAND"), SetModeReply)
        assert r is not None and r.success, r
        wait_until(lambda: not truth.last("truth").armed, 40, "landed and disarmed")
    planner.law = None


def counters(st) -> tuple[dict, dict]:
    return diag(st.session, "fmu").values, diag(st.session, "sim").values


# ---------------------------------------------------------------- item 5: unsafe setpoints


def test_unsafe_setpoints_never_reach_the_fc_fmu_holds_and_counts_them(fst):
    st, planner, truth = fst
    start = ensure_hovering(st, planner, truth)
    f0, s0 = counters(st)
    bad = {
        "NaN velocity": TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=math.nan, y=1.0)),
        "1000 m/s": TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=1000.0)),
        "inf position": TrajectorySetpoint(position_valid=True, position_m=Vector3(x=math.inf, z=3.0)),
        "100 km away": TrajectorySetpoint(position_valid=True, position_m=Vector3(x=1e5, z=3.0)),
        "10 km up": TrajectorySetpoint(position_valid=True, position_m=Vector3(z=1e4)),
        "NaN yaw": TrajectorySetpoint(velocity_valid=True, yaw_valid=True, yaw_rad=math.nan),
        "NaN acceleration": TrajectorySetpoint(velocity_valid=True, acceleration_valid=True,
                                               acceleration_mps2=Vector3(y=math.nan)),
    }
    t0 = time.monotonic()
    for sp in bad.values():
        planner.law = lambda st_, sp=sp: TrajectorySetpoint(**{f: getattr(sp, f) for f in sp.__struct_fields__})
        time.sleep(0.5)
    planner.law = hold_at(pos(start))
    wait_until(lambda: diag(st.session, "fmu").values.get("planner") == "streaming", 5, "following good setpoints again")
    time.sleep(1.2)  # a fresh diagnostics/sim after the last setpoint fmu could have forwarded
    f1, s1 = counters(st)
    track = np.array([pos(m) for m in truth.get("truth", t0)])
    drift = float(np.linalg.norm(track - pos(start), axis=1).max())
    rejected = int(f1.get("setpoints_rejected", 0)) - int(f0.get("setpoints_rejected", 0))
    print(f"unsafe setpoints: fmu rejected {rejected}; FC got non-finite {s0['setpoints_nonfinite']} -> "
          f"{s1['setpoints_nonfinite']}, max speed {s1['setpoint_max_speed_mps']} m/s; drift {drift:.2f} m")
    assert int(s1["setpoints_nonfinite"]) == int(s0["setpoints_nonfinite"]) == 0, "non-finite setpoints reached the FC"
    assert float(s1["setpoint_max_speed_mps"]) <= 3.0, "an out-of-envelope velocity reached the FC"
    assert int(s1["setpoints"]) > int(s0["setpoints"]) + 100, "fmu stopped streaming to the FC"
    assert rejected >= len(bad) * 15, f"only {rejected} setpoints counted as rejected"
    assert drift < 0.5, f"vehicle moved {drift:.2f} m while fed garbage"
    assert truth.last("truth").flight_mode == "OFFBOARD"


# ---------------------------------------------------------------- item 9b: brake, no fly-back


@pytest.mark.parametrize("how", ["silent", "gone"])
def test_planner_lost_at_speed_brakes_and_holds_where_it_stops(fst, how):
    st, planner, truth = fst
    ensure_hovering(st, planner, truth)
    planner.law = cruise_east(2.0)
    wait_until(lambda: (m := truth.last("truth")) and m.velocity_mps.x > 1.9, 10, "cruising east at 2 m/s")
    time.sleep(0.5)
    t_lost = time.monotonic()
    at_loss = truth.last("truth")
    if how == "silent":
        planner.law = None
    else:
        planner.vanish()   # liveliness gone, setpoints keep coming: must be ignored at once
    time.sleep(4.0)
    track = truth.get("truth", t_lost)
    d = diag(st.session, "fmu").values
    x = np.array([m.position_m.x for m in track])
    peak, final = float(x.max()), float(x[-1])
    print(f"planner {how} at {speed(at_loss):.2f} m/s: stopped {peak - at_loss.position_m.x:.2f} m on, "
          f"flew back {peak - final:.3f} m; hold_reason {d.get('hold_reason')!r}")
    assert len(track) > 100
    assert peak - final < 0.15, f"flew back {peak - final:.2f} m toward where the planner was lost"
    assert speed(track[-1]) < 0.15 and speed(track[-2]) < 0.15, "not stopped 4 s after the planner was lost"
    assert peak - at_loss.position_m.x < 2.0, "braked too late"
    assert d["offboard"] == "hold"
    assert d["hold_reason"] == ("planner silent" if how == "silent" else "planner not alive")
    planner.law = hold_at(pos(track[-1]))  # before coming back: fmu would follow a cruise law again
    planner.declare_alive()
    assert truth.last("truth").flight_mode == "OFFBOARD"


# ---------------------------------------------------------------------------------- feed-forward


def hold_with_feed_forward(p, accel_enu_mps2, valid: bool = True, jerk: bool = False) -> callable:
    """Hold at p (position + zero velocity) with an acceleration feed-forward (marked valid or not)."""
    def law(st):
        sp = hold_at(p)(st)
        sp.acceleration_valid, sp.acceleration_mps2 = valid, Vector3.from_array(np.asarray(accel_enu_mps2, float))
        sp.jerk_valid, sp.jerk_mps3 = jerk, Vector3(x=1.0 if jerk else 0.0)
        return sp
    return law


def east_acceleration_during(truth: Capture, planner: TestPlanner, law, hold, pulse_s: float = 0.5) -> float:
    """Mean true east acceleration (m/s^2) while `law` is followed for pulse_s (its first 0.1 s,
    the attitude settling, left out); then back to `hold` and at rest."""
    t0 = time.monotonic()
    planner.law = law
    time.sleep(pulse_s)
    planner.law = hold
    samples = [m for m in truth.get("truth", t0 + 0.1) if m.header.stamp_ns]
    samples = samples[:int(100 * (pulse_s - 0.1))]          # 100 Hz truth, within the pulse
    wait_at_rest(truth)
    return float(np.mean([m.acceleration_mps2.x for m in samples]))


def test_acceleration_feed_forward_reaches_the_fc_and_accelerates_the_vehicle_and_jerk_is_refused(fst):
    """Same position/velocity setpoint, with and without a valid 3 m/s^2 east feed-forward: the
    true acceleration follows the feed-forward only when it is marked valid (fmu used to drop it).
    A setpoint marking jerk valid cannot be sent over MAVLink: refused, counted, held with the reason."""
    st, planner, truth = fst
    rest = ensure_hovering(st, planner, truth)
    hold = hold_at(pos(rest))
    ff = [3.0, 0.0, 0.0]
    with_ff = east_acceleration_during(truth, planner, hold_with_feed_forward(pos(rest), ff), hold)
    without = east_acceleration_during(truth, planner, hold_with_feed_forward(pos(rest), ff, valid=False), hold)
    f0 = diag(st.session, "fmu").values
    t0 = time.monotonic()
    planner.law = hold_with_feed_forward(pos(rest), ff, jerk=True)
    held = wait_until(lambda: (d := diag(st.session, "fmu").values) and "jerk_valid" in d.get("hold_reason", "") and d, 5,
                      "fmu refusing the jerk setpoint")
    time.sleep(0.5)
    moved = max(float(np.linalg.norm(pos(m) - pos(rest))) for m in truth.get("truth", t0))
    planner.law = hold
    wait_until(lambda: diag(st.session, "fmu").values.get("planner") == "streaming", 5, "following again")
    print(f"true east acceleration: {with_ff:.2f} m/s^2 with a valid 3 m/s^2 feed-forward, {without:.2f} without; "
          f"jerk: rejected {f0['setpoints_rejected']} -> {held['setpoints_rejected']}, moved {moved:.2f} m")
    assert with_ff > 1.0, f"feed-forward 3 m/s^2 east gave {with_ff:.2f} m/s^2"
    assert abs(without) < 0.5, f"an ignored feed-forward moved the vehicle ({without:.2f} m/s^2)"
    assert int(held["setpoints_rejected"]) > int(f0["setpoints_rejected"])
    assert held["offboard"] in ("brake", "hold") and moved < 0.3


# ---------------------------------------------------------------- item 8: FC reboot


def rate_hz(session, key: str, cls: type, seconds: float = 2.0) -> float:
    n = [0]
    sub = session.declare_subscriber(key, lambda s: n.__setitem__(0, n[0] + 1))
    try:
        time.sleep(0.3)
        n0, t0 = n[0], time.monotonic()
        time.sleep(seconds)
        return (n[0] - n0) / (time.monotonic() - t0)
    finally:
        sub.undeclare()


def test_fc_reboot_is_detected_and_stream_rates_are_requested_again(fst):
    st, planner, truth = fst
    land(st, planner, truth)
    before = rate_hz(st.session, "state/vehicle", VehicleState)
    f0, s0 = counters(st)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a GCS on the sim's link reboots it
        s.sendto(GCS.command_long_encode(1, 1, M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 1, 0, 0, 0, 0, 0, 0).pack(GCS),
                 st.sim_address)
    wait_until(lambda: int(diag(st.session, "sim").values["reboots"]) == int(s0["reboots"]) + 1, 5, "the sim rebooted")
    wait_until(lambda: latest(st.session, "state/vehicle", VehicleState, 1.0, lambda m: m.connected), 10, "link back")
    time.sleep(1.0)
    after = rate_hz(st.session, "state/vehicle", VehicleState)
    imu = rate_hz(st.session, "fmu/out/sensor_combined", VehicleState)
    f1, s1 = counters(st)
    print(f"FC reboot: state/vehicle {before:.1f} Hz -> {after:.1f} Hz, IMU {imu:.1f} Hz; fmu reboots detected "
          f"{f0.get('reboots_detected')} -> {f1.get('reboots_detected')}, link set-ups {f0.get('link_setups')} -> "
          f"{f1.get('link_setups')}; sim time_boot_ms {s0['time_boot_ms']} -> {s1['time_boot_ms']}")
    assert int(s1["time_boot_ms"]) < int(s0["time_boot_ms"])
    assert before > 45 and after > 45, f"state/vehicle {before:.1f} Hz before, {after:.1f} Hz after the reboot"
    assert imu > 90, f"FC IMU {imu:.1f} Hz after the reboot (PX4 default 50, asked 100)"
    assert int(f1["reboots_detected"]) == int(f0["reboots_detected"]) + 1
    assert int(f1["link_setups"]) == int(f0["link_setups"]) + 1


# ---------------------------------------------------------------- items 7 / 3c: fmu outage


def test_fmu_killed_mid_motion_restarted_fmu_never_replays_stale_motion(fst):
    """kill -9 fmu while the vehicle flies east; the 'planner' keeps streaming that motion with its
    old stamp. The sim fails over to RTL (PX4 SITL default) 1 s after the last setpoint; the
    restarted fmu streams a brake/hold, the sim resumes OFFBOARD (as PX4 does), and the stale
    east motion must never be flown. Fresh setpoints are followed again afterwards."""
    st, planner, truth = fst
    ensure_hovering(st, planner, truth)
    planner.law = cruise_east(1.5)
    wait_until(lambda: (m := truth.last("truth")) and m.velocity_mps.x > 1.4, 10, "moving east")
    time.sleep(0.3)
    old_pid = st.pids()["fmu"]
    assert is_service_process(old_pid, "fmu")
    planner.replay = planner.last_sent              # stale motion from now on
    t_kill = time.monotonic()
    os.kill(old_pid, signal.SIGKILL)
    try:
        rtl = wait_until(lambda: next((m for m in truth.get("truth", t_kill) if m.flight_mode == "RTL"), None), 5,
                         "sim offboard-loss failsafe RTL")
        rtl_s = (rtl.header.stamp_ns - truth.get("truth", t_kill)[0].header.stamp_ns) / 1e9
        wait_until(lambda: st.pids().get("fmu") not in (None, old_pid), 20, "aero up restarted fmu")
        back = wait_until(lambda: next((m for m in truth.get("truth", t_kill) if m.flight_mode == "OFFBOARD"
                                        and m.header.stamp_ns > rtl.header.stamp_ns), None), 20,
                          "OFFBOARD again once the new fmu streams")
        t_back = time.monotonic()
        time.sleep(5.0)
        after = truth.get("truth", t_back)
        d = diag(st.session, "fmu").values
        s = diag(st.session, "sim").values
        xy = np.array([m.position_m.to_array()[:2] for m in after])
        travel = float(np.linalg.norm(xy - back.position_m.to_array()[:2], axis=1).max())
        print(f"fmu killed: RTL {rtl_s:.2f} s after; back in OFFBOARD, then moved {travel:.2f} m horizontally; "
              f"stale setpoints refused {d.get('setpoints_stale')}, hold_reason {d.get('hold_reason')!r}")
        assert 0.9 < rtl_s < 1.6, f"RTL {rtl_s:.2f} s after the last setpoint (COM_OF_LOSS_T 1 s)"
        assert travel < 1.0, f"flew {travel:.2f} m after fmu came back: stale motion replayed"
        assert speed(after[-1]) < 0.15, "not holding 5 s after fmu came back"
        assert int(d["setpoints_stale"]) > 50 and d["offboard"] == "hold" and int(d["setpoints_sent"]) == 0
        assert int(s["commander_offboard_resumed"]) >= 1 and after[-1].flight_mode == "OFFBOARD"
        # Fresh motion (computed from the new fmu's state) is followed again.
        planner.replay = None
        planner.law = hold_at(pos(after[-1]))
        wait_until(lambda: diag(st.session, "fmu").values.get("planner") == "streaming", 5, "following fresh setpoints")
    finally:
        planner.replay = None
        land(st, planner, truth)


# ---------------------------------------------------------------- item 6: the MAVLink link


@pytest.fixture
def fmu_alone(zenoh_router, tmp_path):
    """start(port, *args) -> Popen of fmu on the router with udpin:127.0.0.1:port; stopped after."""
    procs: list[subprocess.Popen] = []

    def start(port: int, *args: str) -> subprocess.Popen:
        log = open(tmp_path / f"fmu{len(procs)}.log", "wb")
        p = subprocess.Popen([sys.executable, "-m", "aeroperception.services.fmu", "--connect", zenoh_router,
                              "--fcu-url", f"udpin:127.0.0.1:{port}", *args],
                             stdout=subprocess.DEVNULL, stderr=log, env=clean_env())
        p.log_path = tmp_path / f"fmu{len(procs)}.log"
        procs.append(p)
        return p

    yield start
    for p in procs:
        interrupt(p, 5.0)


@contextmanager
def sim_vehicle(fcu_port: int):
    runner = SimVehicleRunner(SimVehicle(seed=2), MavlinkEndpoint(target=("127.0.0.1", fcu_port),
                                                                  bind=("127.0.0.1", 0)), speed=1.0).start()
    try:
        yield runner
    finally:
        runner.stop()


def received(sock: socket.socket) -> int:
    sock.setblocking(False)
    n = 0
    while True:
        try:
            sock.recv(65535)
            n += 1
        except BlockingIOError:
            return n


def test_fmu_talks_only_to_the_flight_controller(fmu_alone, zenoh_router):
    fcu = free_udp_port()
    session = zenoh_client(zenoh_router)
    junk = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(200)]
    try:
        with sim_vehicle(fcu) as runner:
            fmu = fmu_alone(fcu)
            wait_until(lambda: latest(session, "state/vehicle", VehicleState, 1.0, lambda m: m.connected), 20,
                       "fmu connected to the sim")
            fake_fc = GCS.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, 0, 0, 0).pack(GCS)
            gcs_hb = GCS.heartbeat_encode(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(GCS)
            for i, s in enumerate(junk):
                s.bind(("127.0.0.1", 0))
                s.sendto(b"\x01\x02\x03\x04\x05" if i % 3 == 0 else gcs_hb if i % 3 == 1 else fake_fc,
                         ("127.0.0.1", fcu))
            tx0 = runner.endpoint.counters["rx_msgs"]
            time.sleep(2.0)
            back = sum(received(s) for s in junk)
            d = diag(session, "fmu").values
            still = latest(session, "state/vehicle", VehicleState, 2.0, lambda m: m.connected)
            print(f"200 foreign senders: {back} datagrams back; fmu rejected {d.get('rejected_datagrams')}, "
                  f"peer {d.get('fcu_peer')}, sim heard {runner.endpoint.counters['rx_msgs'] - tx0} msgs from fmu")
            assert back == 0, f"fmu sent {back} datagrams to senders that are not the flight controller"
            assert int(d["rejected_datagrams"]) >= 200 and int(d["link_locks"]) == 1
            assert d["fcu_peer"] == "127.0.0.1:%d" % runner.endpoint.local_address[1]
            assert still is not None and runner.endpoint.counters["rx_msgs"] > tx0 + 50
            assert fmu.poll() is None
    finally:
        for s in junk:
            s.close()
        session.close()


def test_fmu_port_cannot_be_shared_or_taken_over(fmu_alone, zenoh_router):
    fcu = free_udp_port()
    session = zenoh_client(zenoh_router)
    try:
        with sim_vehicle(fcu):
            fmu_alone(fcu)
            wait_until(lambda: latest(session, "state/vehicle", VehicleState, 1.0, lambda m: m.connected), 20,
                       "fmu connected to the sim")
            for host in ("127.0.0.1", "0.0.0.0"):
                thief = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                thief.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                thief.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
                try:
                    with pytest.raises(OSError) as e:
                        thief.bind((host, fcu))
                    assert e.value.errno == errno.EADDRINUSE
                finally:
                    thief.close()
    finally:
        session.close()


@pytest.mark.parametrize("reuse", [False, True])
def test_fmu_refuses_to_start_on_a_taken_port(fmu_alone, reuse):
    fcu = free_udp_port()
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    if reuse:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    holder.bind(("127.0.0.1", fcu))
    try:
        fmu = fmu_alone(fcu)
        try:
            code = fmu.wait(20)
        except subprocess.TimeoutExpired:
            raise AssertionError("fmu kept running on a port another socket holds") from None
        err = fmu.log_path.read_text()
        lines = [line for line in err.splitlines() if "error" in line]
        assert code != 0
        assert len(lines) == 1 and f"127.0.0.1:{fcu}" in lines[0] and "in use" in lines[0], err
        assert "Traceback" not in err
    finally:
        holder.close()


def test_fmu_relocks_onto_a_restarted_fc_after_the_link_was_lost(fmu_alone, zenoh_router):
    fcu = free_udp_port()
    session = zenoh_client(zenoh_router)
    try:
        with sim_vehicle(fcu) as first:
            fmu_alone(fcu, "--param", "fcu_relock_s=1.0")
            wait_until(lambda: latest(session, "state/vehicle", VehicleState, 1.0, lambda m: m.connected), 20,
                       "fmu connected to the first FC")
            first_port = first.endpoint.local_address[1]
        with sim_vehicle(fcu) as second:  # a new ephemeral port: a different address
            wait_until(lambda: diag(session, "fmu").values.get("fcu_peer") == "127.0.0.1:%d" % second.endpoint.local_address[1],
                       15, "fmu locked onto the restarted FC")
            assert second.endpoint.local_address[1] != first_port
            wait_until(lambda: latest(session, "state/vehicle", VehicleState, 1.0, lambda m: m.connected), 10,
                       "state/vehicle from the restarted FC")
            assert int(diag(session, "fmu").values["link_locks"]) == 2
    finally:
        session.close()


def test_offboard_right_after_the_link_comes_up_waits_for_the_stream_and_retries_a_refusal(fmu_alone, zenoh_router):
    """PX4 accepts OFFBOARD only after a setpoint stream. CI saw a mission's OFFBOARD reach the FC
    < 1 s after fmu linked to it: refused TEMPORARILY_REJECTED, the mission failed, the vehicle
    auto-disarmed. Here the FC wants 2 s of stream, more than fmu's offboard_warmup_s (1.5 s), and the
    request comes the moment fmu is connected: fmu waits, is refused, re-sends, and is accepted."""
    fcu = free_udp_port()
    session = zenoh_client(zenoh_router)
    runner = SimVehicleRunner(SimVehicle({"COM_OF_WARM_T": 2.0}, seed=2),
                              MavlinkEndpoint(target=("127.0.0.1", fcu), bind=("127.0.0.1", 0)), speed=1.0).start()
    try:
        fmu_alone(fcu, "--param=command_timeout_s=5")
        wait_until(lambda: latest(session, "state/vehicle", VehicleState, 1.0, lambda m: m.connected), 20,
                   "fmu connected to the sim")
        t0 = time.monotonic()
        reply = fmu_call(session, "fmu/srv/set_mode", SetModeRequest(mode="OFFBOARD"), SetModeReply, timeout_s=10)
        took = time.monotonic() - t0
        assert reply is not None and reply.success, reply
        assert runner.vehicle.commander.mode == "OFFBOARD"
        retried = wait_until(lambda: int(diag(session, "fmu").values.get("commands_retried", 0)), 5,
                             "diagnostics/fmu counting the re-sent request")
        print(f"OFFBOARD right after link-up: accepted after {took:.2f} s, {retried} re-sends")
        assert retried >= 1 and took < 5.0
    finally:
        runner.stop()
        session.close()
