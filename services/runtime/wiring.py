"""The contract wires the service (PX4's uORB members, dora's dataflow.yml): `Node.bind(contract,
handlers)` declares every subscriber, publisher and queryable a contract.py lists, with the QoS and
strictness its Topic declares, and delivers each input to the handler its declaration names
(`Topic.handler_name`: `on_<key chunks>` unless given).

Refused at start, in one line naming the fix: an input or queryable without a handler, a handler
(a method named `on_*`) that no declared key feeds, and a publisher the contract lacks
(`wiring[key]` for a key not in OUTPUTS). So the code cannot use a key its contract does not
declare, and the contract cannot declare an input nobody handles; `check_handlers` is the same
rule without Zenoh, for a service's unit test.

It must never decide anything about the data: it only declares and binds.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator

import zenoh

from .keys import DEFAULT_QOS, QoS, Queries, Topics

if TYPE_CHECKING:
    from .node import Node, Publisher

# Methods named on_* that are not input handlers: the runtime's own hooks.
RUNTIME_HOOKS = frozenset({"on_config"})


class WiringError(RuntimeError):
    """The code and its contract disagree (a missing or unknown handler, an undeclared output)."""


def zenoh_qos(qos: QoS) -> dict[str, Any]:
    """Keyword arguments for session.declare_publisher from a declared QoS ({} = zenoh's defaults)."""
    if qos == DEFAULT_QOS:
        return {}
    return dict(priority=getattr(zenoh.Priority, qos.priority.upper()), express=qos.express,
                congestion_control=getattr(zenoh.CongestionControl, qos.congestion.upper()))


def _name(contract: Any) -> str:
    return getattr(contract, "NAME", "") or getattr(contract, "__name__", "contract")


def _selected(table: Mapping, keys: Iterable[str] | None, what: str, service: str) -> list[str]:
    if keys is None:
        return list(table)
    keys = list(keys)
    unknown = [k for k in keys if k not in table]
    if unknown:
        raise WiringError(f"{service}: {', '.join(unknown)} not in its contract's {what} "
                          f"(declared: {', '.join(table) or 'none'})")
    return keys


def _lookup(handlers: Any, name: str) -> Callable | None:
    fn = handlers.get(name) if isinstance(handlers, Mapping) else getattr(handlers, name, None)
    return fn if callable(fn) else None


def _candidates(handlers: Any) -> set[str]:
    """The names that claim to be input handlers: a mapping's keys, an object's on_* methods."""
    if handlers is None:
        return set()
    if isinstance(handlers, Mapping):
        return set(handlers)
    return {n for n in dir(type(handlers)) if n.startswith("on_") and callable(getattr(type(handlers), n))}


def check_handlers(contract: Any, handlers: Any, inputs: Iterable[str] | None = None,
                   services: Iterable[str] | None = None) -> dict[tuple[str, str], Callable]:
    """{("INPUTS" | "SERVICES", key): bound handler} for the inputs and queryables selected (None: all declared); raises
    WiringError when one has no handler, or a handler (an `on_*` method) matches no declared key."""
    service = _name(contract)
    ins: Topics = getattr(contract, "INPUTS", None) or Topics()
    srvs: Queries = getattr(contract, "SERVICES", None) or Queries()
    declared = {d.handler_name: k for t in (ins, srvs) for k, d in t.declared.items()}
    unknown = sorted(_candidates(handlers) - set(declared) - RUNTIME_HOOKS)
    if unknown:
        raise WiringError(f"{service}: handler {unknown[0]} matches no input or service in its contract "
                          f"(declared handlers: {', '.join(sorted(declared)) or 'none'})")
    out: dict[tuple[str, str], Callable] = {}
    for table, keys, what in ((ins, inputs, "INPUTS"), (srvs, services, "SERVICES")):
        for key in _selected(table, keys, what, service):
            name = table.declared[key].handler_name
            fn = _lookup(handlers, name) if handlers is not None else None
            if fn is None:
                raise WiringError(f"{service}: {what} {key!r} has no handler: define {name}"
                                  f"({'msg' if what == 'INPUTS' else 'request'}) or name one with handler=")
            out[(what, key)] = fn
    return out


class Wiring(Mapping):
    """What bind declared: `wiring[key]` is the Publisher of a declared output."""

    def __init__(self, service: str, publishers: dict[str, "Publisher"], declared_outputs: Iterable[str]):
        self.service = service
        self.publishers = publishers
        self._declared = set(declared_outputs)

    def __getitem__(self, key: str) -> "Publisher":
        pub = self.publishers.get(key)
        if pub is None:
            why = "not bound in this process" if key in self._declared else "its contract's OUTPUTS lacks it"
            raise WiringError(f"{self.service}: no publisher for {key!r}: {why}")
        return pub

    def __contains__(self, key: object) -> bool:
        return key in self.publishers

    def __iter__(self) -> Iterator[str]:
        return iter(self.publishers)

    def __len__(self) -> int:
        return len(self.publishers)


def bind(node: "Node", contract: Any, handlers: Any, *, inputs: Iterable[str] | None = None,
         outputs: Iterable[str] | None = None, services: Iterable[str] | None = None) -> Wiring:
    """Check the handlers, then declare the outputs' publishers and the inputs' subscribers and
    the queryables (each selection None: all the contract declares; a process that owns part of a
    service's keys, e.g. the simulator's render processes, selects its part)."""
    service = _name(contract)
    bound = check_handlers(contract, handlers, inputs, services)
    outs: Topics = getattr(contract, "OUTPUTS", None) or Topics()
    pubs = {k: node.publisher(k, outs[k], qos=outs.declared[k].qos)
            for k in _selected(outs, outputs, "OUTPUTS", service)}
    ins: Topics = getattr(contract, "INPUTS", None) or Topics()
    srvs: Queries = getattr(contract, "SERVICES", None) or Queries()
    for (what, key), fn in bound.items():
        if what == "INPUTS":
            t = ins.declared[key]
            node.subscribe(key, t.schema, fn, strict=t.strict)
        else:
            q = srvs.declared[key]
            node.serve(key, q.request, q.reply, fn, locked=q.locked)
    return Wiring(service, pubs, outs)
