"""Logger: JSON lines with fields, level threshold, per-key throttling, re-entrancy, a closed stream."""
from __future__ import annotations

import io
import json
import threading
import time



from aeroperception.services.runtime import (
    Logger,
)


def lines(buf: io.StringIO) -> list[dict]:
    return [json.loads(line) for line in buf.getvalue().splitlines()]


def test_logger_writes_json_lines_with_fields():
    buf = io.StringIO()
    log = Logger("planner", "info", stream=buf)
    log.info("started", rate_hz=50, where={"x": 1.0}, obj=object())
    log.debug("hidden")
    log.warn("slow", ms=12.5)
    log.error("failed", error="x")
    recs = lines(buf)
    assert [r["event"] for r in recs] == ["started", "slow", "failed"]
    assert [r["level"] for r in recs] == ["info", "warn", "error"]
    first = recs[0]
    assert first["service"] == "planner" and first["rate_hz"] == 50 and first["where"] == {"x": 1.0}
    assert isinstance(first["obj"], str)  # not JSON-serializable: str()
    assert abs(first["ts"] - time.time()) < 5


def test_logger_levels_threshold():
    buf = io.StringIO()
    log = Logger("s", "warn", stream=buf)
    log.info("no")
    log.warn("yes")
    assert [r["event"] for r in lines(buf)] == ["yes"]
    buf = io.StringIO()
    Logger("s", "debug", stream=buf).debug("dbg")
    assert lines(buf)[0]["level"] == "debug"


def test_logger_throttles_per_key():
    buf = io.StringIO()
    log = Logger("s", stream=buf)
    logged = [log.throttled("warn", "bad:a", "invalid", period_s=0.2, n=i) for i in range(100)]
    assert logged.count(True) == 1
    assert log.throttled("warn", "bad:b", "invalid", period_s=0.2)  # another key logs
    time.sleep(0.25)
    assert log.throttled("warn", "bad:a", "invalid", period_s=0.2)  # period over: logs again
    recs = lines(buf)
    assert [r["key"] for r in recs] == ["bad:a", "bad:b", "bad:a"]
    assert recs[0]["n"] == 0


def test_logger_reentrant_call_does_not_deadlock():
    """A signal handler runs on the main thread, possibly inside log(): logging from it must not
    deadlock (simulated by a stream whose write logs again)."""

    class Reentrant(io.StringIO):
        inner = False

        def write(self, s):
            if not self.inner:
                self.inner = True
                log.info("inner")
            return super().write(s)

    buf = Reentrant()
    log = Logger("s", stream=buf)
    t = threading.Thread(target=log.info, args=("outer",), daemon=True)
    t.start()
    t.join(2.0)
    assert not t.is_alive(), "Logger deadlocked on a re-entrant call"
    assert [r["event"] for r in lines(buf)] == ["inner", "outer"]


def test_logger_survives_closed_stream():
    buf = io.StringIO()
    log = Logger("s", stream=buf)
    buf.close()
    log.error("after_close")  # must not raise
