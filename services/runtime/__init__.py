"""The small shared runtime every service is built on: Node (Zenoh session, typed pub/sub,
queryables, liveliness, diagnostics, parameters), the contract vocabulary (Topic, Query), the
action pattern, rate loops, the clock, structured logs and the process shell (`Service`, `run`)."""
from .actions import ActionClient, ActionServer, GoalHandle
from .clock import ServiceClock
from .keys import Queries, Query, Topic, Topics
from .latest import LatestWorker, RateGate
from .log import Logger
from .node import CallError, Health, Node, Publisher, call
from .params import Param, ParamError, ParamSet
from .rate import LoopStats, RateLoop
from .service import Service, run

__all__ = [
    "ActionClient", "ActionServer", "GoalHandle", "ServiceClock", "Queries", "Query", "Topic", "Topics", "LatestWorker", "RateGate",
    "Logger", "CallError", "Health", "Node", "Publisher", "call", "Param", "ParamError", "ParamSet", "LoopStats",
    "RateLoop", "Service", "run",
]
