"""`aero eval lidar|vio|detector|objects|trajectory`: accuracy of the perception services against truth (simulator truth or
real recordings), printed as a table and written as JSON (+ PNG for vio)."""
from __future__ import annotations

import argparse
import importlib

from aeroperception.tools.common import CliError, add_session_arguments


def register(sub: argparse._SubParsersAction) -> None:
    ev = sub.add_parser("eval", help="accuracy against truth (tables, JSON)")
    esub = ev.add_subparsers(dest="eval_cmd", required=True)
    p = esub.add_parser("lidar", help="ground removal P/R/F1 and obstacle FP/FN vs sim truth; KITTI vs Patchwork++")
    p.add_argument("--scenario", action="append", default=None,
                   help="scenario to render scans in (repeatable; default open_field, village, slope_forest)")
    p.add_argument("--kitti", nargs="*", default=None, metavar="BIN",
                   help="SemanticKITTI .bin scans (default: ../shared/data/kitti when present)")
    p.add_argument("-n", type=int, default=20, help="scans per scenario")
    p.add_argument("--altitude", type=float, action="append", default=None, metavar="M",
                   help="flight height above the terrain (repeatable; default 4 m)")
    p.add_argument("--json", default=None, metavar="FILE", help="write the figures as JSON")
    p.set_defaults(func=_lidar)

    p = esub.add_parser("vio", help="VIO vs ground truth (EuRoC folder or live sim): ATE, RPE, drift, NEES; JSON + PNG")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--euroc", metavar="DIR", help="EuRoC/ASL dataset folder (contains mav0/)")
    src.add_argument("--live", action="store_true", help="the running vio against sim/truth/state")
    p.add_argument("--duration", type=float, default=60.0, help="--live: seconds to record (at most, with --until-landed)")
    p.add_argument("--until-landed", action="store_true",
                   help="--live: stop once the vehicle (sim truth) has flown and is down and disarmed again")
    add_session_arguments(p)
    p.add_argument("--out", default="vio_eval", metavar="DIR", help="where to write vio_eval.json / .png")
    p.add_argument("--strategy", default="klt_stereo", help="VioStrategy (klt_stereo, klt_mono)")
    p.add_argument("--align", default="se3", choices=["se3", "yaw"], help="trajectory alignment for ATE")
    p.add_argument("--rpe-delta-s", type=float, default=1.0, help="RPE window")
    p.add_argument("--max-frames", type=int, default=None)
    p.set_defaults(func=lambda a: importlib.import_module("aeroperception.tools.eval.vio").run(
        a.euroc, a.out, a.strategy, a.align, a.rpe_delta_s, a.max_frames, a if a.live else None))

    p = esub.add_parser("detector", help="mAP@0.5 and per-class P/R of a YOLOv8 ONNX vs sim truth boxes (held-out renders or live)")
    p.add_argument("--model", default=None, metavar="ONNX", help="default: the bundled aero_sim_det.onnx")
    p.add_argument("--live", action="store_true",
                   help="a running stack: sensors/camera/left/image through the model vs sim/truth/boxes")
    p.add_argument("--detections", action="store_true",
                   help="with --live: the detector service's perception/detections vs sim/truth/boxes")
    p.add_argument("--set", action="append", default=None, dest="sets", metavar="NAME",
                   help="offline held-out set (repeatable; default all: village@1001, village@1002, open_field, slope_forest)")
    p.add_argument("-n", type=int, default=60, help="offline: images per held-out set")
    p.add_argument("--duration", type=float, default=20.0, help="--live: seconds to record at most")
    p.add_argument("--until-landed", action="store_true",
                   help="--live: evaluate one flight: stop once the vehicle (sim truth) has flown and is down and disarmed")
    p.add_argument("--max-frames", type=int, default=None,
                   help="--live: frame pairs to evaluate at most (default 60; unbounded with --until-landed)")
    p.add_argument("--period", type=float, default=0.0, metavar="S",
                   help="--live: evaluate at most one frame per S seconds (default: every frame)")
    p.add_argument("--conf", type=float, default=0.40, help="operating threshold for precision/recall")
    p.add_argument("--nms", type=float, default=0.45, help="NMS IoU threshold")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    p.add_argument("--json", default=None, metavar="FILE", help="write the figures as JSON")
    add_session_arguments(p)
    p.set_defaults(func=_detector)
    _register_objects(esub)
    _register_trajectory(esub)


def _register_trajectory(esub) -> None:
    p = esub.add_parser("trajectory", help="a flight against its mission's legs by sim truth: time, cross-track "
                                           "RMS/max, peak speed/acceleration/jerk, corner overshoot, tracking error")
    p.add_argument("--live", action="store_true", required=True, help="a running stack flying a mission")
    p.add_argument("--duration", type=float, default=120.0, help="seconds to record (at most, with --until-landed)")
    p.add_argument("--until-landed", action="store_true",
                   help="stop once the vehicle (sim truth) has flown and is down and disarmed again")
    p.add_argument("--json", default=None, metavar="FILE", help="write the figures as JSON")
    add_session_arguments(p)
    p.set_defaults(func=lambda a: importlib.import_module("aeroperception.tools.eval.trajectory").run_live(a))


def _register_objects(esub) -> None:
    p = esub.add_parser("objects", help="tracked objects vs the scenario's targets: found / missed / duplicated, "
                                        "false tracks, position error, ID switches (live, or a recorded flight replayed)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--live", action="store_true", help="a running stack's perception/objects")
    src.add_argument("--replay", default=None, metavar="MCAP",
                     help="run the objects logic offline over a recorded flight (aero record --images with "
                          "perception/detections, state/vehicle, sensors/camera/*/info, fmu/out/home_position)")
    p.add_argument("--scenario", default=None,
                   help="the sim's scenario, the truth (name or YAML path; default: --live village, "
                        "--replay the one the recording names)")
    p.add_argument("--param", action="append", default=None, metavar="NAME=VALUE",
                   help="--replay: an objects parameter instead of its default (repeatable)")
    p.add_argument("--duration", type=float, default=60.0, help="--live: seconds to score (at most, with --until-landed)")
    p.add_argument("--until-landed", action="store_true",
                   help="--live: stop once the vehicle (sim truth) has flown and is down and disarmed again")
    p.add_argument("--json", default=None, metavar="FILE", help="write the figures as JSON")
    add_session_arguments(p)
    p.set_defaults(func=_objects)


def _objects(a) -> int:
    mod = importlib.import_module("aeroperception.tools.eval.objects")
    if a.replay is None:
        if a.param:
            raise CliError("--param needs --replay (a live service's parameters: aero param set objects NAME VALUE)")
        return mod.run_live(a)
    if a.until_landed:
        raise CliError("--until-landed needs --live (a replay runs over the whole recording)")
    return mod.run_replay(a)


def _detector(a) -> int:
    mod = importlib.import_module("aeroperception.tools.eval.detector")
    if a.live:
        return mod.run_live(a)
    if a.detections:
        from aeroperception.tools.common import CliError
        raise CliError("--detections needs --live (it evaluates the running detector service)")
    return mod.run_offline(a.model or mod.default_model(), a.n, a.json, a.threads, a.sets, conf=a.conf, nms=a.nms)


def _lidar(a) -> int:
    from aeroperception.services.runtime.data import kitti_scans

    mod = importlib.import_module("aeroperception.tools.eval.lidar")
    scenarios = a.scenario or ["open_field", "village", "slope_forest"]
    kitti = a.kitti if a.kitti is not None else [str(p) for p in kitti_scans()]
    if any(not 0.3 <= h <= 100.0 for h in a.altitude or ()):
        raise CliError("--altitude: give a height above the terrain between 0.3 and 100 m")
    return mod.run(scenarios, kitti, a.n, a.json, a.altitude or [4.0])
