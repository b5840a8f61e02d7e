"""`aero bench pubsub`: one-way latency of raw eclipse-zenoh vs the runtime's typed pub/sub.

Topology is the deployed one: a router (in this process) and two client processes on loopback,
ping (this process) and pong (a child). Ping stamps, pong echoes, one-way = RTT / 2. The raw
baseline puts/echoes bytes with zenoh directly; the typed path encodes a schema message
through Node.publisher, pong decodes it through Node.subscribe (validation, lock, callback),
re-encodes and publishes it back, and ping decodes the echo. Same run, same machine.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh

from aeroperception.schemas import Image, NDArray, VehicleState, encode
from aeroperception.services.runtime.node import Node
from aeroperception.services.runtime.session import make_config, open_session

PING, PONG = "bench/ping", "bench/pong"


def make_payload(kind: str):
    if kind == "state":
        return VehicleState(flight_mode="OFFBOARD", armed=True, battery_remaining=0.8)
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    return Image(height=480, width=640, encoding="rgb8", step=640 * 3, data=NDArray.from_numpy(img))


# ---------------------------------------------------------------- pong (child process)


def pong(endpoint: str, path: str, kind: str) -> None:
    cls = VehicleState if kind == "state" else Image
    if path == "raw":
        s = open_session(make_config(connect=endpoint), max_wait_s=5)
        pub = s.declare_publisher(PONG)
        s.declare_subscriber(PING, lambda smp: pub.put(smp.payload))
        close = s.close
    else:
        node = Node("bench_pong", connect=endpoint, log_level="warn")
        node.connect(max_wait_s=5)
        pub = node.publisher(PONG, cls)
        node.subscribe(PING, cls, pub.publish)
        close = node.close
    print("ready", flush=True)
    sys.stdin.readline()  # parent closes stdin to stop us
    close()


# ---------------------------------------------------------------- ping (this process)


def measure(endpoint: str, path: str, kind: str, n: int) -> np.ndarray:
    child = subprocess.Popen([sys.executable, "-m", "aeroperception.tools.bench_pubsub", "--pong",
                              endpoint, path, kind], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        if child.stdout.readline().strip() != "ready":
            raise RuntimeError("pong process failed to start")
        msg = make_payload(kind)
        cls = type(msg)
        got = threading.Event()
        if path == "raw":
            s = open_session(make_config(connect=endpoint), max_wait_s=5)
            pub = s.declare_publisher(PING)
            payload = encode(msg)
            s.declare_subscriber(PONG, lambda _smp: got.set())
            send = lambda: pub.put(payload)  # noqa: E731
            close = s.close
        else:
            node = Node("bench_ping", connect=endpoint, log_level="warn")
            node.connect(max_wait_s=5)
            tpub = node.publisher(PING, cls)
            node.subscribe(PONG, cls, lambda _m: got.set())
            send = lambda: tpub.publish(msg)  # noqa: E731
            close = node.close
        time.sleep(0.3)  # let declarations propagate
        out = []
        for i in range(n + 20):
            got.clear()
            t0 = time.perf_counter()
            send()
            if not got.wait(1.0):
                continue
            if i >= 20:  # warm-up
                out.append((time.perf_counter() - t0) / 2 * 1e3)
        close()
        return np.array(out)
    finally:
        child.stdin.close()
        try:
            child.wait(5)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


def run(n: int = 1000, port: int = 17480) -> int:
    endpoint = f"tcp/127.0.0.1:{port}"
    conf = make_config(mode="router", listen=[endpoint])
    conf.insert_json5("scouting/delay", "0")
    conf.insert_json5("connect/endpoints", "[]")
    router = zenoh.open(conf)
    rows = []
    try:
        for kind, count in (("state", n), ("image", max(100, n // 5))):
            raw = measure(endpoint, "raw", kind, count)
            typed = measure(endpoint, "typed", kind, count)
            size = len(encode(make_payload(kind)))
            for label, arr in (("raw zenoh", raw), ("runtime typed", typed)):
                rows.append((kind, size, label, len(arr), np.median(arr), np.percentile(arr, 99),
                             np.median(arr) / np.median(raw)))
    finally:
        router.close()
    print(f"one-way latency, client -> router -> client on loopback ({os.cpu_count()} cores), RTT/2")
    print(f"{'payload':<8} {'bytes':>8} {'path':<14} {'n':>5} {'median_ms':>10} {'p99_ms':>8} {'x_raw':>6}")
    for kind, size, label, cnt, med, p99, ratio in rows:
        print(f"{kind:<8} {size:>8} {label:<14} {cnt:>5} {med:>10.3f} {p99:>8.3f} {ratio:>6.2f}")
    return 0


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--pong", nargs=3, metavar=("ENDPOINT", "PATH", "KIND"))
    a = ap.parse_args()
    if a.pong:
        pong(*a.pong)
