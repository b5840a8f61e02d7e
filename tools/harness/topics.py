"""Reading the stack's keys from outside it: a client session, liveliness, the next message on a key,
a rate over a window, and `Capture` (every message on some keys with its arrival time)."""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

import zenoh

from aeroperception.schemas import DiagnosticStatus, SchemaError, decode
from aeroperception.services.runtime.node import LIVELINESS_ROOT
from aeroperception.services.runtime.session import make_config, open_session

from .waiting import wait_until


def zenoh_client(endpoint: str, max_wait_s: float = 5.0) -> zenoh.Session:
    """A client session (the project's zenoh.json5, connect replaced by `endpoint`).
    The caller closes it."""
    session = open_session(make_config(None, endpoint, mode="client"), max_wait_s=max_wait_s)
    if session is None:
        raise RuntimeError(f"no Zenoh router reachable at {endpoint} within {max_wait_s} s")
    return session


def token_alive(session: zenoh.Session, service: str, vehicle: str = "default", timeout_s: float = 1.0) -> bool:
    """Whether the liveliness token aero/alive/<vehicle>/<service> exists right now."""
    replies = session.liveliness().get(f"{LIVELINESS_ROOT}/{vehicle}/{service}", timeout=timeout_s)
    return any(r.ok is not None for r in replies)


def latest(session: zenoh.Session, key: str, cls: type, timeout_s: float = 3.0,
           pred: Callable[[Any], bool] | None = None) -> Any:
    """The next message on `key` that decodes as `cls` (and satisfies `pred`) within timeout_s,
    else None. Payloads that do not decode are ignored."""
    got: list[Any] = []
    ev = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), cls)
        except SchemaError:
            return
        if not got and (pred is None or pred(msg)):
            got.append(msg)
            ev.set()

    sub = session.declare_subscriber(key, on_sample)
    try:
        ev.wait(timeout_s)
    finally:
        sub.undeclare()
    return got[0] if got else None


def wait_for_message(session: zenoh.Session, key: str, cls: type, pred: Callable[[Any], bool] | None = None,
                     timeout_s: float = 10.0) -> Any:
    """Like `latest`, but AssertionError when nothing matching came within timeout_s."""
    msg = latest(session, key, cls, timeout_s, pred)
    if msg is None:
        raise AssertionError(f"no matching {cls.__name__} on {key} within {timeout_s:.1f} s")
    return msg


def diag(session: zenoh.Session, name: str, timeout_s: float = 3.0) -> DiagnosticStatus:
    """The next diagnostics/<name>; AssertionError when none came within timeout_s."""
    d = latest(session, f"diagnostics/{name}", DiagnosticStatus, timeout_s)
    assert d is not None, f"no diagnostics/{name} within {timeout_s:g} s"
    return d


def sample_stream(session: zenoh.Session, key: str, cls: type, min_count: int, window_s: float,
                  timeout_s: float = 10.0) -> tuple[list[Any], float]:
    """Messages on `key` decoded as `cls`: wait for `min_count` (else fail after `timeout_s`), then
    count for `window_s`. Returns every message received and the rate over the window (Hz)."""
    msgs: list[Any] = []
    sub = session.declare_subscriber(key, lambda sample: msgs.append(decode(sample.payload.to_bytes(), cls)))
    try:
        wait_until(lambda: len(msgs) >= min_count, timeout_s, f"{min_count} {cls.__name__} on {key}")
        n0, t0 = len(msgs), time.monotonic()
        time.sleep(window_s)
        rate_hz = (len(msgs) - n0) / (time.monotonic() - t0)
    finally:
        sub.undeclare()
    return list(msgs), rate_hz


class Capture:
    """Every decoded message on some keys with the monotonic time it arrived: {name: [(t, msg)]}.

    `Capture(session, {"truth": ("sim/truth/state", VehicleState), ...})`; undecodable payloads are
    skipped; `with` closes it. Not the recorder service: nothing is written to disk."""

    def __init__(self, session: zenoh.Session, keys: dict[str, tuple[str, type]]):
        self.lock = threading.Lock()
        self.data: dict[str, list[tuple[float, Any]]] = {name: [] for name in keys}
        self.subs = [session.declare_subscriber(key, self._cb(name, cls)) for name, (key, cls) in keys.items()]
        self._feeds: list[tuple[list, Callable]] = []

    def feed(self, name: str, listeners: list[Callable[[float, Any], None]]) -> None:
        """Also capture as `name` what a source outside Zenoh hands its `listeners` (fn(time, msg))."""
        self.data[name] = []

        def add(t: float, msg: Any) -> None:
            with self.lock:
                self.data[name].append((t, msg))
        listeners.append(add)
        self._feeds.append((listeners, add))

    def _cb(self, name: str, cls: type):
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = decode(sample.payload.to_bytes(), cls)
            except SchemaError:
                return
            with self.lock:
                self.data[name].append((time.monotonic(), msg))
        return on_sample

    def since(self, name: str, t: float = 0.0) -> list[tuple[float, Any]]:
        """(arrival time, message) of those that arrived at or after `t`."""
        with self.lock:
            return [(ts, m) for ts, m in self.data[name] if ts >= t]

    def get(self, name: str, since: float = 0.0) -> list:
        """The messages (without times) that arrived at or after `since`."""
        with self.lock:
            return [m for ts, m in self.data[name] if ts >= since]

    def last(self, name: str):
        with self.lock:
            return self.data[name][-1][1] if self.data[name] else None

    def __enter__(self) -> "Capture":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for s in self.subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - the session may already be gone
                pass
        for listeners, add in self._feeds:
            if add in listeners:
                listeners.remove(add)
