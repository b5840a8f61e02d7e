"""VIO CPU per stereo frame on recorded inputs, without the stack: what the service spends on a
frame, repeatable and comparable between two versions of services/vio.

`record` renders the sim's stereo camera and IMU along an orbit in a scenario once
(tools/bench/vio.py's sequence: 640x480 rgb8 at 20 Hz, 200 Hz IMU) and stores them as the encoded
payloads the sim publishes (Image / Imu msgpack). `run` replays them the way services/vio/main.py
handles them: per frame the IMU samples since the previous frame decoded and converted
(messages.imu_sample), both images decoded and viewed (messages.pixels), the strategy's
process_frame called; CPU time (time.process_time, every thread) around all of it. `--pace-hz 20`
feeds them as the camera does: caches go cold between frames and a frame costs ~25 % more than
back to back, as in the service. It prints mean / median / p90 / p99 (the mean is what a share of
a core follows: with the window covariance every 2nd frame the median sits among the cheap frames)
and can write the estimates, so two versions can be checked for identical output. `ab` runs two
versions of the vio package (folders holding a copy of services/vio) alternately in fresh
processes: interleaved, so the machine's drift from minute to minute hits both alike. `service`
runs the vio service itself, fed over Zenoh behind a router of its own on a free loopback port,
and reads its CPU per frame, per thread and its page faults from /proc (Zenoh's receive included).

    python -m aeroperception.tools.bench.vio_replay record --frames 300 --out /tmp/vio_inputs.pkl
    git archive HEAD services/vio | tar -x -C /tmp/vio_before
    python -m aeroperception.tools.bench.vio_replay ab /tmp/vio_inputs.pkl /tmp/vio_before/services/vio services/vio
    python -m aeroperception.tools.bench.vio_replay service /tmp/vio_inputs.pkl /tmp/vio_before/services/vio services/vio
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def record(n_frames: int, out: str, scenario: str = "village") -> None:
    from aeroperception.schemas import Header, Image, Imu, Vector3, encode
    from aeroperception.tools.bench.vio import sim_sequence

    seq = sim_sequence(n_frames, scenario=scenario)
    frames = []
    for t, left, right in zip(seq.stamps_ns, seq.left, seq.right):
        enc = "mono8" if left.ndim == 2 else "rgb8"
        frames.append((t, encode(Image.from_numpy(left, enc, Header(stamp_ns=t, frame_id="camera_left_optical"))),
                       encode(Image.from_numpy(right, enc, Header(stamp_ns=t, frame_id="camera_right_optical")))))
    imu = [(s.t_ns, encode(Imu(header=Header(stamp_ns=s.t_ns, frame_id="base_link"),
                               angular_velocity_radps=Vector3.from_array(s.gyro_radps),
                               linear_acceleration_mps2=Vector3.from_array(s.accel_mps2)))) for s in seq.imu]
    infos = [encode(i) for i in seq.camera_infos]
    truth = [np.asarray(tr.position_enu_m, float) for tr in seq.truth]
    with open(out, "wb") as f:
        pickle.dump({"frames": frames, "imu": imu, "infos": infos, "truth": truth, "scenario": scenario}, f)
    print(f"{len(frames)} stereo frames, {len(imu)} IMU samples -> {out}")


def load_vio(pkg_dir: str | None):
    """The vio package in `pkg_dir` (a copy of services/vio) imported under a name of its own, or
    the installed one."""
    if pkg_dir is None or Path(pkg_dir).resolve() == Path(__file__).resolve().parents[2] / "services" / "vio":
        import aeroperception.services.vio as pkg
        return pkg
    name = "vio_under_test"
    spec = importlib.util.spec_from_file_location(name, Path(pkg_dir) / "__init__.py",
                                                  submodule_search_locations=[str(pkg_dir)])
    pkg = importlib.util.module_from_spec(spec)
    sys.modules[name] = pkg
    spec.loader.exec_module(pkg)
    return pkg


def _service_process_settings(base: str) -> None:
    """What this version's service sets for its process at start (OpenCV's threads, malloc), so a
    replay costs what the service would: main.start does it there, which a replay does not run."""
    import cv2

    contract = importlib.import_module(f"{base}.contract")
    main = importlib.import_module(f"{base}.main")
    params = {p.name: p for p in contract.PARAMS}
    if "opencv_threads" in params and params["opencv_threads"].default > 0:
        cv2.setNumThreads(params["opencv_threads"].default)
    if hasattr(main, "keep_freed_memory"):
        main.keep_freed_memory()


def replay(data: dict, pkg_dir: str | None = None, profile: str | None = None, pace_hz: float = 0.0,
           threads: int | None = None) -> dict:
    """Per-frame CPU ms of the service's work on the recorded inputs, and the estimates."""
    from aeroperception.schemas import CameraInfo, Image, Imu, decode

    load_vio(pkg_dir)
    base = "vio_under_test" if "vio_under_test" in sys.modules else "aeroperception.services.vio"
    messages = importlib.import_module(f"{base}.messages")
    dto = importlib.import_module(f"{base}.dto")
    strategy = importlib.import_module(f"{base}.strategy")
    calibration = importlib.import_module(f"{base}.calibration")

    _service_process_settings(base)
    if threads is not None:
        import cv2
        cv2.setNumThreads(threads)
    infos = [decode(b, CameraInfo) for b in data["infos"]]
    calib = calibration.CameraCalibration.from_camera_infos(*infos)
    vio = strategy.create_strategy("klt_stereo", strategy.VioConfig())
    imu = data["imu"]
    imu_t = np.array([t for t, _ in imu])
    prof = None
    if profile:
        import cProfile
        prof = cProfile.Profile()
    cpu_ms, poses, covs, states = [], [], [], []
    prev = -1
    w0 = time.monotonic()
    for k, (t, left_b, right_b) in enumerate(data["frames"]):
        if pace_hz > 0:   # as the camera comes: caches go cold between frames, as in the service
            time.sleep(max(0.0, w0 + k / pace_hz - time.monotonic()))
        lo, hi = int(np.searchsorted(imu_t, prev, side="right")), int(np.searchsorted(imu_t, t, side="right"))
        prev = t
        if prof:
            prof.enable()
        c0 = time.process_time()
        samples = [messages.imu_sample(decode(b, Imu)) for _, b in imu[lo:hi]]
        left, right = decode(left_b, Image), decode(right_b, Image)
        frame = dto.NavCameraFrame(k + 1, t, messages.pixels(left), messages.pixels(right))
        window = dto.ImuWindow(samples[0].t_ns if samples else t, t, samples)
        try:
            out = vio.process_frame(frame, window, calib)
        except dto.VioDegradedError as e:
            out = e.output
        except dto.VioError:
            out = None
        cpu_ms.append((time.process_time() - c0) * 1e3)
        if prof:
            prof.disable()
        states.append(vio.health_snapshot().state)
        poses.append(None if out is None else out.world_T_body.tolist())
        covs.append(None if out is None else [out.pose_covariance_6x6.tolist(), out.twist_covariance_6x6.tolist()])
    if prof:
        prof.dump_stats(profile)
    return {"cpu_ms": cpu_ms, "poses": poses, "covs": covs, "states": states, "keyframes": vio.keyframes}


def summary(cpu_ms, skip: int = 5) -> dict:
    a = np.array(cpu_ms[skip:])
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "p99": float(np.percentile(a, 99)),
            "mean": float(a.mean()), "frames": len(a)}


def ate_m(poses, truth) -> float:
    """RMSE of position after a translation + rotation alignment (Umeyama without scale)."""
    idx = [i for i, p in enumerate(poses) if p is not None]
    est = np.array([np.asarray(poses[i])[:3, 3] for i in idx])
    gt = np.array([truth[i] for i in idx])
    me, mg = est.mean(0), gt.mean(0)
    U, _, Vt = np.linalg.svd((gt - mg).T @ (est - me))
    S = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    err = (est - me) @ R.T + mg - gt
    return float(np.sqrt((err ** 2).sum(1).mean()))


def _cpu_s(pid: int) -> float:
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / 100.0   # utime + stime, clock ticks (USER_HZ 100)


def _minflt(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[7])


def _threads_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread name (comm) of a process."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = f"{(task / 'comm').read_text().strip()}:{task.name}"
            out[name] = out.get(name, 0.0) + _cpu_s_path(task / "stat")
        except OSError:
            continue
    return out


def _cpu_s_path(stat: Path) -> float:
    f = stat.read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / 100.0


def gc_stats() -> None:
    """In the service's process: time Python's garbage collections per generation and write them
    to $VIO_REPLAY_GC_OUT at exit (a full collection walks every object the process holds)."""
    import gc
    import os

    out = os.environ.get("VIO_REPLAY_GC_OUT")
    if not out:
        return
    stats: dict[int, list] = {0: [0, 0.0], 1: [0, 0.0], 2: [0, 0.0]}
    t0 = [0.0]

    def cb(phase, info):
        if phase == "start":
            t0[0] = time.thread_time()
        else:
            s = stats[info["generation"]]
            s[0] += 1
            s[1] += time.thread_time() - t0[0]

    gc.callbacks.append(cb)
    import threading

    names: dict[int, str] = {}

    def note_threads():   # thread ids -> Python names, to name the per-thread CPU
        while True:
            names.update({t.native_id: t.name for t in threading.enumerate()})
            Path(out).write_text(json.dumps({"gc": stats, "objects": len(gc.get_objects()), "threads": names}))
            time.sleep(2.0)

    threading.Thread(target=note_threads, daemon=True, name="replay-notes").start()


def service_run(data: dict, pkg_dir: str | None, frames: int | None = None, rate_hz: float = 20.0) -> dict:
    """The vio service itself (its own process, behind its own router on a free loopback port) fed
    the recorded payloads over Zenoh at `rate_hz`, IMU first: its CPU (/proc/PID/stat, every
    thread: Zenoh's receive, decoding, the worker, OpenCV) over the replay, per frame."""
    import socket

    from aeroperception.schemas import CameraInfo, Image, Imu, Odometry, decode
    from aeroperception.services.runtime import Node

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ep = f"tcp/127.0.0.1:{port}"
    procs = [subprocess.Popen([sys.executable, "-m", "aeroperception.tools.cli", "router", "--listen", ep],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    launch = ("import sys, importlib; from aeroperception.tools.bench.vio_replay import load_vio, gc_stats; "
              "gc_stats(); pkg = load_vio(sys.argv[1] or None); "
              "sys.exit(importlib.import_module(pkg.__name__ + '.main').main(sys.argv[2:]))")
    try:
        time.sleep(1.0)
        vio = subprocess.Popen([sys.executable, "-c", launch, pkg_dir or "", "--connect", ep],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(vio)
        node = Node("vio_replay", connect=ep)
        node.connect(max_wait_s=10)
        outs = []
        node.subscribe("state/visual_odometry", Odometry, lambda m: outs.append(m.header.stamp_ns))
        from aeroperception.services.sim.qos import qos_for
        pubs = {k: node.publisher(k, Image, **qos_for(k)) for k in
                ("sensors/camera/left/image", "sensors/camera/right/image")}
        imu_pub = node.publisher("sensors/imu", Imu, **qos_for("sensors/imu"))
        info_pubs = [node.publisher(f"sensors/camera/{s}/info", CameraInfo) for s in ("left", "right")]
        infos = [decode(b, CameraInfo) for b in data["infos"]]
        t_end = time.monotonic() + 20
        while not (info_pubs[0].matched and imu_pub.matched) and time.monotonic() < t_end:
            time.sleep(0.1)
        time.sleep(1.0)   # subscribers declared; the service settled
        for p, i in zip(info_pubs, infos):
            p.publish(i)
        imu = [(t, decode(b, Imu)) for t, b in data["imu"]]
        todo = [(t, decode(lb, Image), decode(rb, Image)) for t, lb, rb in data["frames"][:frames]]
        time.sleep(0.5)
        k = 0
        c0, w0, th0, f0 = _cpu_s(vio.pid), time.monotonic(), _threads_cpu_s(vio.pid), _minflt(vio.pid)
        for n, (t, left, right) in enumerate(todo):
            while k < len(imu) and imu[k][0] <= t:
                imu_pub.publish(imu[k][1])
                k += 1
            pubs["sensors/camera/left/image"].publish(left)
            pubs["sensors/camera/right/image"].publish(right)
            if n % 20 == 0:
                for p, i in zip(info_pubs, infos):
                    p.publish(i)
            time.sleep(max(0.0, w0 + (n + 1) / rate_hz - time.monotonic()))
        time.sleep(0.3)
        c1, w1, th1, f1 = _cpu_s(vio.pid), time.monotonic(), _threads_cpu_s(vio.pid), _minflt(vio.pid)
        node.close()
        threads = {k: round((v - th0.get(k, 0.0)) * 1e3 / len(todo), 2) for k, v in th1.items()}
        return {"cpu_ms_per_frame": (c1 - c0) * 1e3 / len(todo), "core_pct": 100 * (c1 - c0) / (w1 - w0),
                "frames": len(todo), "outputs": len(outs), "page_faults_per_frame": (f1 - f0) / len(todo),
                "threads_ms_per_frame": {k: v for k, v in sorted(threads.items(), key=lambda kv: -kv[1]) if v > 0}}
    finally:
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()


def _service_cli(a) -> int:
    import os

    os.environ["AERO_LINKS"] = a.links   # the service inherits it
    data = pickle.load(open(a.data, "rb"))
    rows: dict[str, list] = {d: [] for d in a.vio}
    for r in range(a.rounds):
        for d in (a.vio if r % 2 == 0 else a.vio[::-1]):
            load = Path("/proc/loadavg").read_text().split()[0]
            s = service_run(data, d, a.frames)
            rows[d].append(s)
            print(f"round {r} {d}: {s['cpu_ms_per_frame']:.2f} ms CPU per frame, {s['core_pct']:.1f} % of a core, "
                  f"{s['outputs']}/{s['frames']} poses, {s['page_faults_per_frame']:.0f} page faults (load {load}); by thread {s['threads_ms_per_frame']}", flush=True)
    for d, rs in rows.items():
        v = [s["cpu_ms_per_frame"] for s in rs]
        print(f"{d}: median {np.median(v):.2f} ms per frame [{min(v):.2f}-{max(v):.2f}] over {len(v)} runs")
    return 0


def _run_cli(a) -> int:
    data = pickle.load(open(a.data, "rb"))
    res = replay(data, a.vio, a.profile, a.pace_hz, a.threads)
    s = summary(res["cpu_ms"])
    s.update(ate_m=ate_m(res["poses"], data["truth"]), keyframes=res["keyframes"],
             tracking=sum(1 for x in res["states"] if x == 1))
    if a.poses:
        json.dump({k: res[k] for k in ("poses", "covs", "states", "cpu_ms")}, open(a.poses, "w"))
    print(json.dumps(s))
    return 0


def _ab_cli(a) -> int:
    rows = {"A": [], "B": []}
    for r in range(a.rounds):
        for name, d in (("A", a.a), ("B", a.b)) if r % 2 == 0 else (("B", a.b), ("A", a.a)):
            cmd = [sys.executable, "-m", "aeroperception.tools.bench.vio_replay", "run", a.data, "--vio", d]
            if a.threads is not None:
                cmd += ["--threads", str(a.threads)]
            if a.poses:
                cmd += ["--poses", f"{a.poses}_{name}.json"]
            if a.pace_hz:
                cmd += ["--pace-hz", str(a.pace_hz)]
            load = Path("/proc/loadavg").read_text().split()[0]
            s = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])
            rows[name].append(s)
            print(f"round {r} {name}: mean {s['mean']:.2f} median {s['median']:.2f} p90 {s['p90']:.2f} "
                  f"p99 {s['p99']:.2f} ms CPU/frame, "
                  f"ATE {s['ate_m']:.3f} m, kf {s['keyframes']}, tracking {s['tracking']} (load {load})", flush=True)
    for name in ("A", "B"):
        print(f"{name} ({a.a if name == 'A' else a.b}), over the rounds:", ", ".join(
            f"{k} {np.median(v):.2f} ms [{min(v):.2f}-{max(v):.2f}]"
            for k, v in ((k, [s[k] for s in rows[name]]) for k in ("mean", "median", "p90"))))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="vio_replay", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("record")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--scenario", default="village")
    p.add_argument("--out", default="/tmp/vio_inputs.pkl")
    p = sub.add_parser("run")
    p.add_argument("data")
    p.add_argument("--vio", default=None, help="folder holding a copy of services/vio (default: the installed one)")
    p.add_argument("--threads", type=int, default=None,
                   help="cv2.setNumThreads (default: what this version's service sets at start)")
    p.add_argument("--profile", default=None, help="write cProfile stats here")
    p.add_argument("--pace-hz", type=float, default=0.0, help="feed frames at this rate (0: back to back)")
    p.add_argument("--poses", default=None, help="write the estimates here (JSON) to compare versions")
    p = sub.add_parser("ab")
    p.add_argument("data")
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--poses", default=None, help="prefix: write each version's estimates to PREFIX_A/B.json")
    p.add_argument("--pace-hz", type=float, default=0.0, help="feed frames at this rate (0: back to back)")
    p = sub.add_parser("service", help="the vio service fed over Zenoh; its process CPU per frame")
    p.add_argument("data")
    p.add_argument("vio", nargs="+", help="folders holding a copy of services/vio, run alternately")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--links", choices=("router", "direct"), default="direct",
                   help="$AERO_LINKS for the service and the feeder (aero up: direct)")
    a = ap.parse_args(argv)
    if a.cmd == "record":
        record(a.frames, a.out, a.scenario)
        return 0
    return {"run": _run_cli, "ab": _ab_cli, "service": _service_cli}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
