"""Bounded waits for a condition: `poll_until` hands the caller the last value (falsy on timeout) to
decide on, `wait_until` fails naming what it waited for. Both poll a predicate; neither sleeps blind."""
from __future__ import annotations

import time
from typing import Any, Callable


def poll_until(pred: Callable[[], Any], timeout_s: float, interval_s: float = 0.05) -> Any:
    """pred()'s first truthy value within timeout_s, else its last (falsy) value."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value or time.monotonic() >= deadline:
            return value
        time.sleep(interval_s)


def wait_until(pred: Callable[[], Any], timeout_s: float = 10.0, what: str = "condition",
               interval_s: float = 0.05) -> Any:
    """pred()'s first truthy value within timeout_s; AssertionError naming `what` after it."""
    value = poll_until(pred, timeout_s, interval_s)
    if not value:
        raise AssertionError(f"timed out after {timeout_s:.1f} s waiting for {what}")
    return value
