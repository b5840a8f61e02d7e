"""What the mission asks of others and keeps until it is answered: the flight-controller calls
(Bridge), one operator request's outcome (Outcome, instead of a callback chain) and a call to the
flight controller still awaiting its answer (FcRequest)."""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable, Protocol


class Bridge(Protocol):
    """The flight-controller calls the mission needs (fmu/srv/* in the running stack).
    `answer(success, message)` is called exactly once, later or immediately."""

    def arm(self, arm: bool, answer: Callable[[bool, str], None]) -> None: ...

    def set_mode(self, mode: str, answer: Callable[[bool, str], None]) -> None: ...


class Outcome:
    """What became of one operator request, one value the requester keeps instead of a callback:
    `result` is (ok, message) once settled, None while the flight controller has not answered
    yet (ARM, DISARM, TAKEOFF's arming, START's OFFBOARD); every other request settles at once.
    A queryable waits on it (`wait`), an action checks it on its tick. Settled once."""

    def __init__(self) -> None:
        self.result: tuple[bool, str] | None = None
        self._settled = threading.Event()

    def settle(self, ok: bool, message: str) -> None:
        if self.result is None:
            self.result = (ok, message)
            self._settled.set()

    @property
    def failed(self) -> bool:
        return self.result is not None and not self.result[0]

    def wait(self, timeout_s: float) -> bool:
        return self._settled.wait(timeout_s)


@dataclass
class FcRequest:
    """One call to the flight controller whose answer the FSM still expects: what was asked, the
    operator request it answers (if any) and what a success leads to ("takeoff": the arming
    before TAKEOFF; "mode": a mode we asked for, whose refusal is the ERROR path)."""

    call: str                          # "arm", "disarm" or the mode name
    outcome: Outcome | None = None
    then: str = ""                     # "" | "takeoff" | "mode"
