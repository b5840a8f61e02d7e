"""`aero bench pubsub|sim|flight|stack|lidar|vio|detector|objects|record|soak`: benchmarks that print median / p99 and the ratio to the raw
baseline measured in the same run. Tests check correctness; these report speed."""
from __future__ import annotations

import argparse
import importlib

from aeroperception.services.sim.contract import SENSOR_CHOICES
from aeroperception.tools.common import CliError


def _bench(module: str, call):
    """The sub-command's function, `call(module, args)`: a bench that cannot run (a stack that did
    not come up, a helper process that failed) says so in one line, not with a traceback."""
    def func(args):
        try:
            return call(importlib.import_module(f"aeroperception.tools.bench.{module}"), args)
        except RuntimeError as e:
            raise CliError(f"bench {module}: {e}") from None
    return func


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks (tables of median, p99, ratio to baseline)")
    bsub = bench.add_subparsers(dest="bench_cmd", required=True)
    p = bsub.add_parser("pubsub", help="raw zenoh vs typed runtime pub/sub latency (state, image); --peers: "
                                       "also peer-to-peer, dora-rs and Cyclone DDS")
    p.add_argument("-n", type=int, default=1000, help="round trips for the small message")
    p.add_argument("--port", type=int, default=17480, help="loopback port of the benchmark router")
    p.add_argument("--peers", action="store_true",
                   help="also zenoh peer-to-peer and as peers the router introduces (raw and typed), dora-rs and "
                        "Cyclone DDS (those installed: "
                        "pip install 'aeroperception[bench]')")
    p.add_argument("--repeat", type=int, default=3, help="interleaved rounds of every path (n split among them)")
    p.set_defaults(func=_bench("pubsub", lambda m, a: m.run(
        a.n, a.port, a.peers, max(1, a.repeat))))
    p = bsub.add_parser("sim", help="sensor render times and achieved rates")
    p.add_argument("-n", type=int, default=50, help="frames per sensor")
    p.add_argument("--scenario", default="village")
    p.set_defaults(func=_bench("sim", lambda m, a: m.run(a.n, a.scenario)))
    p = bsub.add_parser("flight", help="hot path state -> planner -> fmu -> MAVLink, with the sim profile running")
    p.add_argument("--duration", type=float, default=20.0, help="seconds of hover to measure")
    p.add_argument("--sensors", default="none", choices=SENSOR_CHOICES, help="sim sensor load while measuring")
    p.add_argument("--priorities", default="on", choices=["on", "off"],
                   help="aero up's scheduling priorities (tools/profiles.yaml); off: all at the default")
    p.add_argument("--links", default="direct", choices=["direct", "router"], help="aero up --links (default direct)")
    p.set_defaults(func=_bench("flight", lambda m, a: m.run(
        a.duration, a.sensors, a.priorities == "on", a.links)))
    p = bsub.add_parser("stack", help="is this machine big enough: the whole stack hovering in the village; per "
                                      "process CPU %% and RSS, achieved vs rated rates, the hot path, idle %%, a verdict")
    p.add_argument("--profile", default="sim", help="aero up profile (sim, viz, ...)")
    p.add_argument("--sensors", default="all", choices=SENSOR_CHOICES,
                   help="what the sim renders (as aero up --sensors)")
    p.add_argument("--duration", type=float, default=30.0, help="seconds measured (after take-off and settling)")
    p.add_argument("--scenario", default="village")
    p.add_argument("--links", default="direct", choices=["direct", "router"], help="aero up --links (default direct)")
    p.set_defaults(func=_bench("stack", lambda m, a: m.run(
        a.profile, a.sensors, a.duration, a.scenario, a.links)))
    p = bsub.add_parser("lidar", help="150k-point scan -> obstacles -> costmap per stage vs the Open3D pipeline")
    p.add_argument("-n", type=int, default=20, help="scans per pipeline")
    p.add_argument("--scenario", default="village")
    p.set_defaults(func=_bench("lidar", lambda m, a: m.run(a.n, a.scenario)))
    p = bsub.add_parser("vio", help="VIO front end / back end / total / CPU per stereo frame vs bare OpenCV KLT, "
                                    "on rendered or (--euroc) real frames")
    p.add_argument("-n", type=int, default=200, help="frames (rendered by the sim's camera, or the recording's first N; "
                                                      "not timed)")
    p.add_argument("--scenario", default="village")
    p.add_argument("--strategy", default="klt_stereo")
    p.add_argument("--euroc", metavar="DIR", help="real frames + IMU from an EuRoC/ASL folder (e.g. "
                                                  "../shared/data/euroc/MH_01_clip) instead of rendered ones")
    p.set_defaults(func=_bench("vio", lambda m, a: m.run(a.n, a.scenario, a.strategy, a.euroc)))
    p = bsub.add_parser("detector", help="detector pre / infer / post per frame: bundled model and a YOLOv8n-sized "
                                         "graph, 640/320, 1/2 threads, fp32/int8, vs bare session.run")
    p.add_argument("-n", type=int, default=30, help="frames per configuration")
    p.add_argument("--scenario", default="village", help="the rendered frame's scenario")
    p.add_argument("--sizes", default="640,320", help="input sizes (square), comma-separated")
    p.add_argument("--threads", default="1,2", help="onnxruntime intra-op thread counts, comma-separated")
    p.add_argument("--model", action="append", default=[], metavar="ONNX",
                   help="also bench this YOLOv8 / YOLO11 / YOLO26 export (repeatable)")
    p.add_argument("--provider", default="cpu", help="ONNX Runtime execution provider: cpu, cuda or tensorrt")
    p.set_defaults(func=_bench("detector", lambda m, a: m.run(
        a.n, a.scenario, tuple(int(s) for s in a.sizes.split(",")), tuple(int(t) for t in a.threads.split(",")),
        tuple(a.model), a.provider)))
    p = bsub.add_parser("objects", help="objects service CPU per detection frame, 1-20 boxes, vs a full-frame disparity map")
    p.add_argument("-n", type=int, default=50, help="frames per box count")
    p.add_argument("--scenario", default="village", help="the rendered pair's scenario")
    p.set_defaults(func=_bench("objects", lambda m, a: m.run(a.n, a.scenario)))
    p = bsub.add_parser("record", help="recorder cost with images on: messages/s, MB/s, drops, CPU %%")
    p.add_argument("--duration", type=float, default=10.0, help="seconds per compression setting")
    p.add_argument("--compression", default="zstd,lz4,none", help="settings to compare (comma-separated)")
    p.set_defaults(func=_bench("record", lambda m, a: m.run(
        a.duration, a.compression)))
    p = bsub.add_parser("soak", help="fly missions in a loop for N minutes; RSS/CPU per service process")
    p.add_argument("--minutes", type=float, default=30.0, help="how long to fly")
    p.add_argument("--sensors", default="all", choices=SENSOR_CHOICES, help="sim sensors rendered meanwhile")
    p.add_argument("--period", type=float, default=5.0, help="seconds between /proc samples")
    p.add_argument("--json", default=None, metavar="FILE", help="write the results as JSON too")
    p.set_defaults(func=_bench("soak", lambda m, a: m.run(
        a.minutes, a.sensors, a.period, a.json)))
