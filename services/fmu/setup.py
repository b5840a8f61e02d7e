"""When fmu (re)does the flight controller link's set-up, free of sockets and Zenoh: the
stream rates and home at the first autopilot heartbeat, again after the FC rebooted (at most
once a second), home asked again every `home_request_period_s` until the FC sent one, and the
FC's local origin asked (once a second at most) while its ground truth comes without one.

The shell sends what each call returns (`Command`s: COMMAND_LONG id + params) and logs the
reboot reason it returns. It must never send anything itself.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mavlink

from .link import RebootWatch

STREAMS_HZ = {  # what we ask the FC for (SET_MESSAGE_INTERVAL); PX4 onboard links honour it
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 50,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 1,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 100,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 1,
    mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 1,
}
SETUP_MIN_INTERVAL_S = 1.0     # a reboot shows as a heartbeat gap and as time_boot_ms going back: one set-up
ORIGIN_REQUEST_PERIOD_S = 1.0


@dataclass(frozen=True)
class Command:
    """A COMMAND_LONG to send without waiting for its ACK (params beyond those given are 0)."""

    command: int
    params: tuple[float, ...] = ()

    def params7(self) -> list[float]:
        return list(self.params) + [0.0] * (7 - len(self.params))


def request_message(msg_id: int) -> Command:
    return Command(mavlink.MAV_CMD_REQUEST_MESSAGE, (msg_id,))


@dataclass
class Setup:
    """What to send now, and why the set-up was redone ('' unless the FC rebooted)."""

    commands: list[Command] = field(default_factory=list)
    rebooted: str = ""


class LinkSetup:
    """Times are monotonic seconds. `home_known`: the FC has sent a HOME_POSITION."""

    def __init__(self, reboot_gap_s: float, ground_truth_rate_hz: float, home_request_period_s: float):
        self.reboots = RebootWatch(reboot_gap_s)
        self.ground_truth_rate_hz = ground_truth_rate_hz
        self.home_request_period_s = home_request_period_s
        self.streams_requested = False
        self.last_setup_s = -math.inf
        self.home_requested_s = -math.inf     # last MAV_CMD_REQUEST_MESSAGE(HOME_POSITION)
        self.origin_requested_s = -math.inf   # last MAV_CMD_REQUEST_MESSAGE(GPS_GLOBAL_ORIGIN)
        self.counters = {"reboots_detected": 0, "link_setups": 0}

    def on_heartbeat(self, now_s: float, home_known: bool) -> Setup:
        """An autopilot heartbeat: the first one sets the link up; one after a gap redoes it."""
        why = self.reboots.on_heartbeat(now_s)
        if not self.streams_requested:
            return Setup(self._request_streams(now_s, home_known))
        return self._rebooted(why, now_s, home_known) if why else Setup()

    def on_boot_time(self, time_boot_ms: int, now_s: float, home_known: bool) -> Setup:
        """A message's time_boot_ms: going back means the FC rebooted."""
        why = self.reboots.on_boot_time(time_boot_ms)
        return self._rebooted(why, now_s, home_known) if why and self.streams_requested else Setup()

    def home_due(self, now_s: float) -> list[Command]:
        """Each second while the link is fresh and the FC has not sent a home: ask again when due."""
        if not self.streams_requested or now_s - self.home_requested_s < self.home_request_period_s:
            return []
        return [self._request_home(now_s)]

    def origin_missing(self, now_s: float) -> list[Command]:
        """Ground truth came without a local origin to place it: ask for the origin when due."""
        if now_s - self.origin_requested_s <= ORIGIN_REQUEST_PERIOD_S:
            return []
        self.origin_requested_s = now_s
        return [request_message(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)]

    def _rebooted(self, why: str, now_s: float, home_known: bool) -> Setup:
        """The FC restarted (or vanished for reboot_gap_s): it is back at its default stream rates
        and may have a new home, so redo the link set-up."""
        if now_s - self.last_setup_s < SETUP_MIN_INTERVAL_S:
            return Setup()
        self.counters["reboots_detected"] += 1
        return Setup(self._request_streams(now_s, home_known) + [self._request_home(now_s)], rebooted=why)

    def _request_streams(self, now_s: float, home_known: bool) -> list[Command]:
        self.streams_requested = True
        self.last_setup_s = now_s
        self.counters["link_setups"] += 1
        streams = dict(STREAMS_HZ)
        if self.ground_truth_rate_hz > 0:
            streams[mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION] = self.ground_truth_rate_hz
        out = [Command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / hz)) for msg_id, hz in streams.items()]
        if not home_known:
            out.append(self._request_home(now_s))
        return out

    def _request_home(self, now_s: float) -> Command:
        self.home_requested_s = now_s
        return request_message(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
