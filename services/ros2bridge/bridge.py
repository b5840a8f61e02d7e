"""One of our keys to one ROS topic and one ROS topic to one of our keys, without Zenoh: the
bridge's configuration, the per-topic gate out (nobody on the ROS side listening: nothing
converted; faster than max_rate_hz: dropped, never queued; an unconvertible sample: counted and
reported, never fatal) and the per-topic gate in (a ROS sample that does not deserialize or
convert: counted and reported, dropped, never fatal).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from aeroperception.services.lib.optical import r_body_optical
from aeroperception.services.runtime import param

from .convert import CATALOG
from .inbound import INFO, Source, ros_type_for
from .rmw import attachment

SIDES = ("left", "right")
MOUNT_FIELDS = ("x_m", "y_m", "z_m", "roll_deg", "pitch_deg", "yaw_deg")


@dataclass(frozen=True)
class RosBridgeConfig:
    """Every parameter of contract.PARAMS (all read at start: the ROS entities are declared from them)."""

    domain_id: int = param("domain_id")
    namespace: str = param("namespace")
    node_name: str = param("node_name")
    topics: str = param("topics")
    max_rate_hz: float = param("max_rate_hz")
    goal_topic: str = param("goal_topic")
    inputs: str = param("inputs")
    left_mount_x_m: float = param("left_mount_x_m")
    left_mount_y_m: float = param("left_mount_y_m")
    left_mount_z_m: float = param("left_mount_z_m")
    left_mount_roll_deg: float = param("left_mount_roll_deg")
    left_mount_pitch_deg: float = param("left_mount_pitch_deg")
    left_mount_yaw_deg: float = param("left_mount_yaw_deg")
    right_mount_x_m: float = param("right_mount_x_m")
    right_mount_y_m: float = param("right_mount_y_m")
    right_mount_z_m: float = param("right_mount_z_m")
    right_mount_roll_deg: float = param("right_mount_roll_deg")
    right_mount_pitch_deg: float = param("right_mount_pitch_deg")
    right_mount_yaw_deg: float = param("right_mount_yaw_deg")

    def sources(self, feedable: list[str]) -> list[Source]:
        """The ROS topics `inputs` ("ros_topic=our_key,...") names, each with the ROS type that
        feeds its key; ValueError naming an entry that is malformed, a key not in `feedable` (the
        contract's OUTPUTS), a key fed twice, a topic the bridge itself publishes (a loop), or a
        camera mount set for a camera whose info is not bridged (it would be ignored)."""
        out: list[Source] = []
        for entry in (e.strip() for e in self.inputs.split(",")):
            if not entry:
                continue
            topic, eq, key = (s.strip() for s in entry.partition("="))
            if not eq or not topic or not key:
                raise ValueError(f"inputs: {entry!r} is not ros_topic=our_key")
            if key not in feedable:
                raise ValueError(f"inputs: {key} cannot be fed from ROS; choose from {', '.join(feedable)}")
            if any(s.key == key for s in out):
                raise ValueError(f"inputs: {key} is fed by two topics")
            name = topic if topic.startswith("/") else ros_name(self.namespace, topic)
            if name in self.published_topics():
                raise ValueError(f"inputs: {name} is published by this bridge (topics): bridging it back is a loop")
            out.append(Source(name, key, ros_type_for(key, name)))
        infos = {s.key.split("/")[2] for s in out if s.ros_type == INFO}
        unused = [f"{side}_mount_{f}" for side in SIDES if side not in infos for f in MOUNT_FIELDS
                  if getattr(self, f"{side}_mount_{f}") != 0.0]
        if unused:
            raise ValueError(f"{', '.join(unused)}: no sensors/camera/{unused[0].split('_')[0]}/info in inputs, "
                             "so no camera model to place on the body")
        return out

    def published_topics(self) -> set[str]:
        topics = {ros_name(self.namespace, CATALOG[k].topic) for k in self.bridged_keys()}
        return topics | ({ros_name(self.namespace, self.goal_topic)} if self.goal_topic.strip("/") else set())

    def t_body_camera(self, side: str) -> np.ndarray:
        """4x4 body FLU <- the camera's optical frame, from the side's mount parameters."""
        m = [getattr(self, f"{side}_mount_{f}") for f in MOUNT_FIELDS]
        t = np.eye(4)
        t[:3, :3] = r_body_optical(*np.radians(m[3:]))
        t[:3, 3] = m[:3]
        return t

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


class InputBridge:
    """`on_sample(cdr)` for each sample of one configured ROS topic: deserialized with
    `deserialize(cdr, ros_type)`, converted with `convert` and handed to `publish`. A sample that
    fails either step is counted and reported (`report(topic, error)`), and dropped."""

    def __init__(self, source: Source, deserialize: Callable[[bytes, str], Any], convert: Callable[[Any], Any],
                 publish: Callable[[Any], None], report: Callable[[str, str], None]):
        self.source = source
        self.deserialize, self.convert, self.publish, self.report = deserialize, convert, publish, report
        self.received = self.errors = 0
        self.convert_ms = 0.0            # the last sample's deserialize + convert time

    def on_sample(self, cdr: bytes) -> None:
        self.received += 1
        t0 = time.perf_counter()
        try:
            msg = self.convert(self.deserialize(cdr, self.source.ros_type))
        except Exception as e:  # noqa: BLE001 - one bad ROS sample is counted, not fatal
            self.errors += 1
            self.report(self.source.topic, f"cannot convert {self.source.ros_type} to {self.source.key}: "
                                           f"{str(e) or type(e).__name__}")
            return
        self.convert_ms = (time.perf_counter() - t0) * 1e3
        self.publish(msg)
