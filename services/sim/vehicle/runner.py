"""Runs the simulated vehicle: fixed-step physics on a sim clock, paced against a wall clock.

One loop, one thread: poll MAVLink (non-blocking) -> step physics -> send due telemetry ->
report truth. With `speed` > 0 the sim clock advances `speed` x wall time (catching up in
bounded bursts when the host is slow, then re-anchoring instead of spiralling); with speed 0
it runs as fast as the CPU allows. All rates (streams, failsafe timers) are in sim time, as in
PX4 lockstep SITL.

The Zenoh shell uses: `on_truth` (VehicleTruth per physics step or at `truth_rate_hz`),
`now_ns()` for sim/clock, `epoch_ns` for stamps on Zenoh, `diagnostics()` for its health, `vehicle.params` for live parameters,
and `start()` / `stop()`.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Callable

from aeroperception.services.sim.truth import VehicleTruth

from .endpoint import MavlinkEndpoint
from .mavlink_module import MavlinkModule
from .model import DEFAULT_PHYSICS_RATE_HZ, SimVehicle

log = logging.getLogger("aeroperception.sim.vehicle")

_MAX_CATCHUP_STEPS = 50  # per loop iteration before giving up on real time


class SimVehicleRunner:
    def __init__(self, vehicle: SimVehicle | None = None, endpoint: MavlinkEndpoint | None = None, *,
                 speed: float = 1.0, physics_rate_hz: float = DEFAULT_PHYSICS_RATE_HZ,
                 on_truth: Callable[[VehicleTruth], None] | None = None, truth_rate_hz: float | None = None,
                 wall_clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 system_id: int = 1, component_id: int = 1):
        if speed < 0:
            raise ValueError("speed must be >= 0 (0: as fast as possible)")
        self.vehicle = vehicle if vehicle is not None else SimVehicle()
        self.endpoint = endpoint
        if endpoint is not None:  # the ids on the wire are the endpoint's; commands are filtered by them
            system_id, component_id = endpoint.encoder.srcSystem, endpoint.encoder.srcComponent
        self.module = MavlinkModule(self.vehicle, system_id, component_id)
        self.speed = float(speed)
        self.dt_s = 1.0 / physics_rate_hz
        self.on_truth = on_truth
        self._truth_period_ns = 0 if truth_rate_hz is None else int(round(1e9 / truth_rate_hz))
        self._next_truth_ns = 0
        self._wall_clock = wall_clock
        self._sleep = sleep
        self.steps = 0
        self.overruns = 0          # times the loop fell behind real time and re-anchored
        self.callback_errors = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wall_start = wall_clock()
        self._sim_start_ns = self.vehicle.time_ns
        # Wall-clock time (ns since the Unix epoch) of sim time 0: stamp = epoch_ns + sim ns. Set
        # when the paced loop starts and, at 1x, again whenever it re-anchors after falling
        # behind, so at 1x a stamp is the wall time its sim instant happened at — what services
        # on wall time stamp with (the fmu's state/vehicle). A fixed epoch taken before the
        # renderers were set up put every sensor stamp ~0.5 s behind state/vehicle, and the
        # lidar placed scans with where the vehicle had been half a second earlier.
        self.epoch_ns = time.time_ns() - self.vehicle.time_ns

    def now_ns(self) -> int:
        """Sim time since the vehicle booted (what it puts in time_boot_ms / TIMESYNC)."""
        return self.vehicle.time_ns

    # ------------------------------------------------------------------ stepping

    def step(self) -> None:
        """One physics step with its I/O. Public so tests can drive the loop deterministically."""
        if self.endpoint is not None:
            for msg in self.endpoint.receive():
                self._send(self.module.handle(msg))
        self.vehicle.step(self.dt_s)
        self.steps += 1
        self._send(self.module.tick())
        if self.on_truth is not None and self.vehicle.time_ns >= self._next_truth_ns:
            self._next_truth_ns = max(self._next_truth_ns + self._truth_period_ns, self.vehicle.time_ns)
            try:
                self.on_truth(self.vehicle.truth())
            except Exception:  # the publisher's problem must not stop the vehicle
                self.callback_errors += 1
                if self.callback_errors == 1:
                    log.exception("on_truth callback failed")

    def _send(self, msgs) -> None:
        if self.endpoint is not None:
            for m in msgs:
                self.endpoint.send(m)

    def run_for(self, duration_s: float) -> None:
        """Step `duration_s` of sim time without pacing."""
        for _ in range(int(round(duration_s / self.dt_s))):
            self.step()

    def run(self, stop: threading.Event | None = None) -> None:
        """Paced loop until `stop` is set."""
        stop = stop or self._stop
        dt_ns = int(round(self.dt_s * 1e9))
        self._anchor(epoch=True)
        while not stop.is_set():
            if self.speed == 0:
                self.step()
                continue
            target_ns = self._sim_start_ns + (self._wall_clock() - self._wall_start) * self.speed * 1e9
            n = 0
            while self.vehicle.time_ns + dt_ns <= target_ns and n < _MAX_CATCHUP_STEPS:
                self.step()
                n += 1
            if n == _MAX_CATCHUP_STEPS:
                self.overruns += 1
                self._anchor(epoch=self.speed == 1.0)
                continue
            wait_s = (self.vehicle.time_ns + dt_ns - target_ns) / 1e9 / self.speed
            self._sleep(min(max(wait_s, 0.0), 0.05))

    def _anchor(self, epoch: bool) -> None:
        """Pace from here: sim time now <-> wall time now (and the stamps' epoch with it)."""
        self._wall_start, self._sim_start_ns = self._wall_clock(), self.vehicle.time_ns
        if epoch:
            self.epoch_ns = max(self.epoch_ns, time.time_ns() - self.vehicle.time_ns)   # stamps never go back

    def start(self) -> "SimVehicleRunner":
        """Run in a daemon thread."""
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, args=(self._stop,), name="sim-vehicle", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        if self.endpoint is not None:
            self.endpoint.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ observability

    def realtime_factor(self) -> float:
        """Sim seconds per wall second since the loop (re)anchored."""
        wall = self._wall_clock() - self._wall_start
        return (self.vehicle.time_ns - self._sim_start_ns) / 1e9 / wall if wall > 0 else 0.0

    def diagnostics(self) -> dict:
        """Flat dict of counters and state for the service's health report."""
        c = self.vehicle.commander
        s = self.vehicle.state
        bat = self.vehicle.airframe.battery
        d = {
            "sim_time_s": round(self.vehicle.time_s, 6),
            "speed": self.speed,
            "realtime_factor": round(self.realtime_factor(), 3),
            "steps": self.steps,
            "overruns": self.overruns,
            "callback_errors": self.callback_errors,
            "mode": c.mode,
            "armed": c.armed,
            "landed_state": c.landed_state,
            "failsafe": c.failsafe_reason if c.failsafe else "",
            "terminated": c.terminated,
            "position_enu_m": [round(float(v), 3) for v in s.position_enu_m],
            "battery_remaining": round(bat.remaining, 4),
            "battery_voltage_v": round(bat.voltage_v, 3),
            "reboots": self.vehicle.reboots,
            **{f"commander_{k}": v for k, v in c.counters.items()},
            **self.module.diagnostics(),
        }
        if self.endpoint is not None:
            d.update(self.endpoint.counters)
            d["peer"] = "%s:%d" % self.endpoint.last_peer if self.endpoint.last_peer else ""
        return d
