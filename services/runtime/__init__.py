"""The small shared runtime every service is built on: Node (Zenoh session, typed pub/sub,
queryables, liveliness, diagnostics, parameters), the contract vocabulary (Topic, Query, QoS)
and the wiring from it (Node.bind), configs from parameters (param, on_config), the
action pattern, rate loops, the clock, structured logs and the process shell (`Service`, `run`)."""
from .actions import ActionClient, ActionServer, GoalHandle
from .clock import ServiceClock
from .config import ConfigError, param, section
from .keys import BULK, EXPRESS, SMALL, QoS, Queries, Query, Topic, Topics
from .latest import LatestWorker, RateGate
from .log import Logger
from .node import CallError, Health, Node, Publisher, call
from .params import Param, ParamError, ParamSet
from .rate import LoopStats, RateLoop
from .service import Service, run
from .wiring import Wiring, WiringError

__all__ = [
    "ActionClient", "ActionServer", "GoalHandle", "ServiceClock", "Queries", "Query", "Topic", "Topics", "LatestWorker", "RateGate",
    "Logger", "CallError", "Health", "Node", "Publisher", "call", "Param", "ParamError", "ParamSet", "LoopStats",
    "RateLoop", "Service", "run", "BULK", "EXPRESS", "SMALL", "QoS", "ConfigError", "param", "section", "Wiring",
    "WiringError",
]
