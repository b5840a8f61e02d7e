"""The simulated vehicle without any I/O: airframe + position control + commander on a sim clock.

This is what unit tests drive directly, and what the MAVLink module and the runner wrap.
Randomness comes from one seed, split into independent streams for physics (wind) and sensors
(telemetry noise), so the true trajectory does not depend on which telemetry was requested.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from aeroperception.services.lib.geo import MapProjection
from aeroperception.services.runtime.params import ParamSet
from aeroperception.services.sim.truth import VehicleTruth

from .commander import Commander
from .control import PositionController
from .dynamics import Multirotor, Terrain
from .estimator import EstimatedState, VisionEstimator
from .params import make_params

DEFAULT_PHYSICS_RATE_HZ = 250.0


class SimVehicle:
    def __init__(self, params: ParamSet | Mapping[str, Any] | None = None, seed: int = 0,
                 terrain: Terrain | None = None):
        """`terrain(x, y)`: ground z (ENU m) under (x, y), the scenario's ground; flat by default.
        Home (the local origin) is on the ground at (0, 0)."""
        self.params = params if isinstance(params, ParamSet) else make_params(params)
        self.terrain = terrain
        self.seed = seed
        physics_seq, sensor_seq, estimator_seq = np.random.SeedSequence(seed).spawn(3)  # first two as before
        self.physics_rng = np.random.default_rng(physics_seq)
        self.sensor_rng = np.random.default_rng(sensor_seq)
        self._estimator_seq = estimator_seq
        self.time_ns = 0
        self.boot_ns = 0          # sim time of the last (re)boot: time_boot_ms counts from here
        self.reboots = 0
        self._build()

    def _build(self) -> None:
        self.airframe = Multirotor(self.params, self.physics_rng, terrain=self.terrain)
        self.controller = PositionController(self.params)
        epoch = getattr(self, "estimator", None) and self.estimator.epoch_ns
        self.estimator = VisionEstimator(self.params, self.airframe.state, np.random.default_rng(self._estimator_seq))
        self.estimator.epoch_ns = epoch
        self.estimate = EstimatedState(self.airframe.state, self.estimator)  # what the FC believes
        self.commander = Commander(self.params, self.estimate, lambda: self.airframe.battery.remaining,
                                   lambda: self.estimator.valid(self.time_ns))

    def reboot(self) -> None:
        """Like power-cycling the autopilot: back on the ground at home, disarmed, termination
        cleared, full battery. The sim clock keeps running (it is the world's clock); the
        autopilot's own time since boot (time_boot_ms) starts again from zero."""
        self.reboots += 1
        self.boot_ns = self.time_ns
        self._build()

    @property
    def time_s(self) -> float:
        return self.time_ns * 1e-9

    @property
    def time_since_boot_ns(self) -> int:
        return self.time_ns - self.boot_ns

    @property
    def state(self):
        return self.airframe.state

    @property
    def home(self) -> MapProjection:
        return MapProjection(self.params.SIM_HOME_LAT, self.params.SIM_HOME_LON)

    def step(self, dt_s: float) -> None:
        """Advance the simulation by dt_s (seconds of sim time)."""
        dt_ns = int(round(dt_s * 1e9))
        now_s = (self.time_ns + dt_ns) * 1e-9
        self.estimator.step(dt_s, self.time_ns)
        setpoint = self.commander.update(now_s)
        command = None
        if setpoint is not None:
            s = self.estimate   # the controller flies on the estimate: estimation error is flight error
            command = self.controller.update(dt_s, setpoint, s.position_enu_m, s.velocity_enu_mps,
                                             s.accel_enu_mps2, s.yaw_rad, self.commander.landed)
        else:
            self.controller.reset()
        self.airframe.step(dt_s, command)
        self.time_ns += dt_ns

    def run_for(self, duration_s: float, rate_hz: float = DEFAULT_PHYSICS_RATE_HZ) -> None:
        """Step at a fixed rate for `duration_s` of sim time (tests, batch runs)."""
        dt = 1.0 / rate_hz
        for _ in range(int(round(duration_s * rate_hz))):
            self.step(dt)

    def truth(self) -> VehicleTruth:
        return self.airframe.truth(self.time_ns)
