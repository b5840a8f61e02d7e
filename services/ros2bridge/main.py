"""Process shell: our keys -> rmw_zenoh publications, one ROS goal topic -> the mission's goto action.

Topics and names are read at start (restart the service to change them). Every sample is
converted and sent from the subscriber's callback: a slow ROS consumer cannot queue anything
here, and `max_rate_hz` drops extra samples of a fast key instead of copying every image.
"""
from __future__ import annotations

import os
import time
from collections import Counter

import zenoh

from aeroperception.schemas import DiagnosticStatus, GoalReply
from aeroperception.services.runtime import Health, Service, run
from aeroperception.services.runtime.node import CallError

from . import contract
from .convert import CATALOG, GOAL_TYPE, Converter, conversion
from .rmw import RosNode, attachment, data_key, make_typestore

CDR = zenoh.Encoding("application/cdr")


def ros_name(namespace: str, topic: str) -> str:
    return "/" + "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)


class RosBridgeService(Service):
    """Publish a configurable set of keys as ROS 2 topics (rmw_zenoh wire format); take goals from ROS."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS

    def start(self) -> None:
        p = self.params
        keys = [k.strip() for k in p.topics.split(",") if k.strip()]
        unknown = [k for k in keys if k not in CATALOG]
        if unknown:
            raise ValueError(f"topics: {', '.join(unknown)} cannot be bridged; choose from {', '.join(CATALOG)}")
        self.store = make_typestore()
        self.conv = Converter(self.store)
        session = self.node.session
        self.ros = RosNode(domain_id=p.domain_id, zid=str(session.zid()), namespace=p.namespace, name=p.node_name)
        self.entities = [session.liveliness().declare_token(self.ros.token())]
        self.sent: Counter = Counter()
        self.dropped: Counter = Counter()
        self.errors: Counter = Counter()
        self.unheard: Counter = Counter()   # samples skipped: no ROS subscriber matched
        self.goals = Counter()
        self.last_goal = ""
        self.topics: dict[str, str] = {}
        entity = 0
        for key in keys:
            entity += 1
            self._bridge(key, entity)
        goal_topic = p.goal_topic.strip("/")
        if goal_topic:
            entity += 1
            self._goal_input(ros_name(p.namespace, goal_topic), entity)

    def _bridge(self, key: str, entity_id: int) -> None:
        b = CATALOG[key]
        topic = ros_name(self.params.namespace, b.topic)
        type_hash = self.store.hash_rihs01(b.ros_type)
        pub = self.node.session.declare_publisher(data_key(self.params.domain_id, topic, b.ros_type, type_hash),
                                                  encoding=CDR)
        self.entities.append(self.node.session.liveliness().declare_token(
            self.ros.endpoint_token("MP", entity_id, topic, b.ros_type, type_hash)))
        convert = conversion(self.conv, b)
        gid = os.urandom(16)
        min_period = 1.0 / self.params.max_rate_hz
        last = [0.0]
        # Nobody on the ROS side listening: no conversion at all (images and clouds cost CPU).
        matching = [pub.matching_status.matching]
        self.entities.append(pub.declare_matching_listener(lambda st: matching.__setitem__(0, st.matching)))

        def on_message(msg) -> None:
            if not matching[0]:
                self.unheard[key] += 1
                return
            now = time.monotonic()
            if now - last[0] < min_period:
                self.dropped[key] += 1
                return
            last[0] = now
            try:
                cdr = self.store.serialize_cdr(convert(msg), b.ros_type)
            except Exception as e:  # noqa: BLE001 - one unconvertible sample is counted, not fatal
                self.errors[key] += 1
                self.node.report_bad_input(key, f"cannot convert to {b.ros_type}: {e}")
                return
            self.sent[key] += 1
            pub.put(bytes(cdr), attachment=attachment(self.sent[key], time.time_ns(), gid))

        self.node.subscribe(key, contract.INPUTS[key], on_message)
        self.topics[topic] = b.ros_type

    def _goal_input(self, topic: str, entity_id: int) -> None:
        type_hash = self.store.hash_rihs01(GOAL_TYPE)
        key = data_key(self.params.domain_id, topic, GOAL_TYPE, type_hash)
        self.entities.append(self.node.session.liveliness().declare_token(
            self.ros.endpoint_token("MS", entity_id, topic, GOAL_TYPE, type_hash)))
        self.node.subscribe_raw(key, lambda s: self._on_goal(key, s))
        self.topics[topic] = GOAL_TYPE

    def _on_goal(self, key: str, sample: zenoh.Sample) -> None:
        """A ROS PoseStamped: decoded strictly (CDR must parse, frame ENU, values finite), then
        sent to the mission as a goto goal; the mission's reply is logged and counted."""
        try:
            goal = self.conv.goal_from_pose_stamped(self.store.deserialize_cdr(sample.payload.to_bytes(), GOAL_TYPE))
        except Exception as e:  # noqa: BLE001 - bad ROS input: counted and dropped
            self.goals["invalid"] += 1
            self.node.report_bad_input(key, str(e) or type(e).__name__)
            return
        self.goals["received"] += 1

        def done(reply: GoalReply | CallError) -> None:
            ok = not isinstance(reply, CallError) and reply.success
            self.goals["accepted" if ok else "refused"] += 1
            self.last_goal = "accepted" if ok else (str(reply) if isinstance(reply, CallError) else reply.message)
            self.node.log.info("ros_goal", accepted=ok, reason=self.last_goal,
                               position=[goal.position_m.x, goal.position_m.y, goal.position_m.z])

        self.node.call_async("mission/action/goto/goal", goal, GoalReply, done, timeout_s=3.0)

    def health(self) -> Health:
        values = {"topics": len(self.topics), "sent": sum(self.sent.values()),
                  "dropped_rate_limit": sum(self.dropped.values()),
                  "skipped_no_subscriber": sum(self.unheard.values()), "convert_errors": sum(self.errors.values()),
                  "goals": ",".join(f"{k}={v}" for k, v in sorted(self.goals.items())) or "none",
                  "last_goal": self.last_goal}
        level = DiagnosticStatus.WARN if self.errors else DiagnosticStatus.OK
        return Health(level, f"{len(self.topics)} ROS topics in domain {self.params.domain_id}", values)

    def stop(self) -> None:
        for t in getattr(self, "tokens", []):
            t.undeclare()


def main(argv=None) -> int:
    return run(RosBridgeService, argv)
