"""SIGINT/SIGTERM handling that cannot deadlock.

A handler that calls threading.Event.set() runs on the main thread between bytecodes; if the
main thread was inside that same Event's wait() (holding its Condition lock) the handler blocks
forever — seen in `aero up` ignoring SIGTERM. So the handler only records the signal, and a
small watcher thread forwards it to an Event from an ordinary thread context.

The Python handler itself runs only on the main thread, between bytecodes. The kernel may deliver
a process-directed signal to any thread (zenoh's threads included); the main thread then is not
interrupted, and if it sits in an untimed Event.wait() the handler never runs — a CI run caught
`aero run` ignoring SIGINT that way. So the main thread waits with `wait()`, which wakes every
`main_poll_s` to let a pending handler run; tools blocking on an Event use `wait_polling`.
"""
from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable


class ShutdownFlag:
    def __init__(self, event: threading.Event | None = None, poll_s: float = 0.05,
                 main_poll_s: float = 0.1) -> None:
        self.event = event or threading.Event()
        self.signal_name: str | None = None
        self._poll_s = poll_s
        self._main_poll_s = main_poll_s

    def install(self) -> "ShutdownFlag":
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._on_signal)
            signal.signal(signal.SIGTERM, self._on_signal)
        threading.Thread(target=self._forward, name="signal-forwarder", daemon=True).start()
        return self

    def _on_signal(self, signum, _frame) -> None:
        self.signal_name = signal.Signals(signum).name  # no locks in here, by design

    def _forward(self) -> None:
        while not self.event.wait(self._poll_s):
            if self.signal_name is not None:
                self.event.set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Event.wait() for the main thread: True once a stop is requested (signal or event),
        False after `timeout_s`."""
        def requested() -> bool:
            if self.signal_name is not None:
                self.event.set()  # ordinary code, not the handler: no deadlock
            return self.event.is_set()
        return wait_polling(self.event, timeout_s, self._main_poll_s, requested)

    def __bool__(self) -> bool:
        return self.signal_name is not None or self.event.is_set()


def wait_polling(event: threading.Event, timeout_s: float | None = None, poll_s: float = 0.1,
                 done: Callable[[], bool] | None = None) -> bool:
    """Event.wait() that wakes every `poll_s` so the main thread runs a signal handler left pending
    (ours, or Python's KeyboardInterrupt) when the kernel gave the signal to another thread.
    `done` (default event.is_set) is checked at each wake-up."""
    done = done or event.is_set
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while not done():
        step = poll_s if deadline is None else min(poll_s, deadline - time.monotonic())
        if step <= 0:
            return False
        event.wait(step)
    return True
