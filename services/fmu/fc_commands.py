"""A command to the flight controller and its verdict, free of sockets and Zenoh: COMMAND_LONG,
its COMMAND_ACK, then the state the command asks for seen in the FC's heartbeat. A refusal
names the FC's reason (the warning STATUSTEXT it sent around the ACK, PX4's "Arming denied:
..."); a TEMPORARILY_REJECTED OFFBOARD request is re-sent while time is left (PX4 refuses
OFFBOARD until the setpoint stream has run a while).

fmu's arm / set_mode / emergency-stop queryables ask through FcCommands; main.py only gives it
the way to send and feeds it the FC's ACKs and STATUSTEXTs.
"""
from __future__ import annotations

import time
from collections import deque
from typing import Callable

from pymavlink.dialects.v20 import common as mavlink

from .logic import CommandWaiter, ack_name

RETRY_S = 0.3       # re-send a TEMPORARILY_REJECTED OFFBOARD request after this


class FcCommands:
    """send(command, params7): put one COMMAND_LONG on the link; link_fresh(): the FC is heard."""

    def __init__(self, send: Callable[[int, list[float]], None], link_fresh: Callable[[], bool], fcu_url: str,
                 counters: dict[str, int], clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep):
        self.send, self.link_fresh, self.fcu_url, self.counters = send, link_fresh, fcu_url, counters
        self.clock, self.sleep = clock, sleep
        self.acks = CommandWaiter()
        self.statustexts: deque[tuple[float, int, str]] = deque(maxlen=16)  # (rx time, severity, text)

    def on_ack(self, m) -> None:
        """A COMMAND_ACK from the FC."""
        self.acks.on_ack(m)

    def on_statustext(self, severity: int, text: str) -> None:
        """A STATUSTEXT from the FC (kept: it may be the reason for a refusal)."""
        self.statustexts.append((self.clock(), severity, text))

    def run(self, command: int, params: list[float], confirm: Callable[[], bool], timeout_s: float,
            retry_rejected: bool = False) -> tuple[bool, str]:
        """COMMAND_LONG, wait for its ACK, then for `confirm()` (heartbeat state) within timeout.
        `retry_rejected`: re-send every RETRY_S while the FC answers TEMPORARILY_REJECTED."""
        if not self.link_fresh():
            return False, f"no link to the flight controller ({self.fcu_url})"
        deadline = self.clock() + timeout_s
        p = params + [0.0] * (7 - len(params))
        while True:
            sent_s = self.clock()
            ev, box = self.acks.expect(command)
            self.send(command, p)
            if not ev.wait(max(0.0, deadline - self.clock())):
                return False, f"no COMMAND_ACK within {timeout_s:.1f} s"
            if box[0] == mavlink.MAV_RESULT_ACCEPTED:
                break
            if (retry_rejected and box[0] == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                    and self.clock() + RETRY_S < deadline):
                self.counters["commands_retried"] += 1
                self.sleep(RETRY_S)
                continue
            reason = self.refusal_reason(sent_s)
            return False, f"flight controller answered {ack_name(box[0])}" + (f": {reason}" if reason else "")
        while self.clock() < deadline:
            if confirm():
                return True, "confirmed by heartbeat"
            self.sleep(0.02)
        return False, "accepted but not confirmed by the heartbeat in time"

    def refusal_reason(self, since_s: float, wait_s: float = 0.3) -> str:
        """The warning STATUSTEXT the FC sent with a refusal (before or just after the ACK), or ''."""
        end = self.clock() + wait_s
        while True:
            texts = [text for t, sev, text in list(self.statustexts)
                     if t >= since_s and sev <= mavlink.MAV_SEVERITY_WARNING]
            if texts or self.clock() >= end:
                return texts[-1] if texts else ""
            self.sleep(0.02)
