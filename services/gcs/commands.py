"""COMMAND_LONG / COMMAND_INT handling (no Zenoh): every command gets exactly one COMMAND_ACK, the
final one, with the real outcome, as PX4 answers:

- ACCEPTED once the stack has done it (a mode change: once the flight controller reports the
  new mode, which fmu/srv/set_mode waits for);
- DENIED when the stack refused it, FAILED when the call into the stack failed or timed out;
  either way a STATUSTEXT with the reason goes to the asker first (PX4 reports refused mode
  changes the same way), so the operator sees why;
- never MAV_RESULT_IN_PROGRESS: PX4 sends it only for long-running operations (calibration),
  and MAVSDK treats an IN_PROGRESS answer to a mode change as the outcome (UNKNOWN).

A retransmission of a command still running (MAVSDK retries after 0.5 s, up to 3 times) is not
executed again and not answered: the final ACK answers the retries too, because MAVSDK matches
an ACK by command id. The stack answers within ~1 s in practice; after `timeout_s` (tick) the
command is answered FAILED.

The stack is reached through `ops` (see Ops, ops.StackOps): arm, set_mode, mission_command,
takeoff, goto, mission_start, change_speed; each answers done(Outcome) once, maybe later
(Outcome.failed: the call itself failed, not a refusal).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Protocol

from pymavlink.dialects.v20 import common as M

from aeroperception.services.mavlink import frames, px4

from .home import Home
from .mission_speed import SPEED_DEFAULT, change_speed_value
from .ops import Done, Outcome

FORCE_MAGIC = 21196


class Ops(Protocol):
    def arm(self, arm: bool, force: bool, done: Done) -> None: ...
    def set_mode(self, mode: str, done: Done) -> None: ...
    def mission_command(self, command: str, done: Done) -> None: ...
    def mission_start(self, done: Done) -> None: ...
    def takeoff(self, altitude_m: float | None, done: Done) -> None: ...
    def goto(self, enu: tuple[float, float, float], yaw_rad: float | None, done: Done) -> None: ...
    def change_speed(self, speed_mps: float | None, done: Done) -> None: ...   # None = the default


@dataclass
class Pending:
    command: int
    peer: tuple[int, int]
    started_s: float
    retransmissions: int = 0


@dataclass
class Command:
    """COMMAND_LONG and COMMAND_INT normalised: params 1-7 (x/y in degrees for COMMAND_INT)."""

    command: int
    params: tuple[float, ...]
    peer: tuple[int, int]
    frame: int = M.MAV_FRAME_GLOBAL

    @classmethod
    def from_msg(cls, msg) -> "Command":
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        if msg.get_type() == "COMMAND_INT":
            x = msg.x / 1e7 if msg.frame not in (M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_ENU) else msg.x / 1e4
            y = msg.y / 1e7 if msg.frame not in (M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_ENU) else msg.y / 1e4
            if msg.x == 0 and msg.y == 0:
                x = y = math.nan
            return cls(msg.command, (msg.param1, msg.param2, msg.param3, msg.param4, x, y, msg.z), peer, msg.frame)
        return cls(msg.command, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                                 msg.param7), peer)


class CommandHandler:
    def __init__(self, send: Callable, ops: Ops, home: Home, *,
                 position_enu: Callable[[], tuple[float, float, float]],
                 request_message: Callable[[int, float], int],
                 set_interval: Callable[[int, float], bool],
                 set_current: Callable[[int], bool],
                 notify: Callable[[str, tuple[int, int]], None] | None = None):
        self.send = send
        self.ops = ops
        self.home = home
        self.position_enu = position_enu
        self.request_message = request_message
        self.set_interval = set_interval
        self.set_current = set_current
        self.notify = notify or (lambda text, peer: None)
        self.pending: dict[tuple[int, tuple[int, int]], Pending] = {}
        self.results: dict[str, int] = {}
        self.retransmissions = 0

    def ack(self, command: int, result: int, peer: tuple[int, int], progress: int = 0) -> None:
        name = M.enums["MAV_RESULT"][result].name if result in M.enums["MAV_RESULT"] else str(result)
        self.results[name] = self.results.get(name, 0) + 1
        self.send(M.MAVLink_command_ack_message(command, result, progress, 0, peer[0], peer[1]))

    # ------------------------------------------------------------ entry points

    def on_set_mode(self, msg, now_s: float) -> None:
        """SET_MODE (the legacy message): its COMMAND_ACK once the stack has answered; DENIED at once
        for a mode we do not know."""
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mode = mode_from_custom_mode(msg.base_mode, msg.custom_mode)
        if mode is None:
            self.ack(M.MAVLINK_MSG_ID_SET_MODE, M.MAV_RESULT_DENIED, peer)
            return
        self.ops.set_mode(mode, lambda outcome: self.ack(
            M.MAVLINK_MSG_ID_SET_MODE, M.MAV_RESULT_ACCEPTED if outcome.ok else M.MAV_RESULT_DENIED, peer))

    def handle(self, msg, now_s: float) -> None:
        c = Command.from_msg(msg)
        key = (c.command, c.peer)
        if key in self.pending:
            # A retransmission while the first one runs: not run twice, answered by the final ACK.
            self.pending[key].retransmissions += 1
            self.retransmissions += 1
            return
        try:
            self._dispatch(c, now_s)
        except Exception as e:  # noqa: BLE001 - one bad command must not kill the link
            self.pending.pop(key, None)
            self.ack(c.command, M.MAV_RESULT_FAILED, c.peer)
            raise e

    def _async(self, c: Command, now_s: float, start: Callable[[Done], None]) -> None:
        key = (c.command, c.peer)
        self.pending[key] = Pending(c.command, c.peer, now_s)

        def done(outcome: Outcome) -> None:
            if self.pending.pop(key, None) is None:
                return   # already answered FAILED by tick()
            if outcome.ok:
                self.ack(c.command, M.MAV_RESULT_ACCEPTED, c.peer)
                return
            self.notify(f"{command_name(c.command)} {'failed' if outcome.failed else 'denied'}: {outcome.message}",
                        c.peer)
            self.ack(c.command, M.MAV_RESULT_FAILED if outcome.failed else M.MAV_RESULT_DENIED, c.peer)

        start(done)

    def _dispatch(self, c: Command, now_s: float) -> None:
        p = c.params
        cmd = c.command
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] not in (0.0, 1.0):
                self.ack(cmd, M.MAV_RESULT_DENIED, c.peer)
                return
            self._async(c, now_s, lambda d: self.ops.arm(p[0] == 1.0, p[1] == FORCE_MAGIC, d))
        elif cmd == M.MAV_CMD_DO_SET_MODE:
            mode = mode_from_set_mode(_int(p[0]), _int(p[1]), _int(p[2]))
            if mode is None:
                self.ack(cmd, M.MAV_RESULT_DENIED, c.peer)
                return
            self._async(c, now_s, lambda d: self.ops.set_mode(mode, d))
        elif cmd == M.MAV_CMD_MISSION_START:
            self._async(c, now_s, self.ops.mission_start)
        elif cmd == M.MAV_CMD_NAV_TAKEOFF:
            alt = p[6] - self.home.alt_m if math.isfinite(p[6]) else None
            if alt is not None and alt <= 0.2:
                alt = None  # PX4: an altitude at or below home means "the default"
            elif alt is not None:
                alt = self.home.local_z(alt)
            self._async(c, now_s, lambda d: self.ops.takeoff(alt, d))
        elif cmd == M.MAV_CMD_NAV_LAND:
            self._async(c, now_s, lambda d: self.ops.mission_command("LAND", d))
        elif cmd == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._async(c, now_s, lambda d: self.ops.mission_command("RTL", d))
        elif cmd == M.MAV_CMD_DO_REPOSITION:
            cur = self.position_enu()
            lat, lon, alt = p[4], p[5], p[6]
            if math.isfinite(lat) and math.isfinite(lon):
                rel = (alt - self.home.alt_m) if math.isfinite(alt) else cur[2]
                if c.frame in (M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
                    rel = alt if math.isfinite(alt) else cur[2]
                target = self.home.to_enu(lat, lon, rel)
            else:
                target = (cur[0], cur[1], self.home.local_z(alt - self.home.alt_m) if math.isfinite(alt) else cur[2])
            yaw = float(frames.yaw_ned_to_enu(math.radians(p[3]))) if math.isfinite(p[3]) else None
            self._async(c, now_s, lambda d: self.ops.goto(target, yaw, d))
        elif cmd == M.MAV_CMD_DO_CHANGE_SPEED:
            # The planner's live speed limit (PLN_MAX_VELOCITY); see mission_speed.change_speed_value.
            if math.isfinite(p[0]) and int(p[0]) in (2, 3) and int(p[0]) == p[0]:
                self.ack(cmd, M.MAV_RESULT_UNSUPPORTED, c.peer)   # no separate climb/descent limit
                return
            try:
                speed = change_speed_value(p[0], p[1])
            except ValueError:
                self.ack(cmd, M.MAV_RESULT_DENIED, c.peer)
                return
            if speed is None:
                self.ack(cmd, M.MAV_RESULT_ACCEPTED, c.peer)      # -1: no change
                return
            target = None if speed == SPEED_DEFAULT else speed
            self._async(c, now_s, lambda d: self.ops.change_speed(target, d))
        elif cmd == M.MAV_CMD_REQUEST_PROTOCOL_VERSION:
            self.ack(cmd, M.MAV_RESULT_ACCEPTED, c.peer)
        elif cmd == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self.ack(cmd, M.MAV_RESULT_ACCEPTED, c.peer)
            self.request_message(M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0)
        elif cmd == M.MAV_CMD_REQUEST_MESSAGE:
            if not math.isfinite(p[0]):
                self.ack(cmd, M.MAV_RESULT_DENIED, c.peer)
                return
            result = self.request_message(int(p[0]), p[1])
            self.ack(cmd, result, c.peer)
        elif cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            ok = math.isfinite(p[0]) and math.isfinite(p[1]) and self.set_interval(int(p[0]), p[1])
            self.ack(cmd, M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_DENIED, c.peer)
        elif cmd == M.MAV_CMD_GET_HOME_POSITION:
            self.ack(cmd, M.MAV_RESULT_ACCEPTED, c.peer)
            self.request_message(M.MAVLINK_MSG_ID_HOME_POSITION, 0)
        elif cmd == M.MAV_CMD_DO_SET_MISSION_CURRENT:
            ok = math.isfinite(p[0]) and self.set_current(int(p[0]))
            self.ack(cmd, M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_DENIED, c.peer)
        else:
            self.ack(cmd, M.MAV_RESULT_UNSUPPORTED, c.peer)

    # ------------------------------------------------------------ timers

    def tick(self, now_s: float, timeout_s: float = 10.0) -> None:
        for key, pend in list(self.pending.items()):
            if now_s - pend.started_s > timeout_s:
                self.pending.pop(key)
                self.notify(f"{command_name(pend.command)} failed: no answer from the stack in {timeout_s:.0f} s",
                            pend.peer)
                self.ack(pend.command, M.MAV_RESULT_FAILED, pend.peer)


def command_name(command: int) -> str:
    """MAV_CMD_DO_SET_MODE -> "DO_SET_MODE" (the number if unknown)."""
    e = M.enums["MAV_CMD"].get(command)
    return e.name.removeprefix("MAV_CMD_") if e is not None else f"command {command}"

def _int(v: float, default: int = 0) -> int:
    """A float parameter as an integer; NaN/inf ("unused" in MAVLink) -> default."""
    return int(v) if math.isfinite(v) else default


def mode_from_set_mode(base_mode: int, custom_main: int, custom_sub: int) -> str | None:
    """DO_SET_MODE / SET_MODE (PX4 main + sub) -> our mode name, None if PX4 has no such mode."""
    if not base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return None
    name = px4.decode(px4.pack(custom_main, custom_sub))
    return None if name.startswith("PX4(") else name


def mode_from_custom_mode(base_mode: int, custom_mode: int) -> str | None:
    main, sub = px4.unpack(custom_mode)
    return mode_from_set_mode(base_mode, main, sub)
