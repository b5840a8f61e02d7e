"""The vehicle's MAVLink side, like PX4's mavlink module on its onboard link: the receiver
(mavlink_receiver.py: incoming commands, setpoints, vision, parameters) and the telemetry streams
(mavlink_streams.py: outgoing messages at their rates), joined here with what both obey: the
silence after a reboot, per-type receive counts, and a handler that fails never stopping the
vehicle.

`handle(msg)` returns the replies to one received message; `tick()` the telemetry due at the
current sim time. No sockets here: the runner moves the messages, so this is testable with plain
message objects. This is the only place in the simulator that sees NED/FRD; every conversion goes
through services/mavlink/frames.py.
"""
from __future__ import annotations

import logging
import time
from collections import Counter

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from .mavlink_receiver import MavlinkReceiver
from .mavlink_streams import OnVehicle, TelemetryStreams
from .model import SimVehicle

log = logging.getLogger("aeroperception.sim.vehicle")

M = mavlink
Message = mavlink.MAVLink_message

class MavlinkModule(OnVehicle):
    def __init__(self, vehicle: SimVehicle, system_id: int = 1, component_id: int = M.MAV_COMP_ID_AUTOPILOT1):
        self.vehicle = vehicle
        self.streams = TelemetryStreams(vehicle, system_id, component_id)
        self.receiver = MavlinkReceiver(vehicle, self.streams, system_id, component_id)
        self.rx_types: Counter[str] = Counter()
        self.counters = self.receiver.counters
        self._reboots_seen = vehicle.reboots
        self._silent_until_ns = -1
        self._last_error_log_s = 0.0

    @property
    def rebooting(self) -> bool:
        """After a reboot the autopilot is silent for SIM_REBOOT_T: it neither sends nor listens."""
        if self.vehicle.reboots != self._reboots_seen:  # rebooted (by command or directly)
            self._reboots_seen = self.vehicle.reboots
            self._silent_until_ns = self.vehicle.time_ns + int(self.vehicle.params.SIM_REBOOT_T * 1e9)
            self.streams.reset()
        return self.vehicle.time_ns < self._silent_until_ns

    def handle(self, m: Message) -> list[Message]:
        """Process one received message; returns the replies. Never raises."""
        mtype = m.get_type()
        self.rx_types[mtype] += 1
        if self.rebooting:
            self.counters["ignored_while_rebooting"] += 1
            return []
        handler = self.receiver.handlers.get(mtype)
        if handler is None:
            self.counters["ignored"] += 1
            return []
        try:
            return handler(m)
        except Exception as e:  # a malformed but CRC-valid message must not stop the vehicle
            self.counters["handler_errors"] += 1
            if time.monotonic() - self._last_error_log_s > 1.0:
                self._last_error_log_s = time.monotonic()
                log.warning("dropped %s: %s: %s", mtype, type(e).__name__, e)
            return []

    def tick(self) -> list[Message]:
        """Telemetry due now (sim time), plus a STATUSTEXT when a failsafe fired."""
        return [] if self.rebooting else self.streams.due()

    def diagnostics(self) -> dict:
        """Flat counters (per-type receive counts are in `rx_types`)."""
        est = self.vehicle.estimator
        return {**self.counters, **est.counters, "vision_error_m": self.receiver.vision_error_m,
                "gps_denied": est.gps_denied, "position_valid": est.valid(self.vehicle.time_ns),
                "estimate_error_m": round(float(np.linalg.norm(self.vehicle.estimate.position_enu_m
                                                             - self.vehicle.state.position_enu_m)), 3), "last_reason": self.commander.last_reason,
                "setpoint_max_speed_mps": round(self.receiver.setpoint_max_speed_mps, 3), "time_boot_ms": self.streams.time_boot_ms,
                "rebooting": self.vehicle.time_ns < self._silent_until_ns}
