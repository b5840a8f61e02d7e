"""`aero bench pubsub`: one-way latency of the runtime's typed pub/sub against raw eclipse-zenoh and,
with `--peers`, against zenoh peer-to-peer, dora-rs and Cyclone DDS, in one run on one machine.

Ping (this process, or dora's ping node) stamps and sends, pong (a child process) echoes, one-way
= RTT / 2; 20 warm-up round trips are not counted. The paths run in `repeats` interleaved rounds
(each a fresh pong), so a machine whose load changes (a shared one) skews no path alone. Same two payloads everywhere: a VehicleState
(~500 B msgpack) and a 640x480 rgb8 Image (~921 KB), as the same encoded bytes on every transport.

- zenoh via router: client -> router -> client, the deployed topology (the router in this process).
- zenoh peer-to-peer: pong listens on loopback, ping connects to it; no router on the path.
- zenoh peers + router: both are peers that connect to the router and listen on loopback; the
  router introduces them (gossip) and data may take their direct link: co-located services that
  keep the router for discovery.
- typed (router / peer-to-peer): the same links; ping encodes a schema message through
  Node.publisher, pong decodes it through Node.subscribe (validation, lock, callback), re-encodes
  and publishes it back, and ping decodes the echo. Raw pong echoes the payload untouched.
- raw+read via router: raw, but the bytes reach Python at both ends (pong `to_bytes()` and puts
  those bytes, ping `to_bytes()` the echo): the least any consumer of the payload pays. Raw
  never reads the payload, so for a 921 KB image it omits the copies zenoh-python makes to hand
  bytes to Python and back (ZBytes has no buffer protocol in 1.10); typed is judged against both.
- dora-rs: a two-node dataflow (`dora run`), the bytes as an Arrow uint8 array (extra `bench`).
- Cyclone DDS: reliable, keep-last 1, the bytes as an IDL sequence<octet>, unicast on loopback in a
  domain of its own (extra `bench`).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from typing import Callable

import numpy as np
import zenoh

from aeroperception.schemas import Image, NDArray, VehicleState, encode
from aeroperception.services.runtime.node import Node
from aeroperception.services.runtime.session import make_config, open_session

PING, PONG = "bench/ping", "bench/pong"
WARMUP = 20
READ_PATH = "raw+read via router"
MAX_LOST = 5          # round trips without an answer (1 s each) before a path is given up


def make_payload(kind: str):
    if kind == "state":
        return VehicleState(flight_mode="OFFBOARD", armed=True, battery_remaining=0.8)
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    return Image(height=480, width=640, encoding="rgb8", step=640 * 3, data=NDArray.from_numpy(img))


def ping_loop(round_trip: Callable[[], bool], n: int) -> np.ndarray:
    """One-way latencies (ms) of n round trips after WARMUP; `round_trip()` sends one ping and
    returns whether its echo came back within 1 s."""
    out, lost = [], 0
    for i in range(n + WARMUP):
        t0 = time.perf_counter()
        if not round_trip():
            lost += 1
            if lost >= MAX_LOST:
                break
            continue
        if i >= WARMUP:
            out.append((time.perf_counter() - t0) / 2 * 1e3)
    return np.array(out)


def echoed(send: Callable[[], None], got: threading.Event) -> Callable[[], bool]:
    """A round trip for callback transports: `got` is set by the echo's callback."""

    def round_trip() -> bool:
        got.clear()
        send()
        return got.wait(1.0)

    return round_trip


# ---------------------------------------------------------------- zenoh: raw and typed, router and peer


LINKS = ("router", "peer", "mesh")


def link_config(endpoint: str, link: str, side: str) -> zenoh.Config:
    """router: a client of the router at `endpoint`. peer: pong listens on `endpoint`, ping connects.
    mesh: a peer of the router at `endpoint` that also listens on loopback (direct links by gossip)."""
    if link == "router":
        return make_config(connect=endpoint)
    if link == "mesh":
        return make_config(connect=endpoint, mode="peer", listen=["tcp/127.0.0.1:0"])
    if side == "pong":
        conf = make_config(mode="peer", listen=[endpoint])
        conf.insert_json5("connect/endpoints", "[]")
        return conf
    return make_config(connect=endpoint, mode="peer", listen=[])


def zenoh_side(endpoint: str, link: str, path: str, kind: str, side: str, on_echo: Callable | None = None):
    """Open one end; returns (send or None, close). Pong echoes; ping calls on_echo per echo."""
    conf = link_config(endpoint, link, side)
    cls = type(make_payload(kind))
    out_key, in_key = (PONG, PING) if side == "pong" else (PING, PONG)
    if path == "raw":
        s = open_session(conf, max_wait_s=5)
        pub = s.declare_publisher(out_key)
        s.declare_subscriber(in_key, (lambda smp: pub.put(smp.payload)) if side == "pong" else (lambda _s: on_echo()))
        payload = encode(make_payload(kind))
        return (lambda: pub.put(payload)), s.close
    if path == "read":   # raw, but the bytes reach Python at each end, as any consumer needs them
        s = open_session(conf, max_wait_s=5)
        pub = s.declare_publisher(out_key)
        s.declare_subscriber(in_key, (lambda smp: pub.put(smp.payload.to_bytes())) if side == "pong"
                             else (lambda smp: on_echo(smp.payload.to_bytes())))
        payload = encode(make_payload(kind))
        return (lambda: pub.put(payload)), s.close
    node = Node(f"bench_{side}", log_level="warn", config=conf)
    node.connect(max_wait_s=5)
    pub = node.publisher(out_key, cls)
    node.subscribe(in_key, cls, pub.publish if side == "pong" else on_echo)
    msg = make_payload(kind)
    return (lambda: pub.publish(msg)), node.close


def measure(endpoint: str, path: str, kind: str, n: int, link: str = "router") -> np.ndarray:
    """Ping-pong over zenoh: path "raw" or "typed", over a link of LINKS (link_config)."""
    child = _child("zenoh", endpoint, link, path, kind)
    try:
        got = threading.Event()
        send, close = zenoh_side(endpoint, link, path, kind, "ping", lambda *_: got.set())
        try:
            time.sleep(0.3)  # let declarations propagate
            return ping_loop(echoed(send, got), n)
        finally:
            close()
    finally:
        _stop(child)


def _child(*args: str) -> subprocess.Popen:
    child = subprocess.Popen([sys.executable, "-m", "aeroperception.tools.bench.pubsub", "--pong", *args],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    if child.stdout.readline().strip() != "ready":
        _stop(child)
        raise RuntimeError(f"pong process ({args[0]}) failed to start")
    return child


def _stop(child: subprocess.Popen) -> None:
    child.stdin.close()   # pong returns when its stdin closes
    try:
        child.wait(5)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()


# ---------------------------------------------------------------- Cyclone DDS


def _dds_type(size: int) -> type:
    """An IDL struct holding `size` bytes: a fixed uint8 array, which Cyclone's Python binding
    (de)serializes as bytes (a sequence<octet> goes element by element)."""
    import types as pytypes
    from dataclasses import dataclass

    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import types as idl

    def body(ns: dict) -> None:
        ns["__annotations__"] = {"data": idl.array[idl.uint8, size]}

    return dataclass(pytypes.new_class(f"Blob{size}", (IdlStruct,), {"typename": f"aero_bench::Blob{size}"}, body))


def dds_side(domain: int, kind: str, side: str, on_echo: Callable | None = None):
    from cyclonedds.core import Listener, Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    data = encode(make_payload(kind))
    blob = _dds_type(len(data))
    dp = DomainParticipant(domain)
    qos = Qos(Policy.Reliability.Reliable(max_blocking_time=1_000_000_000), Policy.History.KeepLast(1))
    out_name, in_name = (f"pong_{kind}", f"ping_{kind}") if side == "pong" else (f"ping_{kind}", f"pong_{kind}")
    writer = DataWriter(dp, Topic(dp, out_name, blob), qos=qos)

    def on_data(reader) -> None:
        for s in reader.take(N=8):
            if side == "pong":
                writer.write(s)
            else:
                on_echo()

    reader = DataReader(dp, Topic(dp, in_name, blob), qos=qos, listener=Listener(on_data_available=on_data))
    payload = blob(data=data)
    handles = (dp, writer, reader)   # kept alive until close
    return (lambda: writer.write(payload)), (lambda: handles and None)


def dds_env() -> dict[str, str]:
    """Cyclone on loopback, unicast discovery (no multicast needed), its own domain."""
    return {"CYCLONEDDS_URI": "<CycloneDDS><Domain><General><Interfaces><NetworkInterface address=\"127.0.0.1\"/>"
                              "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>"
                              "<ParticipantIndex>auto</ParticipantIndex><Peers><Peer address=\"127.0.0.1\"/></Peers>"
                              "</Discovery></Domain></CycloneDDS>"}


def measure_dds(kind: str, n: int) -> np.ndarray:
    domain = 100 + os.getpid() % 100
    os.environ.update(dds_env())
    child = _child("dds", str(domain), kind)
    got = threading.Event()
    send, close = dds_side(domain, kind, "ping", got.set)
    try:
        time.sleep(1.0)   # discovery
        return ping_loop(echoed(send, got), n)
    finally:
        close()
        _stop(child)


# ---------------------------------------------------------------- dora-rs


def dora_node(role: str, kind: str, n: int = 0, out_file: str = "") -> None:
    """A node of the two-node dataflow: ping measures and writes its latencies to out_file."""
    import pyarrow as pa
    from dora import Node as DoraNode

    node = DoraNode()
    if role == "pong":
        for event in node:
            if event["type"] == "INPUT":
                node.send_output("out", event["value"])
            elif event["type"] == "STOP":
                break
        return
    payload = pa.array(np.frombuffer(encode(make_payload(kind)), dtype=np.uint8))

    def round_trip() -> bool:
        node.send_output("out", payload)
        event = node.next(timeout=1.0)
        return event is not None and event["type"] == "INPUT"

    out = ping_loop(round_trip, n).tolist()
    with open(out_file, "w") as f:
        json.dump(out, f)


def measure_dora(kind: str, n: int, timeout_s: float = 120.0) -> np.ndarray:
    with tempfile.TemporaryDirectory(prefix="aero-bench-dora-") as work:   # dora's logs and out/ too
        return _run_dora(work, kind, n, timeout_s)


def _run_dora(work: str, kind: str, n: int, timeout_s: float) -> np.ndarray:
    out_file = os.path.join(work, "ping.json")
    me = "-m aeroperception.tools.bench.pubsub --dora"
    flow = {"nodes": [
        {"id": "ping", "path": sys.executable, "args": f"{me} ping {kind} {n} {out_file}",
         "inputs": {"pong": "pong/out"}, "outputs": ["out"]},
        {"id": "pong", "path": sys.executable, "args": f"{me} pong {kind}",
         "inputs": {"ping": "ping/out"}, "outputs": ["out"]},
    ]}
    yml = os.path.join(work, "dataflow.yml")
    with open(yml, "w") as f:
        json.dump(flow, f)   # JSON is YAML
    proc = subprocess.run(["dora", "run", yml], cwd=work, capture_output=True, text=True, timeout=timeout_s,
                          stdin=subprocess.DEVNULL)
    if not os.path.exists(out_file):
        raise RuntimeError(f"dora run failed (exit {proc.returncode}): {(proc.stderr or proc.stdout)[-300:]}")
    with open(out_file) as f:
        return np.array(json.load(f))


# ---------------------------------------------------------------- the table


def peers_available() -> dict[str, str]:
    """{peer: "" if installed else why not}."""
    dora = "" if importlib.util.find_spec("dora") and shutil.which("dora") else \
        "not installed (pip install 'aeroperception[bench]')"
    dds = "" if importlib.util.find_spec("cyclonedds") else "not installed (pip install 'aeroperception[bench]')"
    return {"dora-rs": dora, "Cyclone DDS": dds}


def run(n: int = 1000, port: int = 17480, peers: bool = False, repeats: int = 3) -> int:
    from aeroperception.tools.harness import free_port

    endpoint = f"tcp/127.0.0.1:{port}"
    conf = make_config(mode="router", listen=[endpoint])
    conf.insert_json5("scouting/delay", "0")
    conf.insert_json5("connect/endpoints", "[]")
    load0 = os.getloadavg()
    missing = peers_available() if peers else {}
    rows = []
    router = zenoh.open(conf)
    try:
        for kind, count in (("state", max(1, n // repeats)), ("image", max(30, n // 5 // repeats))):
            peer_ep = lambda: f"tcp/127.0.0.1:{free_port()}"  # noqa: E731
            paths: list[tuple[str, Callable[[], np.ndarray]]] = [
                ("zenoh via router", lambda: measure(endpoint, "raw", kind, count)),
                (READ_PATH, lambda: measure(endpoint, "read", kind, count)),
                ("typed via router", lambda: measure(endpoint, "typed", kind, count)),
            ]
            if peers:
                paths += [("zenoh peer-to-peer", lambda: measure(peer_ep(), "raw", kind, count, "peer")),
                          ("typed peer-to-peer", lambda: measure(peer_ep(), "typed", kind, count, "peer")),
                          ("zenoh peers+router", lambda: measure(endpoint, "raw", kind, count, "mesh")),
                          ("typed peers+router", lambda: measure(endpoint, "typed", kind, count, "mesh"))]
                if not missing["dora-rs"]:
                    paths.append(("dora-rs", lambda: measure_dora(kind, count)))
                if not missing["Cyclone DDS"]:
                    paths.append(("Cyclone DDS", lambda: measure_dds(kind, count)))
            size = len(encode(make_payload(kind)))
            # Rounds interleave the paths, so a change of the machine's load hits them all alike.
            got: dict[str, list[np.ndarray]] = {label: [] for label, _ in paths}
            errors: dict[str, str] = {}
            for _ in range(repeats):
                for label, fn in paths:
                    if label in errors:
                        continue
                    try:
                        got[label].append(fn())
                    except (RuntimeError, subprocess.TimeoutExpired) as e:
                        errors[label] = str(e)[:60]
            meds = {label: float(np.median(np.concatenate(a))) for label, a in got.items() if a}
            base, read = meds.get(paths[0][0], float("nan")), meds.get(READ_PATH, float("nan"))
            for label, _ in paths:
                arr = np.concatenate(got[label]) if got[label] else np.array([])
                if not len(arr):
                    rows.append((kind, size, label, 0, float("nan"), float("nan"), float("nan"), float("nan"),
                                 errors.get(label, "no round trip came back")))
                    continue
                rows.append((kind, size, label, len(arr), meds[label], np.percentile(arr, 99),
                             meds[label] / base, meds[label] / read, errors.get(label, "")))
    finally:
        router.close()
    load1 = os.getloadavg()
    print(f"one-way latency on loopback, RTT/2 ({os.cpu_count()} cores; load average {load0[0]:.1f} at start, "
          f"{load1[0]:.1f} at end: ratios within this run are what compare)")
    print(f"{'payload':<8} {'bytes':>8} {'path':<19} {'n':>5} {'median_ms':>10} {'p99_ms':>8} {'x_router':>8} "
          f"{'x_read':>7}")
    for kind, size, label, cnt, med, p99, ratio, ratio_read, note in rows:
        print(f"{kind:<8} {size:>8} {label:<19} {cnt:>5} {med:>10.3f} {p99:>8.3f} {ratio:>8.2f} {ratio_read:>7.2f}"
              + (f"  {note}" if note else ""))
    print(f"x_router: to raw zenoh via the router, which never reads the payload; x_read: to {READ_PATH} "
          "(the bytes reach Python at both ends)")
    for peer, why in missing.items():
        if why:
            print(f"{peer}: {why}")
    return 0


def pong(transport: str, *args: str) -> None:
    if transport == "zenoh":
        endpoint, link, path, kind = args
        _, close = zenoh_side(endpoint, link, path, kind, "pong")
    else:
        domain, kind = args
        os.environ.update(dds_env())
        _, close = dds_side(int(domain), kind, "pong")
    print("ready", flush=True)
    sys.stdin.readline()  # parent closes stdin to stop us
    close()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--pong", nargs="+", metavar="ARG")
    ap.add_argument("--dora", nargs="+", metavar="ARG")
    a = ap.parse_args()
    if a.pong:
        pong(*a.pong)
    elif a.dora:
        role, kind, *rest = a.dora
        dora_node(role, kind, *(int(rest[0]), rest[1]) if rest else ())
