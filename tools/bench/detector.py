"""`aero bench detector`: what one camera frame costs the detector on this machine, per stage
(letterbox preprocessing, inference, decode + NMS postprocessing), for the bundled model (when it
is in the package) and a YOLOv8n-sized graph (tools/training/yolov8n_graph.py, built here: 8.7 GFLOPs at
640, random weights calibrated to ~50 candidate boxes), at 640 and 320 input, 1 and 2 onnxruntime
threads, fp32 and int8 (onnxruntime dynamic quantization). The baseline, measured interleaved in
the same run on the same session, is a bare `session.run` on a ready tensor: the ratio says
what the detector's own code adds around inference. The frame is a village render from the sim.
Every row runs on the ONNX Runtime execution provider asked for (`--provider`, the detector's
`execution_provider`: cpu by default) and says which provider the session really ran on.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from aeroperception.services.detector import contract
from aeroperception.services.detector.logic import resolve_model_path
from aeroperception.services.detector.yolo import ModelError, YoloModel, letterbox, session_providers

WARMUP = 3


def village_frame(scenario: str = "village") -> np.ndarray:
    """One 640x480 rgb8 left-camera render of the scenario, looking along the street."""
    from aeroperception.services.sim.sensors.rig import build_sensors
    from aeroperception.services.sim.sensors.synthetic import orbit_truth
    from aeroperception.services.sim.world.scenario import load_scenario

    scn = load_scenario(scenario)
    stereo = build_sensors(scn).stereo
    (x, y, z), _ = scn.start_pose()
    truth = orbit_truth(0, center_enu_m=(x, y + 8.0, z + 2.0), radius_m=8.0, roll_amp_rad=0.0, pitch_amp_rad=0.0)
    left, _ = stereo.render(truth)
    return left if left.ndim == 3 else np.repeat(left[:, :, None], 3, axis=2)


def ort_providers() -> list[str]:
    import onnxruntime as ort

    return ort.get_available_providers()


def _stats(ms: list[float]) -> tuple[float, float]:
    a = np.asarray(ms)
    return float(np.median(a)), float(np.percentile(a, 99))


def bench_model(path: Path, threads: int, input_hw: tuple[int, int] | None, image: np.ndarray, n: int,
                provider: str = "cpu") -> dict:
    """Stage times (ms lists) of `n` frames through YoloModel, and bare session.run interleaved."""
    m = YoloModel.load(path, threads=threads, input_hw=input_hw, provider=provider)
    bare_tensor, _ = m.preprocess(image, "rgb")
    feed = {m.input_name: bare_tensor}
    out = {"pre": [], "infer": [], "post": [], "total": [], "bare": [], "dets": 0, "input_hw": m.input_hw,
           "provider": m.session.get_providers()[0]}
    for i in range(n + WARMUP):
        t0 = time.perf_counter()
        tensor, info = m.preprocess(image, "rgb")
        t1 = time.perf_counter()
        y = m.infer(tensor)
        t2 = time.perf_counter()
        dets = m.postprocess(y, info, image.shape[:2], 0.40, 0.45)
        t3 = time.perf_counter()
        m.session.run(None, feed)
        t4 = time.perf_counter()
        if i >= WARMUP:
            for k, v in (("pre", t1 - t0), ("infer", t2 - t1), ("post", t3 - t2), ("total", t3 - t0), ("bare", t4 - t3)):
                out[k].append(v * 1e3)
            out["dets"] = len(dets)
    return out


def _quantize(src: Path, dst: Path) -> Path:
    import logging

    from onnxruntime.quantization import QuantType, quantize_dynamic

    logging.getLogger().setLevel(logging.ERROR)          # its "consider pre-processing" advice
    quantize_dynamic(str(src), str(dst), weight_type=QuantType.QUInt8)
    return dst


def _models(tmp: Path, image: np.ndarray, sizes: list[int],
            extra: list[Path]) -> list[tuple[str, Path, tuple[int, int] | None]]:
    """(label, path, input size or None for the model's own) for every model to bench."""
    from aeroperception.tools.training.yolov8n_graph import build, calibrate_scores

    out = []
    bundled = resolve_model_path(contract.BUNDLED_MODEL)
    if not bundled.is_file():
        print(f"(no bundled model at {bundled})")
    given = [("bundled", bundled)] * bundled.is_file() + [(p.stem[:10], p) for p in extra]
    for i, (name, path) in enumerate(given):
        q = _quantize(path, tmp / f"{i}_int8.onnx")
        for prec, p in (("fp32", path), ("int8", q)):
            try:
                YoloModel.load(p, input_hw=(sizes[0], sizes[0]))
                out += [(f"{name} {prec}", p, (s, s)) for s in sizes]
            except ModelError:                                  # fixed input size: its own only
                out.append((f"{name} {prec}", p, None))
    for s in sizes:
        fp32 = tmp / f"yolov8n_{s}.onnx"
        info = build(fp32, (s, s), cls_bias=0.0)
        tensor, _ = letterbox(image, (s, s), 32, channels="rgb")
        calibrate_scores(fp32, info["cls_convs"], tensor)
        print(f"YOLOv8n-sized graph {s}x{s}: {info['gflops']:.2f} GFLOPs, {info['params'] / 1e6:.2f} M parameters, "
              f"{info['anchors']} anchors")
        out += [("yolov8n-size fp32", fp32, (s, s)), ("yolov8n-size int8", _quantize(fp32, tmp / f"yolov8n_{s}_int8.onnx"), (s, s))]
    return out


def run(n: int = 30, scenario: str = "village", sizes: tuple[int, ...] = (640, 320),
        threads: tuple[int, ...] = (1, 2), models: tuple[str, ...] = (), provider: str = "cpu") -> int:
    extra = [Path(m).expanduser() for m in models]
    try:
        session_providers(provider, ort_providers())
        for m in extra:
            YoloModel.load(m, provider=provider)
    except ModelError as e:
        print(f"aero bench detector: {e}", file=sys.stderr)
        return 2
    image = village_frame(scenario)
    rows = []
    with tempfile.TemporaryDirectory(prefix="aero-bench-detector-") as d:
        for label, path, hw in _models(Path(d), image, list(sizes), extra):
            for t in threads:
                r = bench_model(path, t, hw, image, n, provider)
                rows.append((label, r, t))
    ran = sorted({r["provider"] for _, r, _ in rows})
    print(f"{n} frames per row ({WARMUP} warm-up), {image.shape[1]}x{image.shape[0]} {scenario} render; ms; "
          f"execution provider {provider}: ran on {', '.join(ran)}")
    print(f"{'model':<18} {'input':>7} {'thr':>3} | {'pre p50':>7} {'p99':>6} | {'infer p50':>9} {'p99':>6} | "
          f"{'post p50':>8} {'p99':>6} | {'total p50':>9} {'p99':>6} {'Hz':>5} | {'bare run p50':>12} {'p99':>6} | "
          f"{'x bare':>6} {'dets':>4}")
    for label, r, t in rows:
        (pre, pre99), (inf, inf99), (post, post99), (tot, tot99), (bare, bare99) = (
            _stats(r[k]) for k in ("pre", "infer", "post", "total", "bare"))
        hw = r["input_hw"]
        print(f"{label:<18} {f'{hw[1]}x{hw[0]}':>7} {t:>3} | {pre:>7.2f} {pre99:>6.2f} | {inf:>9.2f} {inf99:>6.2f} | "
              f"{post:>8.2f} {post99:>6.2f} | {tot:>9.2f} {tot99:>6.2f} {1e3 / tot:>5.1f} | {bare:>12.2f} {bare99:>6.2f} | "
              f"{tot / bare:>6.2f} {r['dets']:>4}")
    print("x bare: total (pre + infer + post) / bare session.run median, same session, interleaved")
    return 0
