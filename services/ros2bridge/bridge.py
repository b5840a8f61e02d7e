"""One of our keys to one ROS topic, without Zenoh: the bridge's configuration and the per-topic
gate (nobody on the ROS side listening: nothing converted; faster than max_rate_hz: dropped, never
queued; an unconvertible sample: counted and reported, never fatal).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Callable

from aeroperception.services.runtime import param

from .convert import CATALOG
from .rmw import attachment


@dataclass(frozen=True)
class RosBridgeConfig:
    """Every parameter of contract.PARAMS (all read at start: the ROS entities are declared from them)."""

    domain_id: int = param("domain_id")
    namespace: str = param("namespace")
    node_name: str = param("node_name")
    topics: str = param("topics")
    max_rate_hz: float = param("max_rate_hz")
    goal_topic: str = param("goal_topic")

    def bridged_keys(self) -> list[str]:
        """The keys `topics` names; ValueError naming those that cannot be bridged (not in CATALOG)."""
        keys = [k.strip() for k in self.topics.split(",") if k.strip()]
        unknown = [k for k in keys if k not in CATALOG]
        if unknown:
            raise ValueError(f"topics: {', '.join(unknown)} cannot be bridged; choose from {', '.join(CATALOG)}")
        return keys


def ros_name(namespace: str, topic: str) -> str:
    return "/" + "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)


class TopicBridge:
    """`on_message(msg)` for each sample of `key`: converted with `convert`, serialized by
    `serialize(ros_msg, ros_type)` and handed to `put(cdr, attachment=...)` (the rmw_zenoh
    publisher's put) with the publication attachment; `on_matching(status)` is the publisher's
    matching listener. `report(key, error)` is told of a sample that cannot be converted."""

    def __init__(self, key: str, ros_type: str, convert: Callable[[Any], Any],
                 serialize: Callable[[Any, str], Any], put: Callable[..., None], max_rate_hz: float,
                 report: Callable[[str, str], None], clock: Callable[[], float] = time.monotonic):
        self.key, self.ros_type = key, ros_type
        self.convert, self.serialize, self.put, self.report, self.clock = convert, serialize, put, report, clock
        self.min_period_s = 1.0 / max_rate_hz
        self.gid = os.urandom(16)
        self.matching = False
        self.last_sent_s: float | None = None
        self.sent = self.dropped = self.unheard = self.errors = 0

    def on_matching(self, status: Any) -> None:
        self.matching = bool(status.matching)

    def on_message(self, msg: Any) -> None:
        if not self.matching:                # images and clouds cost CPU: only for a listener
            self.unheard += 1
            return
        now = self.clock()
        if self.last_sent_s is not None and now - self.last_sent_s < self.min_period_s:
            self.dropped += 1
            return
        self.last_sent_s = now
        try:
            cdr = self.serialize(self.convert(msg), self.ros_type)
        except Exception as e:  # noqa: BLE001 - one unconvertible sample is counted, not fatal
            self.errors += 1
            self.report(self.key, f"cannot convert to {self.ros_type}: {e}")
            return
        self.sent += 1
        self.put(bytes(cdr), attachment=attachment(self.sent, time.time_ns(), self.gid))
