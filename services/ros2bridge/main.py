"""Process shell: our keys -> rmw_zenoh publications, configured ROS sensor topics -> our sensors/**,
one ROS goal topic -> the mission's goto action.

Topics and names are read at start (restart the service to change them). Every sample is
converted and sent from the subscriber's callback (bridge.TopicBridge): a slow ROS consumer
cannot queue anything here, and `max_rate_hz` drops extra samples of a fast key instead of
copying every image.

Our keys are wired from the contract: the `topics` parameter selects which of its INPUTS are
bound (bind_selection), each to its TopicBridge through one table of handlers; the `inputs`
parameter selects which of its OUTPUTS are declared, each fed by one ROS topic (bridge.InputBridge),
so only the keys a ROS driver really feeds are published. The ROS side is
declared by hand, and must be: rmw_zenoh's data keys (`<domain>/<namespace>/<topic>/<type>/<hash>`,
CDR payloads, built from the parameters at start) and its `@ros2_lv/**` liveliness tokens are
not the stack's key space, so no contract Topic can name them.
"""
from __future__ import annotations

import functools
from collections import Counter

import zenoh

from aeroperception.schemas import DiagnosticStatus, GoalReply, GoToPositionGoal
from aeroperception.services.runtime import Health, Service, run
from aeroperception.services.runtime.node import CallError

from . import contract
from .bridge import SIDES, InputBridge, RosBridgeConfig, TopicBridge, ros_name
from .convert import CATALOG, GOAL_TYPE, Converter, conversion
from .inbound import Source
from .rmw import QOS_SENSOR_DATA, RosNode, data_key, make_typestore

CDR = zenoh.Encoding("application/cdr")


class RosBridgeService(Service):
    """Publish a configurable set of keys as ROS 2 topics (rmw_zenoh wire format); take goals from ROS."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = RosBridgeConfig

    def handlers(self) -> dict:
        """Every input to its TopicBridge (`_on_input` with its key)."""
        return {t.handler_name: functools.partial(self._on_input, key) for key, t in contract.INPUTS.declared.items()}

    def bind_selection(self) -> dict:
        # an unknown key, a malformed or looping input fails at start, naming what exists
        self.sources = self.cfg.sources(list(contract.OUTPUTS))
        return {"inputs": self.cfg.bridged_keys(), "outputs": [s.key for s in self.sources]}

    def start(self) -> None:
        p = self.cfg
        self.store = make_typestore()
        self.conv = Converter(self.store)
        session = self.node.session
        self.ros = RosNode(domain_id=p.domain_id, zid=str(session.zid()), namespace=p.namespace, name=p.node_name)
        self.entities = [session.liveliness().declare_token(self.ros.token())]
        self.bridges: dict[str, TopicBridge] = {}
        self.inputs: list[InputBridge] = []
        self.goals = Counter()
        self.last_goal = ""
        self.topics: dict[str, str] = {}
        entity = 0
        for key in p.bridged_keys():
            entity += 1
            self._bridge(key, entity)
        goal_topic = p.goal_topic.strip("/")
        if goal_topic:
            entity += 1
            self._goal_input(ros_name(p.namespace, goal_topic), entity)
        mounts = {side: p.t_body_camera(side) for side in SIDES}
        for source in self.sources:
            entity += 1
            self._sensor_input(source, mounts, entity)

    def _bridge(self, key: str, entity_id: int) -> None:
        b = CATALOG[key]
        topic = ros_name(self.cfg.namespace, b.topic)
        type_hash = self.store.hash_rihs01(b.ros_type)
        pub = self.node.session.declare_publisher(data_key(self.cfg.domain_id, topic, b.ros_type, type_hash),
                                                  encoding=CDR)
        self.entities.append(self.node.session.liveliness().declare_token(
            self.ros.endpoint_token("MP", entity_id, topic, b.ros_type, type_hash)))
        bridge = self.bridges[key] = TopicBridge(key, b.ros_type, conversion(self.conv, b), self.store.serialize_cdr,
                                                 pub.put, self.cfg.max_rate_hz, self.node.report_bad_input)
        # Nobody on the ROS side listening: no conversion at all (images and clouds cost CPU).
        bridge.matching = pub.matching_status.matching
        self.entities.append(pub.declare_matching_listener(bridge.on_matching))
        self.topics[topic] = b.ros_type

    def _on_input(self, key: str, msg) -> None:
        self.bridges[key].on_message(msg)

    def _goal_input(self, topic: str, entity_id: int) -> None:
        type_hash = self.store.hash_rihs01(GOAL_TYPE)
        key = data_key(self.cfg.domain_id, topic, GOAL_TYPE, type_hash)
        self.entities.append(self.node.session.liveliness().declare_token(
            self.ros.endpoint_token("MS", entity_id, topic, GOAL_TYPE, type_hash)))
        self.node.subscribe_raw(key, functools.partial(self._on_goal, key))
        self.topics[topic] = GOAL_TYPE

    def _sensor_input(self, source: Source, mounts: dict, entity_id: int) -> None:
        """A ROS topic -> one of our keys: any type hash of its type on the data key (Humble's
        rmw_zenoh has none, Jazzy's is RIHS01), announced as a best-effort subscription (what a
        driver's SensorDataQoS publisher matches) with Jazzy's hash."""
        type_hash = self.store.hash_rihs01(source.ros_type)
        self.entities.append(self.node.session.liveliness().declare_token(
            self.ros.endpoint_token("MS", entity_id, source.topic, source.ros_type, type_hash, QOS_SENSOR_DATA)))
        bridge = InputBridge(source, self.store.deserialize_cdr, source.converter(mounts),
                             self._publisher(source.key), self.node.report_bad_input)
        self.inputs.append(bridge)
        self.node.subscribe_raw(data_key(self.cfg.domain_id, source.topic, source.ros_type, "*"),
                                lambda sample: bridge.on_sample(sample.payload.to_bytes()))
        self.topics[source.topic] = source.ros_type

    def _publisher(self, key: str):
        return self.io[key].publish

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
        self.node.call_async("mission/action/goto/goal", goal, GoalReply, functools.partial(self._on_goal_reply, goal),
                             timeout_s=3.0)

    def _on_goal_reply(self, goal: GoToPositionGoal, reply: GoalReply | CallError) -> None:
        ok = not isinstance(reply, CallError) and reply.success
        self.goals["accepted" if ok else "refused"] += 1
        self.last_goal = "accepted" if ok else (str(reply) if isinstance(reply, CallError) else reply.message)
        self.node.log.info("ros_goal", accepted=ok, reason=self.last_goal,
                           position=[goal.position_m.x, goal.position_m.y, goal.position_m.z])

    def health(self) -> Health:
        bridges = self.bridges.values()
        ins = self.inputs
        errors = sum(b.errors for b in bridges) + sum(b.errors for b in ins)
        values = {"topics": len(self.topics), "sent": sum(b.sent for b in bridges),
                  "received": sum(b.received for b in ins), "input_errors": sum(b.errors for b in ins),
                  **{f"convert_ms.{b.source.key}": round(b.convert_ms, 2) for b in ins},
                  "dropped_rate_limit": sum(b.dropped for b in bridges),
                  "skipped_no_subscriber": sum(b.unheard for b in bridges),
                  "convert_errors": sum(b.errors for b in bridges),
                  "goals": ",".join(f"{k}={v}" for k, v in sorted(self.goals.items())) or "none",
                  "last_goal": self.last_goal}
        level = DiagnosticStatus.WARN if errors else DiagnosticStatus.OK
        return Health(level, f"{len(self.topics)} ROS topics in domain {self.cfg.domain_id}", values)

    def stop(self) -> None:
        for t in getattr(self, "tokens", []):
            t.undeclare()


def main(argv=None) -> int:
    return run(RosBridgeService, argv)
