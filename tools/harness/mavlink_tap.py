"""`MavlinkTap`: a UDP relay between a flight controller and fmu in the harness's own process, so a
test or a fault row can cut the FC link, speak to the FC as the companion, and check every setpoint
fmu sends it (finite, inside the speed envelope and the geofence)."""
from __future__ import annotations

import math
import select
import socket
import threading
import time
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import Vector3, VehicleState
from aeroperception.services.mavlink import frames, px4
from aeroperception.services.lib.geofence import Geofence

SAFE_SETPOINT_SPEED_MPS = 20.0       # a setpoint faster than this at the FC is unsafe


def msgid(pkt: bytes) -> int | None:
    """The message id of one MAVLink v1/v2 frame, read from its header (no parsing)."""
    if len(pkt) >= 10 and pkt[0] == 0xFD:
        return pkt[7] | pkt[8] << 8 | pkt[9] << 16
    if len(pkt) >= 6 and pkt[0] == 0xFE:
        return pkt[5]
    return None


SET_POSITION_TARGET_LOCAL_NED = mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED
LOCAL_POSITION_NED = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
COMMAND_ACK = mavlink.MAVLINK_MSG_ID_COMMAND_ACK
HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
_IGNORE = {  # type_mask bit -> field
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE: "x", mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE: "y",
    mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE: "z", mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE: "vx",
    mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE: "vy", mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE: "vz",
    mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE: "afx", mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE: "afy",
    mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE: "afz", mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE: "yaw",
    mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE: "yaw_rate",
}


HOLD_HERE_M = 1.0    # a position setpoint this close to where the FC says it is commands no motion


def setpoint_problem(m, fence: Geofence, floor_m: float = -1.0, here_enu_m: np.ndarray | None = None,
                     armed: bool = True) -> str | None:
    """Why a SET_POSITION_TARGET_LOCAL_NED the FC received is unsafe, or None: a used field not
    finite, a speed above SAFE_SETPOINT_SPEED_MPS, or, while the FC is `armed`, a position outside the
    fence or below `floor_m` (the FC's local frame; NED: z down) that is not where the FC says the
    vehicle is (`here_enu_m`, its LOCAL_POSITION_NED: a hold there moves nothing). PX4's estimate
    wanders off after losing GPS (57-100 m on the ground, disarmed): a hold at it flies nothing."""
    used = {f: getattr(m, f) for bit, f in _IGNORE.items() if not m.type_mask & bit}
    bad = [f for f, v in used.items() if not math.isfinite(v)]
    if bad:
        return f"non-finite {','.join(bad)}"
    v = [used.get(f, 0.0) for f in ("vx", "vy", "vz")]
    if math.hypot(*v) > SAFE_SETPOINT_SPEED_MPS:
        return f"speed {math.hypot(*v):.1f} m/s"
    if armed and all(f in used for f in ("x", "y", "z")):
        east, north, up = m.y, m.x, -m.z
        here = here_enu_m is not None and float(np.linalg.norm(np.asarray(here_enu_m) - [east, north, up])) < HOLD_HERE_M
        if not here and (math.hypot(east, north) > fence.radius_m or up > fence.max_altitude_m or up < floor_m):
            return f"position ({east:.1f}, {north:.1f}, {up:.1f}) ENU outside the fence"
    return None


class MavlinkTap:
    """A UDP relay between the FC (the built-in sim or PX4 SITL) and fmu, in this process.

    The FC sends to `sim_port`; the tap forwards to fmu's udpin port from a socket of its own and
    relays fmu's replies back. `cut` drops everything both ways (FC link loss), `cut_to_fc` only
    what fmu sends (the FC hears no setpoints; its own view is still tracked); `to_fc` injects a
    message to the FC as if from the companion; every setpoint fmu sends is decoded and checked
    (`setpoints`, `unsafe`); `stamps` per message id FC -> fmu give stream rates.
    """

    def __init__(self, sim_port: int, fmu_port: int, fence: Geofence | None = None):
        self.from_sim = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.from_sim.bind(("127.0.0.1", sim_port))
        self.to_fmu = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to_fmu.bind(("127.0.0.1", 0))
        self.fmu = ("127.0.0.1", fmu_port)
        self.fence = fence or Geofence.from_params()
        self.floor_m = -1.0          # a setpoint below this (ENU up, the FC's local frame) is unsafe
        self.sim_addr: tuple[str, int] | None = None
        self.cut = threading.Event()          # both ways (FC link loss)
        self.cut_to_fc = threading.Event()    # companion -> FC only (the FC hears no setpoints)
        self.lock = threading.Lock()
        self.setpoints: list[tuple[float, Any]] = []   # (monotonic, message) last few minutes
        self.unsafe: list[tuple[float, str]] = []
        self.setpoints_total = 0
        self.stamps: dict[int, list[float]] = {LOCAL_POSITION_NED: []}   # rx time of tracked ids
        self.acks: list[tuple[float, int, int]] = []   # (time, command, result) the FC sent
        # The FC's own view (LOCAL_POSITION_NED + HEARTBEAT) as VehicleState: the truth when
        # Zenoh is down (router kill); in the sim its estimate is the truth plus noise.
        self.fc_track: list[tuple[float, VehicleState]] = []
        self.fc_armed, self.fc_mode = False, ""   # the FC's HEARTBEAT
        self.dropped = 0
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self.enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink-tap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.from_sim, self.to_fmu], [], [], 0.1)
            except (OSError, ValueError):
                return
            for s in ready:
                try:
                    pkt, addr = s.recvfrom(65535)
                except OSError:
                    continue
                now = time.monotonic()
                try:
                    if s is self.from_sim:   # the FC's view is tracked even while the link is cut
                        self.sim_addr = addr
                        mid = msgid(pkt)
                        if mid in self.stamps:
                            with self.lock:
                                self.stamps[mid].append(now)
                                if len(self.stamps[mid]) > 20000:
                                    del self.stamps[mid][:10000]
                        if mid in (LOCAL_POSITION_NED, HEARTBEAT):
                            self._fc_state(pkt, now)
                        elif mid == COMMAND_ACK:
                            for m in self._parse(pkt):
                                with self.lock:
                                    self.acks.append((now, m.command, m.result))
                        if self.cut.is_set():
                            self.dropped += 1
                        else:
                            self.to_fmu.sendto(pkt, self.fmu)
                    elif self.cut.is_set() or self.cut_to_fc.is_set():
                        self.dropped += 1
                    else:
                        if msgid(pkt) == SET_POSITION_TARGET_LOCAL_NED:
                            self._check(pkt, now)
                        if self.sim_addr:
                            self.from_sim.sendto(pkt, self.sim_addr)
                except OSError:
                    pass

    def _parse(self, pkt: bytes) -> list:
        p = self._parser
        p.buf, p.buf_index, p.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
        try:
            msgs = p.parse_buffer(pkt) or []
        except Exception:  # noqa: BLE001 - a frame pymavlink cannot parse is nothing we track
            return []
        return [m for m in msgs if m is not None and m.get_type() != "BAD_DATA"]

    def _fc_state(self, pkt: bytes, now: float) -> None:
        for m in self._parse(pkt):
            if m.get_type() == "HEARTBEAT" and m.autopilot != mavlink.MAV_AUTOPILOT_INVALID:   # the autopilot's own
                self.fc_armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self.fc_mode = px4.decode(m.custom_mode)
            elif m.get_type() == "LOCAL_POSITION_NED":
                vs = VehicleState(position_m=Vector3.from_array(frames.ned_to_enu(np.array([m.x, m.y, m.z]))),
                                  velocity_mps=Vector3.from_array(frames.ned_to_enu(np.array([m.vx, m.vy, m.vz]))),
                                  armed=self.fc_armed, flight_mode=self.fc_mode, connected=True)
                with self.lock:
                    self.fc_track.append((now, vs))
                    if len(self.fc_track) > 20000:
                        del self.fc_track[:10000]

    def fc_track_since(self, t: float) -> list[tuple[float, VehicleState]]:
        with self.lock:
            return [(ts, m) for ts, m in self.fc_track if ts >= t]

    def _check(self, pkt: bytes, now: float) -> None:
        for m in self._parse(pkt):
            if m.get_type() != "SET_POSITION_TARGET_LOCAL_NED":
                continue
            with self.lock:
                here = self.fc_track[-1][1].position_m.to_array() if self.fc_track else None
            why = setpoint_problem(m, self.fence, self.floor_m, here, self.fc_armed)
            with self.lock:
                self.setpoints_total += 1
                self.setpoints.append((now, m))
                if len(self.setpoints) > 30000:
                    del self.setpoints[:15000]
                if why:
                    self.unsafe.append((now, why))

    def setpoints_since(self, t: float) -> list:
        with self.lock:
            return [m for ts, m in self.setpoints if ts >= t]

    def unsafe_since(self, t: float) -> list[str]:
        with self.lock:
            return [why for ts, why in self.unsafe if ts >= t]

    def rate_hz(self, mid: int, t0: float, t1: float) -> float:
        with self.lock:
            n = sum(1 for ts in self.stamps[mid] if t0 <= ts < t1)
        return n / max(t1 - t0, 1e-6)

    def to_fc(self, msg) -> None:
        """Send one MAVLink message to the FC as the companion would (replies go to fmu)."""
        if self.sim_addr is None:
            raise RuntimeError("the FC has not sent anything yet")
        self.from_sim.sendto(msg.pack(self.enc), self.sim_addr)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.from_sim.close()
        self.to_fmu.close()
