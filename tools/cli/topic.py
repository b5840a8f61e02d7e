"""`aero topic list|echo|hz|pub`, `aero service call`, `aero node list`: inspect and inject
any key of the stack from a shell, like `ros2 topic` / `ros2 service` / `ros2 node`."""
from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from collections import defaultdict

import msgpack
import zenoh

from aeroperception.schemas import (
    Header, Message, SchemaError, decode, encode, from_builtins, get_schema, schema_id, to_builtins,
)
from aeroperception.services.runtime.node import LIVELINESS_ROOT, CallError, encoding_for, schema_of
from aeroperception.services.runtime.node import call as rpc_call
from aeroperception.services.runtime.signals import wait_polling

from aeroperception.tools import contracts
from aeroperception.tools.common import CliError, TrailingPositionalParser, add_session_arguments, dump, emit, full_key, open_client, parse_data, summarize

LEVEL_NAMES = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}   # DiagnosticStatus.level
SILENCE_HINT_S = 2.5
"""`topic echo` says on stderr that nothing publishes its key after this long without a sample."""


def register(sub: argparse._SubParsersAction) -> None:
    topic = sub.add_parser("topic", help="list, echo, measure and publish keys")
    tsub = topic.add_subparsers(dest="topic_cmd", required=True, parser_class=TrailingPositionalParser)

    p = tsub.add_parser("list", help="keys seen in a time window, with rate and schema")
    add_session_arguments(p)
    p.add_argument("--duration", type=float, default=2.0, help="listening window in seconds")
    p.add_argument("pattern", nargs="?", default="**", help="key expression (default **)")
    p.set_defaults(func=topic_list)

    p = tsub.add_parser("echo", help="print decoded messages on a key (YAML, or --json)")
    add_session_arguments(p)
    p.add_argument("key")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--count", "-n", type=int, default=0, help="stop after N messages")
    p.add_argument("--timeout", type=float, default=0.0, help="stop after T seconds (0: never)")
    p.add_argument("--raw", action="store_true", help="show arrays in full")
    p.set_defaults(func=topic_echo)

    p = tsub.add_parser("hz", help="measure the publishing rate of a key")
    add_session_arguments(p)
    p.add_argument("key")
    p.add_argument("--window", type=float, default=5.0, help="seconds of history per estimate")
    p.add_argument("--duration", type=float, default=0.0, help="stop after T seconds (0: never)")
    p.set_defaults(func=topic_hz)

    p = tsub.add_parser("pub", help="publish a message, validated against its schema first")
    add_session_arguments(p)
    p.add_argument("key")
    p.add_argument("data", nargs="?", default=None, help="message fields as YAML or JSON (before or after the options)")
    p.add_argument("--type", "-t", required=True, dest="type_name", help="schema name (see `aero schema list`)")
    p.add_argument("--rate", type=float, default=0.0, help="repeat at HZ until Ctrl-C (0: once)")
    p.add_argument("--count", "-n", type=int, default=0, help="with --rate: stop after N messages")
    p.set_defaults(func=topic_pub)

    svc = sub.add_parser("service", help="call request/response services (queryables)")
    ssub = svc.add_subparsers(dest="service_cmd", required=True, parser_class=TrailingPositionalParser)
    p = ssub.add_parser("call", help="send a request and print the reply")
    add_session_arguments(p)
    p.add_argument("key")
    p.add_argument("data", nargs="?", default=None, help="request fields as YAML or JSON")
    p.add_argument("--type", "-t", dest="type_name", default=None,
                   help="request schema to validate against before sending")
    p.add_argument("--timeout", type=float, default=5.0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=service_call)

    node = sub.add_parser("node", help="services alive on the network")
    nsub = node.add_subparsers(dest="node_cmd", required=True)
    p = nsub.add_parser("list", help="alive services (liveliness) with their last health")
    add_session_arguments(p)
    p.add_argument("--wait", type=float, default=1.2, help="seconds to collect diagnostics")
    p.set_defaults(func=node_list)
    p = nsub.add_parser("check", help="exit 0 when a service is alive and healthy (container healthchecks)")
    add_session_arguments(p)
    p.add_argument("name", nargs="?", default=None,
                   help="service name; without it: only whether the router answers")
    p.add_argument("--wait", type=float, default=2.5, help="seconds to wait for its diagnostics (1 Hz)")
    p.add_argument("--fail-on", default="ERROR", choices=["WARN", "ERROR", "STALE"],
                   help="health level that counts as unhealthy (default ERROR: ERROR and STALE fail)")
    p.set_defaults(func=node_check)


# ---------------------------------------------------------------- decoding


def decode_sample(sample: zenoh.Sample) -> tuple[str, object]:
    """(schema id, plain data) for any sample: typed when its encoding names a known schema."""
    raw = sample.payload.to_bytes()
    sid = schema_of(sample.encoding)
    if sid:
        try:
            cls = get_schema(sid)
        except SchemaError:
            cls = None
        if cls is not None:
            return sid, to_builtins(decode(raw, cls))
    try:
        return sid or str(sample.encoding), msgpack.unpackb(raw, raw=False)
    except Exception:  # noqa: BLE001 - not msgpack: show what it is
        try:
            return str(sample.encoding), raw.decode()
        except UnicodeDecodeError:
            return str(sample.encoding), f"<{len(raw)} bytes>"


# ---------------------------------------------------------------- topic


def topic_list(args) -> int:
    session = open_client(args)
    stats: dict[str, list] = defaultdict(lambda: [0, 0, "", 0.0, 0.0])  # count, bytes, schema, first, last
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        now = time.monotonic()
        with lock:
            st = stats[str(s.key_expr)]
            if st[0] == 0:
                st[3] = now
            st[0] += 1
            st[1] += len(s.payload)
            st[2] = schema_of(s.encoding) or str(s.encoding)
            st[4] = now

    sub = session.declare_subscriber(full_key(args, args.pattern), on_sample)
    time.sleep(args.duration)
    sub.undeclare()
    session.close()
    if not stats:
        print(f"no data on {args.pattern} within {args.duration:.1f} s (is the stack up?)", file=sys.stderr)
        return 1
    width = max(len(k) for k in stats)
    print(f"{'KEY':<{width}}  {'RATE_HZ':>8}  {'BYTES':>9}  SCHEMA")
    for k in sorted(stats):
        n, b, sid, first, last = stats[k]
        print(f"{k:<{width}}  {rate_text(n, last - first):>8}  {b // max(n, 1):9d}  {sid}")
    return 0


def rate_text(count: int, span_s: float) -> str:
    """Rate from the intervals seen (count - 1 over the first-to-last span), not count / window:
    a 1 Hz key seen twice in a 2 s window is 1 Hz, not 0.5 (a single sample has no rate: "-")."""
    if count < 2 or span_s <= 0:
        return "-"
    return f"{(count - 1) / span_s:.1f}"


def topic_echo(args) -> int:
    session = open_client(args)
    done = threading.Event()
    got_one = threading.Event()
    count = [0]
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        try:
            sid, data = decode_sample(s)
        except SchemaError as e:
            print(f"# {s.key_expr}: invalid payload: {e}", file=sys.stderr, flush=True)
            return
        got_one.set()
        with lock:
            if done.is_set():
                return
            shown = data if args.raw else summarize(data)
            if args.json:
                ok = emit(dump({"key": str(s.key_expr), "schema": sid, "data": shown}, True))
            else:
                ok = emit(f"# {s.key_expr} [{sid}]\n" + dump(shown, False))
            count[0] += 1
            if not ok or (args.count and count[0] >= args.count):
                done.set()  # enough, or nobody reads stdout any more (`| head -1`)

    key = full_key(args, args.key)
    sub = session.declare_subscriber(key, on_sample)
    try:
        t_end = time.monotonic() + args.timeout if args.timeout else float("inf")
        first = min(SILENCE_HINT_S, args.timeout) if args.timeout else SILENCE_HINT_S
        if not wait_polling(done, first) and not got_one.is_set() and time.monotonic() < t_end:
            print(silence_hint(session, key, args), file=sys.stderr, flush=True)
        wait_polling(done, None if t_end == float("inf") else max(0.0, t_end - time.monotonic()))
    except KeyboardInterrupt:
        pass
    sub.undeclare()
    session.close()
    if (args.count and count[0] < args.count) or (args.timeout and count[0] == 0):
        print(f"aero: received {count[0]} of {args.count or 'any'} messages on {args.key} within {args.timeout} s",
              file=sys.stderr)
        return 1
    return 0


def silence_hint(session: zenoh.Session, key: str, args, listen_s: float = 1.0) -> str:
    """Why `topic echo KEY` is silent: nobody declares KEY; the keys that look like it, among
    those the contracts declare and those published right now."""
    seen: set[str] = set()

    def on_any(s: zenoh.Sample) -> None:
        seen.add(str(s.key_expr))

    sub = session.declare_subscriber("**", on_any)
    time.sleep(listen_s)
    sub.undeclare()
    prefix = f"{args.vehicle}/" if getattr(args, "vehicle", "") else ""
    known = {prefix + k for k in contracts.declared_keys(contracts.load_contracts()) if "*" not in k and "<" not in k}
    declared = any(contracts.key_matches(key, k) or contracts.key_matches(k, key) for k in known)
    why = "its publisher is not running" if declared else "no service declares it"
    near = contracts.close_keys(key, known | seen)
    hint = f"did you mean {', '.join(near)}?" if near else "`aero topic list` shows what is published."
    return (f"aero: nothing published on {key} in {SILENCE_HINT_S:.1f} s ({why}); {hint} "
            "Still waiting (Ctrl-C or --timeout to stop).")


def topic_hz(args) -> int:
    session = open_client(args)
    stamps: list[float] = []
    lock = threading.Lock()

    def on_sample(_s) -> None:
        with lock:
            stamps.append(time.perf_counter())

    sub = session.declare_subscriber(full_key(args, args.key), on_sample)
    t_end = time.monotonic() + args.duration if args.duration else float("inf")
    status = 0
    try:
        while time.monotonic() < t_end:
            time.sleep(min(1.0, max(0.0, t_end - time.monotonic())))
            with lock:
                now = time.perf_counter()
                while stamps and stamps[0] < now - args.window:
                    stamps.pop(0)
                window = list(stamps)
            if len(window) < 2:
                if not emit(f"{args.key}: no messages in the last {args.window:.0f} s"):
                    break
                status = 1
                continue
            gaps = [b - a for a, b in zip(window, window[1:])]
            rate = (len(window) - 1) / (window[-1] - window[0])
            if not emit(f"{args.key}: rate {rate:.2f} Hz  min {min(gaps)*1e3:.1f} ms  max {max(gaps)*1e3:.1f} ms"
                        f"  std {statistics.pstdev(gaps)*1e3:.2f} ms  window {len(window)}"):
                break
            status = 0
    except KeyboardInterrupt:
        pass
    sub.undeclare()
    session.close()
    return status


def build_message(type_name: str, text: str, stamp: bool = True) -> Message:
    try:
        cls = get_schema(type_name)
        data = parse_data(text)
        if not isinstance(data, dict):
            raise CliError(f"message data must be a mapping of field names, got {data!r}")
        msg = from_builtins(data, cls, strict=True)  # what a user types is a command: no unknown fields
    except SchemaError as e:
        raise CliError(f"{e}") from None
    header = getattr(msg, "header", None)
    if stamp and isinstance(header, Header) and header.stamp_ns == 0:
        header.stamp_ns = time.time_ns()
    return msg


def check_declared_type(key: str, type_name: str) -> str | None:
    """A warning when the contracts declare `key` with another schema than `type_name`."""
    declared = contracts.declared_schemas(key, contracts.load_contracts())
    if not declared or any(s == type_name for s, _svc, _role in declared):
        return None
    schema, svc, role = declared[0]
    return (f"aero: warning: {key} is declared as {schema} ({svc} {role} it), not {type_name}; "
            f"its readers will reject or misread this message")


def topic_pub(args) -> int:
    msg = build_message(args.type_name, args.data or "{}")
    warning = check_declared_type(args.key.strip("/"), type(msg).__name__)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    session = open_client(args)
    pub = session.declare_publisher(full_key(args, args.key), encoding=encoding_for(type(msg)))
    sent = 0
    try:
        if args.rate <= 0:
            pub.put(encode(msg))
            sent = 1
            time.sleep(0.2)  # let the router forward before the session closes
        else:
            period = 1.0 / args.rate
            nxt = time.perf_counter()
            while not args.count or sent < args.count:
                header = getattr(msg, "header", None)
                if isinstance(header, Header):
                    header.stamp_ns = time.time_ns()
                pub.put(encode(msg))
                sent += 1
                nxt += period
                time.sleep(max(0.0, nxt - time.perf_counter()))
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    pub.undeclare()
    session.close()
    print(f"published {sent} x {schema_id(type(msg))} on {args.key}", file=sys.stderr)
    return 0


# ---------------------------------------------------------------- service / node


def service_call(args) -> int:
    if args.type_name:
        request = build_message(args.type_name, args.data or "{}", stamp=False)
        payload, enc = encode(request), encoding_for(type(request))
    else:
        data = parse_data(args.data) if args.data else None
        payload = msgpack.packb(data) if data is not None else None
        enc = zenoh.Encoding("application/msgpack") if data is not None else None
    session = open_client(args)
    key = full_key(args, args.key)
    try:
        replies = list(session.get(key, payload=payload, encoding=enc, timeout=args.timeout))
    finally:
        session.close()
    if not replies:
        raise CliError(f"{key}: no service answered (is it running? `aero node list`)")
    status = 0
    for r in replies:
        if r.ok is None:
            print(f"{key}: error reply: {r.err.payload.to_string()}", file=sys.stderr)
            status = 1
            continue
        sid, data = decode_sample(r.ok)
        print(dump({"key": str(r.ok.key_expr), "schema": sid, "reply": summarize(data)} if args.json
                   else summarize(data), args.json))
        if isinstance(data, dict) and data.get("success") is False:
            status = 1
    return status


def _diagnostics_callback(handle):
    """A subscriber callback passing each decodable diagnostics sample (as a dict) to `handle`."""
    def on_diag(s: zenoh.Sample) -> None:
        try:
            _sid, d = decode_sample(s)
        except SchemaError:
            return
        if isinstance(d, dict):
            handle(d)
    return on_diag


def node_list(args) -> int:
    session = open_client(args)
    health: dict[str, dict] = {}
    on_diag = _diagnostics_callback(lambda d: health.__setitem__(str(d.get("name", "")), d))

    sub = session.declare_subscriber("**/diagnostics/*", on_diag)
    sub2 = session.declare_subscriber("diagnostics/*", on_diag)
    alive = sorted(str(r.ok.key_expr) for r in session.liveliness().get(f"{LIVELINESS_ROOT}/**", timeout=2.0)
                   if r.ok is not None)
    time.sleep(args.wait)
    sub.undeclare()
    sub2.undeclare()
    session.close()
    if not alive:
        print("no services alive", file=sys.stderr)
        return 1
    print(f"{'VEHICLE':<10} {'SERVICE':<14} {'HEALTH':<6} MESSAGE")
    for k in alive:
        vehicle, name = k.split("/")[-2:]
        d = health.get(name, {})
        print(f"{vehicle:<10} {name:<14} {LEVEL_NAMES.get(d.get('level'), '-'):<6} {d.get('message', '')}")
    return 0


def node_check(args) -> int:
    """Liveliness + diagnostics as one exit code: what a Docker/compose healthcheck (or a
    systemd/k8s probe) runs. The token aero/alive/<vehicle>/<name> must exist and the service's
    last diagnostics (within --wait) must be below --fail-on; no diagnostics at all is unhealthy
    (a hung service keeps its token but stops its 1 Hz status)."""
    session = open_client(args, wait_s=min(3.0, max(0.5, args.wait)))
    try:
        if not args.name:
            print("router: reachable")
            return 0
        vehicle = args.vehicle or "default"
        got = threading.Event()
        last: dict = {}

        def keep(d: dict) -> None:
            last.update(d)
            got.set()

        on_diag = _diagnostics_callback(keep)

        sub = session.declare_subscriber(full_key(args, f"diagnostics/{args.name}"), on_diag)
        try:
            tokens = [r for r in session.liveliness().get(f"{LIVELINESS_ROOT}/{vehicle}/{args.name}", timeout=2.0)
                      if r.ok is not None]
            if not tokens:
                print(f"{args.name}: not alive (no liveliness token for vehicle {vehicle})", file=sys.stderr)
                return 1
            if not got.wait(args.wait):
                print(f"{args.name}: alive but no diagnostics within {args.wait:g} s (hung?)", file=sys.stderr)
                return 1
        finally:
            sub.undeclare()
    finally:
        session.close()
    level = int(last.get("level", 3))
    name = LEVEL_NAMES.get(level, str(level))
    limit = {v: k for k, v in LEVEL_NAMES.items()}[args.fail_on]
    line = f"{args.name}: {name} {last.get('message', '')}".rstrip()
    if level >= limit:
        print(line, file=sys.stderr)
        return 1
    print(line)
    return 0


def call_or_fail(session, key, request, reply_cls, timeout_s=5.0):
    try:
        return rpc_call(session, key, request, reply_cls, timeout_s)
    except CallError as e:
        raise CliError(str(e)) from None


def call_once(args, key: str, request, reply_cls, timeout_s: float = 5.0):
    """One call on a session of its own (the CLI's one-shot queries); `key` without the vehicle prefix."""
    session = open_client(args)
    try:
        return call_or_fail(session, full_key(args, key), request, reply_cls, timeout_s)
    finally:
        session.close()
