"""The vocabulary of a service's contract (services/<name>/contract.py).

A contract declares, once, every key the service's code touches:

- INPUTS / OUTPUTS = Topics(Topic(key, schema, rate_hz, note), ...): subscribed / published.
  A Topics maps key -> schema, so code reads `contract.OUTPUTS[key]` for the type it publishes.
- SERVICES / CALLS = Queries(Query(key, request, reply, note), ...): queryables served / called
  (key -> (request, reply)).
- ACTIONS / ACTION_CALLS: action base keys served / used (`<base>/goal`, `/cancel`, `/feedback`,
  `/result`; runtime/actions.py).
- LIVELINESS: the services whose liveliness token (aero/alive/<vehicle>/<name>) this one watches;
  "*" = every service.

tools/contracts.py reads these by parsing the file (never importing it) for `aero topic`,
`aero docs reference` and the key table in docs/reference/keys.md; tests/unit/test_contracts.py walks
each service's code and fails on a key used but not declared here, or declared but never used.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Topic:
    """A published or subscribed key. rate_hz: the nominal (for a bounded stream, the highest)
    rate a producer publishes at; None for event-driven keys (the note says when)."""

    key: str
    schema: Any
    rate_hz: float | None = None
    note: str = ""


@dataclass(frozen=True)
class Query:
    """A queryable served or called: request schema (None: no payload) -> reply schema."""

    key: str
    request: Any
    reply: Any
    note: str = ""


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
