"""`aero bench record`: what recording costs. A publisher offers a camera-on load (stereo
640x480 rgb8 at 20 Hz, IMU 200 Hz, state 50 Hz) to the real recorder service process (preset
all, images on) over a router on loopback; the table gives the sustained messages/s and MB/s
written, what was dropped, the file's MB/s after compression and the recorder's CPU %
(from /proc, user + system, 100 % = one core)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from aeroperception.schemas import Header, Image, Imu, VehicleState, encode
from aeroperception.services.recorder.files import info
from aeroperception.services.runtime.node import encoding_for
from aeroperception.services.runtime.session import make_config, open_session

from aeroperception.tools.harness import free_port, proc_stats
from aeroperception.tools.cli.router import open_router

STREAMS = (("sensors/camera/left/image", 20.0), ("sensors/camera/right/image", 20.0),
           ("sensors/imu", 200.0), ("state/vehicle", 50.0))


def _cpu_s(pid: int) -> float:
    stats = proc_stats(pid)
    if stats is None:
        raise RuntimeError(f"the recorder (pid {pid}) exited during the benchmark")
    return stats[1]


def _frame(i: int) -> np.ndarray:
    """A camera-like picture (smooth gradients, texture, sensor noise): compresses like a real one."""
    y, x = np.mgrid[0:480, 0:640]
    base = ((x + 3 * i) % 256 * 0.6 + (y % 64) * 1.5).astype(np.uint8)
    noise = np.random.default_rng(i).integers(0, 8, (480, 640), dtype=np.uint8)
    g = base + noise
    return np.stack([g, g // 2 + 40, 255 - g], axis=-1)


def _payloads() -> dict[str, list[bytes]]:
    imgs = [encode(Image.from_numpy(_frame(i), header=Header(stamp_ns=i, frame_id="cam"))) for i in range(4)]
    return {"sensors/camera/left/image": imgs, "sensors/camera/right/image": imgs[::-1],
            "sensors/imu": [encode(Imu(header=Header(stamp_ns=1)))],
            "state/vehicle": [encode(VehicleState(header=Header(stamp_ns=1)))]}


def _one(endpoint: str, compression: str, duration_s: float, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen([sys.executable, "-m", "aeroperception.services.recorder", "--connect", endpoint,
                             "--param", "preset=all", "--param", "record_images=true",
                             "--param", f"compression={compression}", "--param", f"output_dir={out}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    session = open_session(make_config(None, endpoint, mode="client"), max_wait_s=5)
    types = {"sensors/camera/left/image": Image, "sensors/camera/right/image": Image, "sensors/imu": Imu,
             "state/vehicle": VehicleState}
    pubs = {k: session.declare_publisher(k, encoding=encoding_for(types[k])) for k, _ in STREAMS}
    payloads = _payloads()
    try:
        deadline = time.monotonic() + 10
        while not any(r.ok is not None for r in session.liveliness().get("aero/alive/default/recorder", timeout=0.5)):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("the recorder did not start")
        time.sleep(1.5)   # its parameter query at start is over
        cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
        nxt = {k: t0 for k, _ in STREAMS}
        sent = offered = 0
        while (now := time.monotonic()) < t0 + duration_s:
            for key, hz in STREAMS:
                while nxt[key] <= now:
                    p = payloads[key][sent % len(payloads[key])]
                    pubs[key].put(p)
                    sent += 1
                    offered += len(p)
                    nxt[key] += 1.0 / hz
            time.sleep(max(0.0, min(nxt.values()) - time.monotonic()))
        wall = time.monotonic() - t0
        cpu = _cpu_s(proc.pid) - cpu0
    finally:
        for p in pubs.values():
            p.undeclare()
        session.close()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    files = sorted(out.glob("*.mcap"))
    ours = [c for f in files for c in info(f).channels if c.topic in dict(STREAMS)]   # not its own diagnostics
    written = sum(c.count for c in ours)
    size = sum(f.stat().st_size for f in files)
    return {"compression": compression, "offered_msgs_s": sent / wall, "offered_mb_s": offered / wall / 1e6,
            "msgs_s": written / wall, "mb_s": sum(c.bytes for c in ours) / wall / 1e6,
            "lost": sent - written, "file_mb_s": size / wall / 1e6, "cpu_pct": 100 * cpu / wall}


def run(duration_s: float = 10.0, compressions: str = "zstd,lz4,none") -> int:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(None, [endpoint])
    rows = []
    try:
        with tempfile.TemporaryDirectory(prefix="aero-bench-record-") as d:
            for comp in compressions.split(","):
                rows.append(_one(endpoint, comp, duration_s, Path(d) / comp))
    finally:
        router.close()
    print(f"recorder, preset all + images, {duration_s:g} s each ({os.cpu_count()} cores): stereo 640x480 rgb8 "
          "20 Hz + IMU 200 Hz + state 50 Hz")
    print(f"{'compression':<12} {'offered msg/s':>13} {'offered MB/s':>12} {'written msg/s':>13} {'MB/s':>7} "
          f"{'lost':>5} {'file MB/s':>9} {'CPU %':>6}")
    for r in rows:
        print(f"{r['compression']:<12} {r['offered_msgs_s']:>13.0f} {r['offered_mb_s']:>12.1f} {r['msgs_s']:>13.0f} "
              f"{r['mb_s']:>7.1f} {r['lost']:>5} {r['file_mb_s']:>9.1f} {r['cpu_pct']:>6.0f}")
    return 0
