"""The vocabulary of a service's contract (services/<name>/contract.py).

A contract declares, once, every key the service's code touches:

- INPUTS / OUTPUTS = Topics(Topic(key, schema, rate_hz, note, qos=, strict=, handler=), ...):
  subscribed / published. A Topics maps key -> schema, so code reads `contract.OUTPUTS[key]` for
  the type it publishes. The Topic is also the wiring: its QoS (priority, express, bulk) and, for
  an input, strict decoding and the handler's name; `Node.bind` (runtime/wiring.py) declares
  every subscriber, publisher and queryable from it.
- SERVICES / CALLS = Queries(Query(key, request, reply, note, handler=), ...): queryables served /
  called (key -> (request, reply)).
- ACTIONS / ACTION_CALLS: action base keys served / used (`<base>/goal`, `/cancel`, `/feedback`,
  `/result`; runtime/actions.py).
- LIVELINESS: the services whose liveliness token (aero/alive/<vehicle>/<name>) this one watches;
  "*" = every service.

tools/contracts.py reads these by parsing the file (never importing it) for `aero topic`,
`aero docs reference` and the key table in docs/reference/keys.md. A service wired by `Node.bind`
cannot use a key its contract lacks (refused at start); tests/unit/test_contracts.py walks the
code of services still wired by hand.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class QoS:
    """How a stream travels (services/sim/qos.py says why each choice). priority: a
    zenoh.Priority name, lower case; express: sent at once, never batched; congestion: "drop" (a
    publisher never waits for a slow subscriber: nothing that may cross a link may block the
    vehicle's loop) or "block"; bulk: images and scans, thinned to `--thin-link-hz` on a thin link
    (tools/cli/router.py)."""

    priority: str = "data"
    express: bool = False
    congestion: str = "drop"
    bulk: bool = False

    def __post_init__(self) -> None:
        if self.priority not in PRIORITIES:
            raise ValueError(f"QoS priority {self.priority!r}: one of {', '.join(PRIORITIES)}")
        if self.congestion not in ("drop", "block"):
            raise ValueError(f"QoS congestion {self.congestion!r}: drop or block")


PRIORITIES = ("real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low", "background")
DEFAULT_QOS = QoS()
# Small high-rate streams (IMU, clock, truth): their own queue ahead of the frames on the same link.
SMALL = QoS(priority="data_high", express=True)
# ~1 MB images and scans: they yield to state, goals and replies on a slow link, and are thinned on a thin one.
BULK = QoS(priority="data_low", bulk=True)
# A setpoint stream: sent at once, not batched with what follows.
EXPRESS = QoS(express=True)


@dataclass(frozen=True)
class Topic:
    """A published or subscribed key. rate_hz: the nominal (for a bounded stream, the highest)
    rate a producer publishes at; None for event-driven keys (the note says when).
    qos: how it travels (published with it). strict: an input that commands motion or state is
    decoded strictly (an unknown field refused); telemetry stays lenient (forward compatible).
    handler: the method an input is delivered to; default `handler_name(key)`."""

    key: str
    schema: Any
    rate_hz: float | None = None
    note: str = ""
    qos: QoS = DEFAULT_QOS
    strict: bool = False
    handler: str | None = None

    @property
    def handler_name(self) -> str:
        return self.handler or handler_name(self.key)


@dataclass(frozen=True)
class Query:
    """A queryable served or called: request schema (None: no payload) -> reply schema."""

    key: str
    request: Any
    reply: Any
    note: str = ""
    handler: str | None = None
    locked: bool = True       # False: the handler waits on something (an FC's ACK) and locks itself

    @property
    def handler_name(self) -> str:
        return self.handler or handler_name(self.key)


def handler_name(key: str) -> str:
    """The handler a key is delivered to unless its declaration names one: `on_` + its chunks,
    placeholders, wildcards and `srv` left out ("state/vehicle" -> on_state_vehicle,
    "planner/srv/select_plugin" -> on_planner_select_plugin, "diagnostics/*" -> on_diagnostics)."""
    chunks = [c for c in key.strip("/").split("/") if c != "srv" and "*" not in c and not c.startswith(("<", "$"))]
    return "on_" + "_".join(chunks)


def _unique(items, what: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        if item.key in out:
            raise ValueError(f"{what} {item.key!r} declared twice")
        out[item.key] = item
    return out


class Topics(dict):
    """{key: schema} in declaration order; `declared[key]` is the Topic (rate, note)."""

    def __init__(self, *topics: Topic):
        self.declared: dict[str, Topic] = _unique(topics, "topic")
        super().__init__((t.key, t.schema) for t in topics)


class Queries(dict):
    """{key: (request, reply)} in declaration order; `declared[key]` is the Query."""

    def __init__(self, *queries: Query):
        self.declared: dict[str, Query] = _unique(queries, "queryable")
        super().__init__((q.key, (q.request, q.reply)) for q in queries)
