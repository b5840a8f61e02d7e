"""SIGINT/SIGTERM handling that cannot deadlock.

A handler that calls threading.Event.set() runs on the main thread between bytecodes; if the
main thread was inside that same Event's wait() (holding its Condition lock) the handler blocks
forever — seen in `aero up` ignoring SIGTERM. So the handler only records the signal, and a
small watcher thread forwards it to an Event from an ordinary thread context.
"""
from __future__ import annotations

import signal
import threading


class ShutdownFlag:
    def __init__(self, event: threading.Event | None = None, poll_s: float = 0.05) -> None:
        self.event = event or threading.Event()
        self.signal_name: str | None = None
        self._poll_s = poll_s

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

    def __bool__(self) -> bool:
        return self.signal_name is not None or self.event.is_set()
