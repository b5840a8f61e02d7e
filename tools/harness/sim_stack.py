"""Flight stacks as `aero chaos`, the fault tests and `aero bench soak` fly them: the flight controller
linked to fmu through a `MavlinkTap` in this process (every port free and on loopback), gcs on free
UDP ports, ready once the planner's setpoints stream through fmu and the mission reports.

`SimStack` flies the built-in simulator (truth: sim/truth/state); `Px4Stack` (px4_stack.py) real
PX4 SITL."""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

from aeroperception.services.lib.geofence import Geofence

from .mavlink_tap import MavlinkTap
from .processes import free_udp_port, profile_services
from .stack import Stack


class FlightStack(Stack):
    """A Stack whose fmu reaches its FC through `tap` (cut it, speak to the FC, check every setpoint)
    and whose gcs binds free UDP ports (`gcs_port`; it sends to `gcs_remote_port`). Subclasses say
    which port the FC sends to (`fc_port`) and their own `aero up` arguments (`fc_args`)."""

    sensors = "none"
    tap_before_up = True    # False: the FC's port must stay free until `aero up` has checked it (PX4)

    def __init__(self, log_dir: str | Path | None, services: list[str], profile: str, extra_args=(),
                 startup_timeout_s: float = 45.0):
        self.fence = Geofence.from_params()
        self.tap: MavlinkTap | None = None
        super().__init__(log_dir or tempfile.mkdtemp(prefix=f"aero-{profile}-"), services, extra_args, profile,
                         startup_timeout_s)

    def fc_port(self) -> int:
        """The UDP port the FC sends its MAVLink to (the tap listens there)."""
        raise NotImplementedError

    def fc_args(self) -> list[str]:
        return []

    def start(self) -> None:
        self.fmu_port = free_udp_port()
        self.gcs_port, self.gcs_remote_port = free_udp_port(), free_udp_port()
        if self.tap_before_up:
            self.open_tap()
        super().start()

    def open_tap(self) -> None:
        self.tap = MavlinkTap(self.fc_port(), self.fmu_port, self.fence)

    def launch_args(self) -> list[str]:
        return [*self.fc_args(),
                "--arg", f"gcs:--param=local_port={self.gcs_port}",
                "--arg", f"gcs:--param=remote_port={self.gcs_remote_port}",
                "--arg", "gcs:--param=bind_ip=127.0.0.1"]

    def wait_ready(self, deadline: float) -> None:
        self.wait_flight_ready(max(1.0, deadline - time.monotonic()))

    def stop(self, timeout_s: float = 8.0) -> int | None:
        code = super().stop(timeout_s)
        if self.tap is not None:
            self.tap.close()
            self.tap = None
        return code


class SimStack(FlightStack):
    """`aero up --profile sim` with a MavlinkTap between sim and fmu. `sensors` is the sim's
    --sensors: the services it feeds are started (a change takes a `restart`)."""

    def __init__(self, log_dir: str | Path | None = None, sensors: str = "none", speed: float = 1.0,
                 services: list[str] | None = None, extra_args: list[str] = (),
                 startup_timeout_s: float = 45.0):
        self.requested = services or profile_services("sim")
        self.sensors, self.speed = sensors, speed
        super().__init__(log_dir, self.requested, "sim", extra_args, startup_timeout_s)

    def start(self) -> None:
        from aeroperception.tools.cli.up import fed_services

        self.services = fed_services(self.requested, self.sensors)[0]   # what `aero up` starts for them
        self._sim_port, self._sim_bind = free_udp_port(), free_udp_port()
        super().start()

    def fc_port(self) -> int:
        return self._sim_port

    def fc_args(self) -> list[str]:
        return ["--sensors", self.sensors, "--speed", str(self.speed), "--fcu-url", f"udpin:127.0.0.1:{self.fmu_port}",
                "--arg", f"sim:--target=127.0.0.1:{self._sim_port}", "--arg", f"sim:--bind=127.0.0.1:{self._sim_bind}"]
