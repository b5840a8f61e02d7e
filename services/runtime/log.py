"""Structured JSON-lines logging to stderr: one object per line with service, level, event, fields.

Why not `logging`: every line must be machine-readable with arbitrary fields, and bad-input
warnings must be rate-limited per key so a flood of garbage cannot flood the log.
"""
from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any, TextIO

LEVELS = {"debug": 10, "info": 20, "warn": 30, "error": 40}


class Logger:
    def __init__(self, service: str, level: str = "info", stream: TextIO | None = None):
        self.service = service
        self.threshold = LEVELS.get(level, 20)
        self.stream = stream or sys.stderr
        # Re-entrant: code that logs from a signal handler runs on the main thread, possibly while
        # that thread is inside log() already; a plain Lock would deadlock it.
        self._lock = threading.RLock()
        self._last_by_key: dict[str, float] = {}

    def log(self, level: str, event: str, **fields: Any) -> None:
        if LEVELS[level] < self.threshold:
            return
        rec = {"ts": round(time.time(), 6), "service": self.service, "level": level, "event": event}
        rec.update(fields)
        line = json.dumps(rec, default=str, separators=(",", ":"))
        with self._lock:
            try:
                self.stream.write(line + "\n")
                self.stream.flush()
            except (ValueError, OSError, RuntimeError):
                pass  # stderr closed during shutdown (or re-entered): nothing useful left to do

    def debug(self, event: str, **f: Any) -> None:
        self.log("debug", event, **f)

    def info(self, event: str, **f: Any) -> None:
        self.log("info", event, **f)

    def warn(self, event: str, **f: Any) -> None:
        self.log("warn", event, **f)

    def error(self, event: str, **f: Any) -> None:
        self.log("error", event, **f)

    def throttled(self, level: str, key: str, event: str, period_s: float = 1.0, **f: Any) -> bool:
        """Log at most once per `period_s` for `key`; returns whether it logged."""
        now = time.monotonic()
        with self._lock:
            last = self._last_by_key.get(key, -1e9)
            if now - last < period_s:
                return False
            self._last_by_key[key] = now
        self.log(level, event, key=key, **f)
        return True
