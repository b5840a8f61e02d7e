"""An observer to run inside a test host (tests/netns.py): prints what it receives as JSON lines.

    python tests/netprobe.py --connect tcp/127.0.0.1:7447 KEYEXPR [KEYEXPR ...]

One line per sample: {"k": key, "st": header stamp (s, wall clock; null without a header),
"rx": receive time (time.time()), "n": payload bytes, "d": decoded fields, arrays and bytes
replaced by their length}; `--no-data` leaves "d" out. Liveliness tokens under aero/alive/** are
followed too: {"alive": key, "put": true|false, "rx": ...}. All hosts share the machine's clock, so
rx - st is the one-way age of a message across the link. Runs until SIGTERM/SIGINT.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import zenoh

from aeroperception.services.runtime.node import LIVELINESS_ROOT
from aeroperception.services.runtime.session import make_config, open_session
from aeroperception.tools.cli.topic import decode_sample

_lock = threading.Lock()


def _emit(obj: dict) -> None:
    line = json.dumps(obj, separators=(",", ":"), default=str)
    with _lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


def _small(v, depth: int = 0):
    if isinstance(v, (bytes, bytearray, memoryview)):
        return len(v)
    if isinstance(v, dict):
        return {k: _small(x, depth + 1) for k, x in v.items()} if depth < 4 else "{...}"
    if isinstance(v, (list, tuple)):
        return len(v) if len(v) > 16 else [_small(x, depth + 1) for x in v]
    return v


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--connect", required=True)
    p.add_argument("--no-data", action="store_true")
    p.add_argument("keys", nargs="+")
    args = p.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    session = open_session(make_config(None, args.connect, mode="client"), stop, max_wait_s=30)
    if session is None:
        print("netprobe: no router", file=sys.stderr)
        return 1

    def on_sample(s: zenoh.Sample) -> None:
        rx = time.time()
        raw_len = len(s.payload)
        try:
            _sid, d = decode_sample(s)
        except Exception:  # noqa: BLE001 - an observer reports what it can
            d = None
        st = None
        if isinstance(d, dict) and isinstance(d.get("header"), dict):
            st = d["header"].get("stamp_ns", 0) / 1e9 or None
        out = {"k": str(s.key_expr), "st": st, "rx": rx, "n": raw_len}
        if not args.no_data:
            out["d"] = _small(d)
        _emit(out)

    def on_token(s: zenoh.Sample) -> None:
        _emit({"alive": str(s.key_expr), "put": s.kind == zenoh.SampleKind.PUT, "rx": time.time()})

    subs = [session.declare_subscriber(k, on_sample) for k in args.keys]
    subs.append(session.liveliness().declare_subscriber(f"{LIVELINESS_ROOT}/**", on_token, history=True))
    _emit({"ready": True, "rx": time.time()})
    stop.wait()
    for s in subs:
        s.undeclare()
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
