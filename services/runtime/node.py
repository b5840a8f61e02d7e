"""Node: one service's Zenoh session with typed pub/sub, queryables, liveliness, diagnostics
and parameters. Services never touch zenoh directly; they use this.

Threading: subscriber callbacks run on Zenoh's threads, queryable handlers on a small worker
pool, timers in their own threads; every user callback runs holding `node.lock`, so service
logic is single-threaded like a ROS executor and needs no locking of its own.
Bad input (undecodable payload, failed validation, a callback that raises) is counted per key,
logged at most once per key per second, reported in diagnostics, and dropped.
"""
from __future__ import annotations

import threading
import time
from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, TypeVar

import zenoh

from aeroperception.schemas import (
    DiagnosticStatus, Message, ParamList, ParamSet as ParamSetMsg, ParamSetReply, SchemaError,
    decode, encode, schema_id,
)
from aeroperception.schemas.system import ParamDescriptor

from .clock import ServiceClock
from .cpu import CpuMeter
from .keys import DEFAULT_QOS, QoS
from .log import Logger
from .params import Param, ParamError, ParamSet
from .rate import RateLoop
from .session import make_config, open_session
from .supervision import INSTANCE_ROOT, DuplicateInstanceError, Instance, this_instance, winner
from .wiring import Wiring, bind, zenoh_qos

M = TypeVar("M", bound=Message)
R = TypeVar("R", bound=Message)

MSGPACK = "application/msgpack"
LIVELINESS_ROOT = "aero/alive"


class CallError(RuntimeError):
    """A request/response call failed: no responder, timeout, or an undecodable reply."""


def encoding_for(cls: type[Message]) -> zenoh.Encoding:
    return zenoh.Encoding(MSGPACK).with_schema(schema_id(cls))


def schema_of(encoding: zenoh.Encoding | str) -> str:
    """The "<name>@<version>" suffix of a sample's encoding, or "" if it has none."""
    s = str(encoding)
    return s.split(";", 1)[1] if ";" in s else ""


@dataclass
class Health:
    """What a service says about itself once a second (levels as DiagnosticStatus)."""

    level: int = DiagnosticStatus.OK
    message: str = "ok"
    values: dict[str, Any] | None = None


class Publisher:
    """Typed publisher: encodes a message of one schema and puts it with its encoding."""

    def __init__(self, node: "Node", key: str, cls: type[Message], qos: QoS | None = None, **zenoh_kwargs: Any):
        """qos: the contract's declaration (keys.QoS); zenoh_kwargs: zenoh's own, for a key no
        contract declares (tools, benchmarks)."""
        self.key, self.cls, self.qos = key, cls, qos or DEFAULT_QOS
        kw = {**zenoh_qos(self.qos), **zenoh_kwargs}
        self._pub = node.session.declare_publisher(key, encoding=encoding_for(cls), **kw)
        self.count = 0

    def publish(self, msg: Message) -> None:
        self._pub.put(encode(msg))
        self.count += 1

    @property
    def matched(self) -> bool:
        """Whether any subscriber matches the key now (~2 us, from Zenoh's own routing state):
        a producer whose message costs milliseconds to make skips it when nobody listens."""
        return self._pub.matching_status.matching  # type: ignore[attr-defined]  # zenoh's stub: bool; it is a MatchingStatus

    def undeclare(self) -> None:
        self._pub.undeclare()


class Node:
    def __init__(self, name: str, *, params: list[Param] | None = None, vehicle: str = "",
                 zenoh_config: str | None = None, connect: str | None = None,
                 log_level: str = "info", sim_time: bool = False, mode: str | None = None,
                 cpu_budget_pct: float | None = None, config: zenoh.Config | None = None):
        """`config`: a ready Zenoh config instead of zenoh_config/connect/mode (a benchmark's
        peer-to-peer link)."""
        self.name = name
        self.vehicle = vehicle
        self.log = Logger(name, log_level)
        self.params = ParamSet.from_declarations(params or [])
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self._conf = config if config is not None else make_config(zenoh_config, connect, mode=mode, service=True)
        self._sim_time = sim_time
        # None until connect(): typed as the session, since every use comes after connect()
        self.session: zenoh.Session = None  # type: ignore[assignment]
        self.clock: ServiceClock | None = None
        self.bad_input: Counter[str] = Counter()
        self.callback_errors: Counter[str] = Counter()
        self.params_rejected = 0
        self._entities: list[Any] = []
        self._loops: list[RateLoop] = []
        self._pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix=f"{name}-q")
        self._health_fn: Callable[[], Health] = lambda: Health()
        self.cpu = CpuMeter(cpu_budget_pct)   # this process's CPU %, RSS and budget (cpu.py)
        self._diag_pub: Publisher | None = None
        self._closed = False
        self.instance: Instance | None = None   # set by an exclusive connect()

    # ------------------------------------------------------------ lifecycle

    def key(self, key: str) -> str:
        """Apply the vehicle prefix (if any) to a stack key."""
        return f"{self.vehicle}/{key}" if self.vehicle else key

    def connect(self, max_wait_s: float | None = None, exclusive: bool = False) -> bool:
        """Open the session (retrying until a router answers), then declare the runtime's own
        entities: liveliness token, diagnostics, parameter endpoints, clock.

        exclusive: one instance of this service per vehicle (services run by `aero up` / `aero
        run` are). If the same service is already alive for this vehicle, close and raise
        DuplicateInstanceError naming it, before declaring anything."""

        def waiting(err: Exception, attempt: int) -> None:
            if attempt == 1 or attempt % 10 == 0:
                self.log.warn("waiting_for_router", status="STALE", error=str(err).split(" at ")[0])

        session = open_session(self._conf, self.stop_event, waiting, max_wait_s)
        if session is None:
            return False
        self.session = session
        token_key = f"{LIVELINESS_ROOT}/{self.vehicle or 'default'}/{self.name}"
        if exclusive:
            self._claim_instance(token_key)
            self._check_simultaneous_start()
        self.clock = ServiceClock(self if self._sim_time else None)
        self._entities.append(self.session.liveliness().declare_token(token_key))  # alive only once it is ours
        self._diag_pub = self.publisher("diagnostics/" + self.name, DiagnosticStatus)
        base = self.key(f"config/{self.name}")
        self.subscribe_raw(f"{base}/**", self._on_param_put)
        self.serve(f"config/{self.name}/@set", ParamSetMsg, ParamSetReply, self._on_param_set)
        self.serve(f"config/{self.name}/@params", None, ParamList, lambda _req: self.param_list())
        self.every(1.0, self._publish_diagnostics, name="diagnostics")
        self.log.info("started", zid=str(self.session.zid()), vehicle=self.vehicle or None)
        return True

    def _instances(self, timeout_s: float = 1.0) -> list[Instance]:
        """Every exclusive instance of this service for this vehicle that answers (ourselves too)."""
        key = f"{INSTANCE_ROOT}/{self.vehicle or 'default'}/{self.name}"
        out = []
        # Every instance replies on the same key: no consolidation, or all but one reply are dropped.
        for r in self.session.get(key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                                  timeout=timeout_s):
            if r.ok is not None and (inst := Instance.from_json(r.ok.payload.to_bytes())) is not None:
                out.append(inst)
        return out

    def _claim_instance(self, token_key: str) -> None:
        """Refuse to start while the same service is alive for this vehicle; otherwise answer
        "who are you" on INSTANCE_ROOT/<vehicle>/<service> for the next one that asks."""
        vehicle = self.vehicle or "default"
        if any(r.ok is not None for r in self.session.liveliness().get(token_key, timeout=1.0)):
            others = self._instances()
            self._refuse(DuplicateInstanceError(self.name, vehicle, winner(others)))
        key = f"{INSTANCE_ROOT}/{vehicle}/{self.name}"

        def whois(q: zenoh.Query) -> None:
            if self.instance is not None:
                q.reply(key, self.instance.to_json())
            q.drop()

        self._entities.append(self.session.declare_queryable(key, whois))
        # Stamped after declaring: a copy that cannot see us yet gets a later stamp than ours.
        self.instance = this_instance(self.name, vehicle, str(self.session.zid()))

    def _check_simultaneous_start(self, settle_s: float = 0.1) -> None:
        """Copies that passed the liveliness check together: the earliest stamp keeps running.
        Waiting `settle_s` first lets every copy stamped before us become visible (declarations
        propagate asynchronously), so exactly one sees no earlier copy."""
        time.sleep(settle_s)
        me = self.instance
        assert me is not None, "_claim_instance() sets it first"
        others = [i for i in self._instances() if i.zid != me.zid]
        first = winner(others + [me])
        if first is not me:
            self._refuse(DuplicateInstanceError(self.name, me.vehicle, first))

    def _refuse(self, err: DuplicateInstanceError) -> None:
        """Close quietly (the caller prints the one-line refusal) and raise."""
        self._closed = True
        self.stop_event.set()
        for ent in reversed(self._entities):
            try:
                ent.undeclare()
            except Exception:  # noqa: BLE001 - best effort
                pass
        self._entities.clear()
        try:
            self.session.close()
        except Exception:  # noqa: BLE001
            pass
        self._pool.shutdown(wait=False, cancel_futures=True)
        raise err

    def close(self) -> None:
        """Stop loops, undeclare everything and close the session (well within 2 s)."""
        if self._closed:
            return
        self._closed = True
        self.stop_event.set()
        for loop in self._loops:
            loop.stop(0.5)
        self._pool.shutdown(wait=False, cancel_futures=True)
        if self.session is not None:
            for ent in reversed(self._entities):
                try:
                    ent.undeclare()
                except Exception:  # noqa: BLE001 - best effort during shutdown
                    pass
            try:
                self.session.close()
            except Exception:  # noqa: BLE001
                pass
        self.log.info("stopped")

    # ------------------------------------------------------------ pub/sub

    def publisher(self, key: str, cls: type[Message], qos: QoS | None = None, **zenoh_kwargs: Any) -> Publisher:
        pub = Publisher(self, self.key(key), cls, qos, **zenoh_kwargs)
        self._entities.append(pub)
        return pub

    def bind(self, contract: Any, handlers: Any, **select: Any) -> Wiring:
        """Declare the contract's subscribers, publishers and queryables and deliver each input to
        its handler (wiring.py): the returned Wiring maps each output key to its Publisher.
        Raises WiringError at once when the code and the contract disagree."""
        return bind(self, contract, handlers, **select)

    def subscribe(self, key: str, cls: type[M], callback: Callable[[M], None], strict: bool = False) -> None:
        """Decode samples on `key` (vehicle prefix applied) as `cls` and call `callback(msg)`.
        `strict=True` for inputs that command motion or state (unknown fields refused);
        telemetry stays lenient (forward compatible)."""
        full = self.key(key)
        expected, ours = cls.__schema_name__, encoding_for(cls)
        wildcard = "*" in full or "$" in full

        def on_sample(sample: zenoh.Sample) -> None:
            # Per-sample cost matters at 100-1000 Hz: the key's and encoding's strings only when needed.
            k = str(sample.key_expr) if wildcard else full
            if sample.encoding != ours:
                named = schema_of(sample.encoding).partition("@")[0]
                if named and named != expected:
                    # Another type under a wildcard (diagnostics/agg under diagnostics/*): not ours.
                    self.log.throttled("debug", f"other:{k}", "other_schema_skipped", schema=named)
                    return
            try:
                msg = decode(sample.payload.to_bytes(), cls, strict=strict)
            except SchemaError as e:
                self.report_bad_input(k, str(e))
                return
            self._invoke(k, callback, msg)

        self._entities.append(self.session.declare_subscriber(full, on_sample))

    def subscribe_raw(self, full_key: str, callback: Callable[[zenoh.Sample], None]) -> None:
        """Raw samples (no decoding), for tools and the runtime's own endpoints. Key used as is."""
        self._entities.append(
            self.session.declare_subscriber(full_key, lambda s: self._invoke(str(s.key_expr), callback, s))
        )

    def run_callback(self, source: str, fn: Callable, *args: Any) -> Any:
        """Run fn(*args) like a subscriber callback: holding node.lock, exceptions counted per
        `source` and logged (throttled), never raised. For input threads a service owns
        (e.g. a MAVLink reader), so their handlers share the service's single-threaded model."""
        return self._invoke(source, fn, *args)

    def on_liveliness(self, pattern: str, callback: Callable[[str, bool], None]) -> None:
        """callback(last key chunk, alive) for tokens under aero/alive/<vehicle>/<pattern>,
        including those already alive (history)."""
        key = f"{LIVELINESS_ROOT}/{self.vehicle or 'default'}/{pattern}"

        def on_sample(s: zenoh.Sample) -> None:
            k = str(s.key_expr)
            self._invoke(k, callback, k.rsplit("/", 1)[-1], s.kind == zenoh.SampleKind.PUT)

        self._entities.append(self.session.liveliness().declare_subscriber(key, on_sample, history=True))

    def _invoke(self, key: str, fn: Callable, *args: Any, locked: bool = True) -> Any:
        try:
            if not locked:
                return fn(*args)
            with self.lock:
                return fn(*args)
        except Exception as e:  # noqa: BLE001 - a bad message must never take the service down
            self.callback_errors[key] += 1
            self.log.throttled("error", f"cb:{key}", "callback_error", error=f"{type(e).__name__}: {e}")
            return None

    def report_bad_input(self, key: str, error: str) -> None:
        """Count, log (once per key per second) and drop an input that failed to decode/validate."""
        self.bad_input[key] += 1
        self.log.throttled("warn", f"bad:{key}", "invalid_payload_dropped", error=error,
                           count=self.bad_input[key])

    # ------------------------------------------------------------ request/response

    def serve(self, key: str, req_cls: type[Message] | None, reply_cls: type[Message],
              handler: Callable[[Any], Message], locked: bool = True) -> None:
        """Queryable: decode the request (None when req_cls is None), reply with handler(req).

        Handlers run on a worker thread holding node.lock (unless locked=False, for handlers
        that wait on something, e.g. a flight controller's ACK, and do their own locking);
        requests are commands, so they are decoded strictly (an unknown field is refused) and
        an invalid request gets a reply with success=False naming the problem.
        """
        full = self.key(key)

        def work(query: zenoh.Query) -> None:
            k = str(query.key_expr)
            try:
                req = None
                if req_cls is not None:
                    raw = query.payload.to_bytes() if query.payload is not None else b"\x80"
                    try:
                        req = decode(raw, req_cls, strict=True)
                    except SchemaError as e:
                        self.report_bad_input(k, str(e))
                        query.reply(k, encode(_failure(reply_cls, f"invalid request: {e}")),
                                    encoding=encoding_for(reply_cls))
                        return
                if not locked:
                    with self.lock:   # declared from the contract before start(), which holds the lock
                        pass          # while it runs: an unlocked handler too waits until it is done
                reply = self._invoke(k, handler, req, locked=locked)
                if reply is None:
                    reply = _failure(reply_cls, "internal error handling the request (see service log)")
                # zenoh's reply QoS (congestion control BLOCK) on purpose: a dropped reply leaves the
                # caller unsure whether a command ran. Replies are rare and small, at priority DATA
                # ahead of the bulk streams; across a full 20 Mbit/s link `aero param get planner`
                # left no setpoint gap (test_saturated_link_never_stalls_the_vehicle).
                query.reply(k, encode(reply), encoding=encoding_for(type(reply)))
            except Exception as e:  # noqa: BLE001
                self.log.throttled("error", f"q:{k}", "query_failed", error=str(e))
            finally:
                query.drop()

        def on_query(query: zenoh.Query) -> None:
            try:
                self._pool.submit(work, query)
            except RuntimeError:  # pool shut down: service is stopping
                query.drop()

        self._entities.append(self.session.declare_queryable(full, on_query))

    def call(self, key: str, request: Message | None, reply_cls: type[R], timeout_s: float = 2.0,
             selector_params: str = "") -> R:
        """Blocking request/response. Raises CallError with a clear reason."""
        return call(self.session, self.key(key), request, reply_cls, timeout_s, selector_params)

    def call_async(self, key: str, request: Message | None, reply_cls: type[R],
                   callback: Callable[[R | CallError], None] | None = None,
                   timeout_s: float = 2.0) -> Future:
        """Non-blocking call; `callback(reply or CallError)` runs holding node.lock."""

        def work() -> R | CallError:
            try:
                res: R | CallError = self.call(key, request, reply_cls, timeout_s)
            except CallError as e:
                res = e
            if callback:
                self._invoke(key, callback, res)
            return res

        return self._pool.submit(work)

    # ------------------------------------------------------------ timers

    def every(self, period_s: float, fn: Callable[[], None], name: str = "timer") -> RateLoop:
        """Run fn every period_s by deadline (own thread, holding node.lock); stats in diagnostics."""

        def body() -> None:
            with self.lock:
                fn()

        def on_error(e: BaseException) -> None:
            self.callback_errors[f"timer:{name}"] += 1
            self.log.throttled("error", f"timer:{name}", "timer_error", error=f"{type(e).__name__}: {e}")

        loop = RateLoop(1.0 / period_s, body, name=f"{self.name}-{name}", on_error=on_error).start()
        self._loops.append(loop)
        return loop

    # ------------------------------------------------------------ diagnostics

    def set_health(self, fn: Callable[[], Health]) -> None:
        self._health_fn = fn

    def diagnostics(self) -> DiagnosticStatus:
        health = self._health_fn()
        values: dict[str, str | int | float | bool] = {}
        for k, v in (health.values or {}).items():
            values[k] = str(v)
        # Callback threads add keys meanwhile: read snapshots (list() of a dict view is atomic under
        # the GIL; most_common iterates in Python and could see the dict change size)
        bad = list(self.bad_input.items())
        values["invalid_msgs"] = str(sum(n for _, n in bad))
        for k, n in sorted(bad, key=lambda kn: -kn[1])[:5]:
            values[f"invalid_msgs[{k}]"] = str(n)
        values["callback_errors"] = str(sum(self.callback_errors.values()))
        values["params_rejected"] = str(self.params_rejected)
        cpu = self.cpu.report()
        values.update(cpu.values())
        for loop in self._loops:
            short = loop.name.removeprefix(self.name + "-")
            if short == "diagnostics":
                continue
            for k, v in loop.stats.summary().items():
                values[f"loop[{short}].{k}"] = str(v)
        level, message = health.level, health.message
        if level == DiagnosticStatus.OK and (self.bad_input or self.callback_errors):
            level, message = DiagnosticStatus.WARN, f"{message}; dropped invalid input"
        if cpu.over_budget:
            level, message = max(level, DiagnosticStatus.WARN), f"{message}; {cpu.problem()}"
        return DiagnosticStatus(header=self.header(), level=level, name=self.name, message=message,
                                hardware_id=self.vehicle or "default", values=values)

    def _publish_diagnostics(self) -> None:
        if self._diag_pub is not None:
            self._diag_pub.publish(self.diagnostics())

    def header(self, frame_id: str = ""):
        from aeroperception.schemas import Header

        return Header(stamp_ns=self.now_ns(), frame_id=frame_id)

    def now_ns(self) -> int:
        return self.clock.now_ns() if self.clock else time.time_ns()

    # ------------------------------------------------------------ parameters

    def param_list(self) -> ParamList:
        out = []
        for n, p in self.params.declared.items():
            out.append(ParamDescriptor(name=n, value=self.params[n], default=p.default,
                                       type=p.type.__name__, unit=p.unit, min=p.min, max=p.max,
                                       choices=list(p.choices) if p.choices else None,
                                       description=p.description, start_only=p.start_only))
        return ParamList(header=self.header(), service=self.name, params=out)

    def set_param(self, name: str, value: Any) -> ParamSetReply:
        """A live set (config/<service>/@set, a put on config/<service>/<name>, gcs): the reply
        carries the value in force afterwards and, when refused, why (params.ParamSet.apply)."""
        try:
            v = self.params.apply(name, value)
        except ParamError as e:
            self.params_rejected += 1
            self.log.warn("param_rejected", name=name, value=value, error=str(e))
            return ParamSetReply(success=False, message=str(e), name=name,
                                 value=self.params.values.get(name))
        self.log.info("param_set", name=name, value=v)
        return ParamSetReply(success=True, message="ok", name=name, value=v)

    def _on_param_put(self, sample: zenoh.Sample) -> None:
        k = str(sample.key_expr)
        name = k.rsplit("/", 1)[-1]
        try:
            msg = decode(sample.payload.to_bytes(), ParamSetMsg, strict=True)
        except SchemaError as e:
            self.report_bad_input(k, str(e))
            return
        self.set_param(msg.name or name, msg.value)

    def _on_param_set(self, req: ParamSetMsg) -> ParamSetReply:
        return self.set_param(req.name, req.value)


def _failure(reply_cls: type[Message], message: str) -> Message:
    fields = getattr(reply_cls, "__struct_fields__", ())
    kw: dict[str, Any] = {}
    if "success" in fields:
        kw["success"] = False
    if "message" in fields:
        kw["message"] = message
    return reply_cls(**kw)


def call(session: zenoh.Session, full_key: str, request: Message | None, reply_cls: type[R],
         timeout_s: float = 2.0, selector_params: str = "") -> R:
    """Request/response on a raw session (used by Node.call and the CLI)."""
    payload = encode(request) if request is not None else None
    enc = encoding_for(type(request)) if request is not None else None
    selector = f"{full_key}?{selector_params}" if selector_params else full_key
    try:
        replies = session.get(selector, payload=payload, encoding=enc, timeout=timeout_s)
    except zenoh.ZError as e:
        raise CallError(f"{full_key}: {e}") from None
    t0 = time.monotonic()
    got_any = False
    for reply in replies:
        got_any = True
        if reply.ok is None:
            why = reply.err.payload.to_string() if reply.err is not None else "?"
            raise CallError(f"{full_key}: service replied with an error: {why}")
        try:
            return decode(reply.ok.payload.to_bytes(), reply_cls)
        except SchemaError as e:
            raise CallError(f"{full_key}: bad reply: {e}") from None
    if not got_any and time.monotonic() - t0 < timeout_s * 0.9:
        raise CallError(f"{full_key}: no service answers on this key (is it running?)")
    raise CallError(f"{full_key}: no reply within {timeout_s:.1f} s")
