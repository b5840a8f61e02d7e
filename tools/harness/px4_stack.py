"""`Px4Stack`: `aero up --profile px4` (PX4 SITL, the SIH quadrotor, as the flight controller) flown from
outside like `SimStack`, judged by SIH's own ground truth (`SihTruth`), never by the stack's account.

PX4 instance N (picked free from 1, instance 0 being a developer's default) sends its onboard link to
14540+N: the tap listens there once `aero up` has checked the port free and relays to fmu on a port
of its own; SIH's display link sends HIL_STATE_QUATERNION to 19410+N, received here."""
from __future__ import annotations

import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import Vector3, VehicleState
from aeroperception.services.mavlink import frames
from aeroperception.services.lib.geo import MapProjection

from .processes import profile_services
from .sim_stack import FlightStack
from .stack import StackStartError
from .topics import Capture
from .waiting import poll_until, wait_until

SIH_DISPLAY_PORT = 19410      # + instance: where PX4's SIH display link sends HIL_STATE_QUATERNION
PX4_GROUND_BELOW_ORIGIN_M = -2.0
# The vehicle profile's services and PX4: no rendered sensors (the px4 profile's follow-mode sim and
# perception), no recorder (nothing here reads its files).
PX4_FLIGHT_SERVICES = [s for s in profile_services("vehicle") if s != "recorder"] + ["px4"]


def px4_command(build: Path, instance: int, *args: str) -> str:
    """A PX4 shell command against running instance N (`px4_command(build, 1, "commander", "mode",
    "auto:loiter")` runs bin/px4-commander --instance 1 mode auto:loiter); AssertionError if it fails."""
    r = subprocess.run([str(Path(build) / "bin" / f"px4-{args[0]}"), "--instance", str(instance), *args[1:]],
                       capture_output=True, text=True, timeout=10)
    assert r.returncode == 0, f"px4-{' '.join(args)}: exit {r.returncode}: {r.stdout}{r.stderr}"
    return r.stdout


class SihTruth:
    """SIH's ground truth (HIL_STATE_QUATERNION at 25 Hz) as ENU metres about the first sample (the
    vehicle on its pad): (monotonic time, [x, y, z]) in `track`; as VehicleState (position, NED ground
    speed turned ENU, armed and mode from `status()`, PX4's own heartbeat) to each `listeners` fn."""

    def __init__(self, port: int, status: Callable[[], tuple[bool, str]] = lambda: (False, "")):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.2)
        self.mav = mavlink.MAVLink(None)
        self.status = status
        self.track: list[tuple[float, np.ndarray]] = []
        self.last: VehicleState | None = None
        self.listeners: list[Callable[[float, VehicleState], None]] = []
        self.lock = threading.Lock()
        self.origin: tuple[MapProjection, float] | None = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="sih-truth", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            try:
                data = self.sock.recv(65535)
            except OSError:
                continue
            try:
                msgs = self.mav.parse_buffer(data) or []
            except mavlink.MAVError:
                continue
            for m in msgs:
                if m.get_type() == "HIL_STATE_QUATERNION":
                    self._add(m)

    def _add(self, m) -> None:
        lat, lon, alt = m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3
        if self.origin is None:
            self.origin = (MapProjection(lat, lon), alt)
        proj, alt0 = self.origin
        north, east = proj.project(lat, lon)
        p = np.array([east, north, alt - alt0])
        armed, mode = self.status()
        state = VehicleState(position_m=Vector3.from_array(p), armed=armed, flight_mode=mode, connected=True,
                             velocity_mps=Vector3.from_array(frames.ned_to_enu(np.array([m.vx, m.vy, m.vz]) / 100.0)))
        now = time.monotonic()
        with self.lock:
            self.track.append((now, p))
            if len(self.track) > 100000:
                del self.track[:50000]
            self.last = state
            listeners = list(self.listeners)
        for fn in listeners:
            fn(now, state)

    def now(self) -> np.ndarray:
        wait_until(lambda: self.track, 5, "SIH ground truth (HIL_STATE_QUATERNION)")
        with self.lock:
            return self.track[-1][1]

    def at_rest(self, timeout_s: float, within_m: float = 0.15, for_s: float = 1.0) -> np.ndarray:
        """The position once the vehicle has stayed within `within_m` for `for_s`."""
        def settled():
            recent = self.since(time.monotonic() - for_s)
            span = time.monotonic() - self.track[0][0] if self.track else 0.0
            if len(recent) > 5 and span > for_s and float(np.ptp(recent, axis=0).max()) < within_m:
                return [recent[-1]]
            return None
        return wait_until(settled, timeout_s, f"the vehicle at rest (within {within_m} m for {for_s} s)")[0]

    def since(self, t: float) -> np.ndarray:
        with self.lock:
            return np.array([p for ts, p in self.track if ts >= t])

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.sock.close()


class Px4Stack(FlightStack):
    """`aero up --profile px4 --px4 BUILD` on a free PX4 instance, with a MavlinkTap between PX4 and
    fmu, gcs on free ports and SIH's truth (`sih`). `truth()` and `capture(truth=...)` answer from
    SIH's truth as SimStack's do from the built-in sim (`landed()`: PX4's land detector, as Stack's
    for every px4 profile)."""

    tap_before_up = False

    def __init__(self, build: str | Path, log_dir: str | Path | None = None, services: list[str] | None = None,
                 extra_args: list[str] = (), startup_timeout_s: float = 90.0):
        self.build = Path(build)
        self.sih: SihTruth | None = None
        services = services or PX4_FLIGHT_SERVICES
        super().__init__(log_dir, services, "px4", extra_args, startup_timeout_s)

    def start(self) -> None:
        from aeroperception.tools.cli import px4_sitl

        instance = px4_sitl.free_instance(1)
        if instance is None:
            raise StackStartError(f"no free PX4 instance in 1..{px4_sitl.MAX_INSTANCE}")
        self.instance, self.px4_ports = instance, px4_sitl.Ports(instance)
        self.sih = SihTruth(SIH_DISPLAY_PORT + instance, self._fc_status)
        super().start()

    def fc_port(self) -> int:
        return self.px4_ports.fmu

    def fc_args(self) -> list[str]:
        return ["--px4", str(self.build), "--px4-instance", str(self.instance),
                "--arg", f"fmu:--fcu-url=udpin:127.0.0.1:{self.fmu_port}"]   # through the tap, not 14540+N

    def launch_env(self) -> dict[str, str]:
        return {"PX4_PARAM_SYS_FAILURE_EN": "1"}   # px4-failure (GPS off) is acked only when enabled at boot

    def open_tap(self) -> None:
        super().open_tap()
        # PX4's local frame: EKF2's height origin is taken at boot and drifts with the baro, so the
        # ground is at up -0.5..-1.1 m (measured) and fmu's hold on the ground is there, not at 0.
        self.tap.floor_m = PX4_GROUND_BELOW_ORIGIN_M

    def wait_ready(self, deadline: float) -> None:
        self.open_tap()
        ready = poll_until(lambda: "Ready for takeoff" in self.service_log("px4") or self.proc.poll() is not None,
                           max(1.0, deadline - time.monotonic()), 0.2)
        if not ready or self.proc.poll() is not None:
            self._fail("PX4 not ready for takeoff")
        super().wait_ready(deadline)

    def _fc_status(self) -> tuple[bool, str]:
        tap = self.tap
        return (tap.fc_armed, tap.fc_mode) if tap is not None else (False, "")

    def stop(self, timeout_s: float = 8.0) -> int | None:
        code = super().stop(timeout_s)
        if self.sih is not None:
            self.sih.close()
            self.sih = None
        return code

    # ------------------------------------------------------------ PX4's view

    def px4_shell(self, *args: str) -> str:
        """A PX4 shell command against this instance (`px4_shell("commander", "mode", "auto:loiter")`)."""
        return px4_command(self.build, self.instance, *args)

    def truth(self, timeout_s: float = 3.0) -> VehicleState:
        wait_until(lambda: self.sih.last, timeout_s, "SIH ground truth (HIL_STATE_QUATERNION)")
        return self.sih.last

    def capture(self, **keys: tuple[str, type]) -> Capture:
        """As Stack.capture, with `truth` fed from SIH's HIL_STATE_QUATERNION (not a Zenoh key)."""
        truth = keys.pop("truth", None)
        cap = super().capture(**keys)
        if truth is not None:
            cap.feed("truth", self.sih.listeners)
        return cap

