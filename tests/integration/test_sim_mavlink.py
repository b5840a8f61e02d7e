"""The simulated vehicle over real UDP with a real pymavlink peer, as fmu talks to PX4 SITL.

The runner is in a thread at `SPEED` x real time, bound to an ephemeral port on 127.0.0.1 and
sending to the peer's `udpin` port (also ephemeral), so a running stack on 14540/14580 is never
disturbed. Every wait is bounded.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")  # before mavutil picks its dialect
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as M  # noqa: E402

from aerotest import free_udp_port, signal_other_thread  # noqa: E402
from aeroperception.services.mavlink import px4  # noqa: E402
from aeroperception.services.sim.vehicle import MavlinkEndpoint, SimVehicle, SimVehicleRunner  # noqa: E402

SPEED = 4.0
POSITION_ONLY = (M.POSITION_TARGET_TYPEMASK_VX_IGNORE | M.POSITION_TARGET_TYPEMASK_VY_IGNORE
                 | M.POSITION_TARGET_TYPEMASK_VZ_IGNORE | M.POSITION_TARGET_TYPEMASK_AX_IGNORE
                 | M.POSITION_TARGET_TYPEMASK_AY_IGNORE | M.POSITION_TARGET_TYPEMASK_AZ_IGNORE
                 | M.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)


class Peer:
    """A companion computer: pymavlink `udpin`, plus a setpoint streamer thread."""

    def __init__(self, port: int):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                               source_component=190, dialect="common")
        self.lock = threading.Lock()
        self.log: list = []
        self._stream_stop = threading.Event()
        self._streamer: threading.Thread | None = None

    def send(self, fn_name: str, *args) -> None:
        with self.lock:
            getattr(self.conn.mav, fn_name)(*args)

    def mark(self) -> int:
        """Position in the received log, for `recv(..., since=mark)` to look back from."""
        return len(self.log)

    def recv(self, mtype: str, pred=lambda m: True, timeout_s: float = 5.0, since: int | None = None):
        """First `mtype` message satisfying `pred` received after `since` (default: from now on).
        Every message is logged, so one that arrived while waiting for another is not lost."""
        i = self.mark() if since is None else since
        deadline = time.monotonic() + timeout_s
        while True:
            for m in self.log[i:]:
                if m.get_type() == mtype and pred(m):
                    return m
            i = len(self.log)
            if time.monotonic() >= deadline:
                raise AssertionError(f"no {mtype} matching the condition within {timeout_s} s")
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is not None:
                self.log.append(m)

    def drain(self) -> None:
        """Read what is queued. A peer that stops reading (sleeping in a test) fills its socket
        buffer at these rates, and the kernel then drops the next datagram: maybe our ACK."""
        while (m := self.conn.recv_match(blocking=False)) is not None:
            self.log.append(m)

    def command(self, command: int, *params, timeout_s: float = 3.0) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.drain()
        self.send("command_long_send", 1, 1, command, 0, *p)
        return self.recv("COMMAND_ACK", lambda a: a.command == command, timeout_s).result

    def stream_setpoints(self, ned_xyz, yaw_ned: float = 0.0, hz: float = 20.0) -> None:
        """Like fmu's offboard stream; hz is wall time (SPEED x slower in sim time)."""
        self.stop_stream()
        self._stream_stop.clear()

        def run():
            while not self._stream_stop.wait(1.0 / hz):
                self.send("set_position_target_local_ned_send", 0, 1, 1, M.MAV_FRAME_LOCAL_NED, POSITION_ONLY,
                          *ned_xyz, 0, 0, 0, 0, 0, 0, yaw_ned, 0)
        self._streamer = threading.Thread(target=run, daemon=True)
        self._streamer.start()

    def stop_stream(self) -> None:
        self._stream_stop.set()
        if self._streamer is not None:
            self._streamer.join(2.0)
            self._streamer = None

    def close(self) -> None:
        self.stop_stream()
        self.conn.close()


@pytest.fixture
def link():
    port = free_udp_port()
    peer = Peer(port)
    endpoint = MavlinkEndpoint(target=("127.0.0.1", port), bind=("127.0.0.1", 0))
    # offboard loss -> HOLD, then LAND after 2 s (the PX4 SITL default, RTL, is tested in test_flight)
    runner = SimVehicleRunner(SimVehicle({"COM_OBL_ACT": 1, "COM_OBL_HOLD_T": 2.0}, seed=11), endpoint,
                              speed=SPEED).start()
    try:
        peer.recv("HEARTBEAT", timeout_s=5.0)  # the peer learns the vehicle's address from this
        yield peer, runner
    finally:
        peer.close()
        runner.stop()
    assert not runner.running


def test_heartbeat_and_identity(link):
    peer, runner = link
    hb = peer.recv("HEARTBEAT")
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    assert px4.decode(hb.custom_mode) == "HOLD"
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert peer.conn.mavlink20()
    assert peer.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == M.MAV_RESULT_ACCEPTED
    ver = peer.recv("AUTOPILOT_VERSION")
    assert ver.capabilities & M.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    assert peer.command(M.MAV_CMD_DO_SET_SERVO, 1, 1500) == M.MAV_RESULT_UNSUPPORTED
    peer.send("timesync_send", 0, 4242)
    ts = peer.recv("TIMESYNC", lambda m: m.ts1 == 4242)
    assert ts.tc1 > 0
    peer.recv("EXTENDED_SYS_STATE", lambda m: m.landed_state == M.MAV_LANDED_STATE_ON_GROUND)
    for mtype in ("LOCAL_POSITION_NED", "ATTITUDE_QUATERNION", "HIGHRES_IMU", "SYS_STATUS", "BATTERY_STATUS",
                  "GLOBAL_POSITION_INT", "ATTITUDE"):
        peer.recv(mtype)
    assert runner.diagnostics()["timesync"] == 1


def test_offboard_flight_over_udp(link):
    peer, runner = link
    # OFFBOARD is refused before a setpoint stream exists
    assert peer.command(M.MAV_CMD_DO_SET_MODE, 1, 6, 0) == M.MAV_RESULT_TEMPORARILY_REJECTED

    target_ned = (4.0, -3.0, -5.0)
    peer.stream_setpoints(target_ned)
    time.sleep(1.5 / SPEED + 0.3)  # > 1 s of sim time of stream
    assert peer.command(M.MAV_CMD_DO_SET_MODE, 1, 6, 0) == M.MAV_RESULT_ACCEPTED
    assert peer.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    hb = peer.recv("HEARTBEAT", lambda m: m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
    assert px4.decode(hb.custom_mode) == "OFFBOARD"

    def near(m):
        return np.linalg.norm(np.array([m.x, m.y, m.z]) - target_ned) < 0.3
    peer.recv("LOCAL_POSITION_NED", near, timeout_s=20.0 / SPEED + 5)
    peer.recv("EXTENDED_SYS_STATE", lambda m: m.landed_state == M.MAV_LANDED_STATE_IN_AIR)
    truth = runner.vehicle.truth().position_enu_m
    np.testing.assert_allclose(truth, [-3.0, 4.0, 5.0], atol=0.5)  # the same point in ENU

    # the setpoint stream stops: PX4 falls back to HOLD (failsafe), then LAND after COM_OBL_HOLD_T
    mark = peer.mark()
    peer.stop_stream()
    hb = peer.recv("HEARTBEAT", lambda m: px4.decode(m.custom_mode) == "HOLD", timeout_s=3.0 / SPEED + 3)
    assert hb.system_status == M.MAV_STATE_CRITICAL
    peer.recv("STATUSTEXT", lambda m: "offboard" in m.text, since=mark)
    peer.recv("HEARTBEAT", lambda m: px4.decode(m.custom_mode) == "LAND", timeout_s=4.0 / SPEED + 3)
    # ... lands and auto-disarms
    peer.recv("HEARTBEAT", lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout_s=15.0 / SPEED + 5)
    peer.recv("EXTENDED_SYS_STATE", lambda m: m.landed_state == M.MAV_LANDED_STATE_ON_GROUND)
    d = runner.diagnostics()
    assert d["setpoints"] > 20 and d["commander_auto_disarms"] == 1


def test_takeoff_and_land_commands(link):
    peer, runner = link
    home_alt = runner.vehicle.params.SIM_HOME_ALT
    assert peer.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert peer.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, float("nan"), float("nan"), float("nan"),
                        home_alt + 3.0) == M.MAV_RESULT_ACCEPTED
    peer.recv("GLOBAL_POSITION_INT", lambda m: abs(m.relative_alt - 3000) < 250, timeout_s=10.0 / SPEED + 5)
    peer.recv("HEARTBEAT", lambda m: px4.decode(m.custom_mode) == "HOLD", timeout_s=5.0)
    assert peer.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0) == M.MAV_RESULT_DENIED  # in the air
    assert peer.command(M.MAV_CMD_NAV_LAND) == M.MAV_RESULT_ACCEPTED
    peer.recv("HEARTBEAT", lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout_s=15.0 / SPEED + 5)


def test_garbage_is_counted_and_dropped(link):
    peer, runner = link
    vehicle_addr = runner.endpoint.local_address
    rng = np.random.default_rng(5)
    good = M.MAVLink(None, 255, 190).heartbeat_encode(6, 8, 0, 0, 0).pack(M.MAVLink(None, 255, 190))
    corrupt = bytearray(good)
    corrupt[-2] ^= 0x55
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(50):
            s.sendto(bytes(rng.integers(0, 256, rng.integers(1, 400), dtype=np.uint8)), vehicle_addr)
        s.sendto(bytes(corrupt), vehicle_addr)
        s.sendto(b"\xfd" + b"\xff" * 20, vehicle_addr)
    time.sleep(0.3)
    # still alive and still answering
    assert runner.running
    assert peer.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION) == M.MAV_RESULT_ACCEPTED
    t0 = runner.now_ns()
    peer.recv("HEARTBEAT", lambda m: runner.now_ns() > t0)
    d = runner.diagnostics()
    assert d["rx_bad"] >= 50
    assert d["handler_errors"] == 0


def test_standalone_entry_point_runs_and_stops_on_sigterm():
    port = free_udp_port()
    peer = Peer(port)
    proc = subprocess.Popen(
        [sys.executable, "-m", "aeroperception.services.sim.vehicle", "--target", f"127.0.0.1:{port}",
         "--bind", "127.0.0.1:0", "--speed", "2", "--seed", "3", "--home", "47.0,8.0,500",
         "--param", "SIM_WIND_E=1.5", "--status-every", "0.5"],
        stderr=subprocess.PIPE, text=True)
    try:
        hb = peer.recv("HEARTBEAT", timeout_s=10.0)
        assert px4.decode(hb.custom_mode) == "HOLD"
        home = peer.recv("HOME_POSITION", timeout_s=10.0)
        assert home.latitude == 470000000 and home.altitude == 500000
        time.sleep(0.8)  # at least one status line
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=3.0) == 0
        assert '"mode": "HOLD"' in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        peer.close()


def test_standalone_entry_point_stops_on_sigint_to_any_thread():
    """No status lines (an untimed wait) and the signal delivered to a thread other than the main
    one: it still stops within 2 s (the handler runs only on the main thread; see signals.py)."""
    port = free_udp_port()
    peer = Peer(port)
    proc = subprocess.Popen([sys.executable, "-m", "aeroperception.services.sim.vehicle", "--target",
                             f"127.0.0.1:{port}", "--bind", "127.0.0.1:0", "--status-every", "0"],
                            stderr=subprocess.PIPE, text=True)
    try:
        peer.recv("HEARTBEAT", timeout_s=10.0)
        t0 = time.monotonic()
        signal_other_thread(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=10.0) == 0
        assert time.monotonic() - t0 < 2.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        peer.close()


def test_entry_point_rejects_bad_arguments():
    out = subprocess.run([sys.executable, "-m", "aeroperception.services.sim.vehicle", "--param", "SIM_MASS=-1",
                          "--bind", "127.0.0.1:0"], capture_output=True, text=True, timeout=20)
    assert out.returncode == 2 and "SIM_MASS" in out.stderr


def test_reboot_over_udp_goes_silent_and_comes_back_at_default_rates(link):
    peer, runner = link
    assert peer.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000) == M.MAV_RESULT_ACCEPTED
    before = peer.recv("LOCAL_POSITION_NED", lambda m: m.time_boot_ms > 4000, timeout_s=4000 / 1000 / SPEED + 3).time_boot_ms
    assert peer.command(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == M.MAV_RESULT_ACCEPTED
    t0 = time.monotonic()
    first = peer.recv("HEARTBEAT", timeout_s=runner.vehicle.params.SIM_REBOOT_T / SPEED + 3.0)
    silent_s = time.monotonic() - t0
    assert silent_s > 0.8 * runner.vehicle.params.SIM_REBOOT_T / SPEED, f"heartbeat {silent_s:.2f} s after reboot"
    assert not first.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    lp = peer.recv("LOCAL_POSITION_NED", timeout_s=2.0)
    assert lp.time_boot_ms < before
    mark = peer.mark()
    end = time.monotonic() + 1.0
    while time.monotonic() < end:  # keep reading: an idle socket buffer overflows at x4
        peer.drain()
        time.sleep(0.005)
    lps = [m for m in peer.log[mark:] if m.get_type() == "LOCAL_POSITION_NED"]
    hz = (len(lps) - 1) / ((lps[-1].time_boot_ms - lps[0].time_boot_ms) / 1000.0)  # in sim time
    assert hz == pytest.approx(30.0, rel=0.15), f"LOCAL_POSITION_NED at {hz:.1f} Hz after the reboot (default 30 Hz)"
    assert runner.vehicle.reboots == 1
