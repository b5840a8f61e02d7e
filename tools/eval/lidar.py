"""`aero eval lidar`: ground removal and obstacle detection of the lidar pipeline against truth.

Simulated scenarios: scans rendered offline by the simulator's own LiDAR model at poses flown
over the scenario (the same code the running sim uses), labelled per point with the hit
geometry (sim/truth/lidar_labels semantics: 0 ground, 1 obstacle, 2 overhead). Metrics per
point within 0.5-10 m of the sensor (requirement LID-4's detection range):
  ground precision / recall / F1;
  obstacle false-positive rate = share of points marked obstacle that are not (non-obstacles marked);
  obstacle false-negative rate = share of true obstacle points not marked (obstacles missed),
  counting obstacle points in LID-1's height band only: at least min_obstacle_height_m above the
  true terrain (the bottom 10 cm of every object is "ground debris" by LID-1's definition).
Real scans: SemanticKITTI .bin files (float32 x, y, z, intensity), with Patchwork++ (PyPI
`pypatchworkpp`, when installed) run on the same scans as a public reference: agreement of the
ground masks and both speeds side by side.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aeroperception.services.lidar import contract
from aeroperception.services.lidar.pipeline import ObstaclePipeline, PipelineConfig, classify, level, sanitize
from aeroperception.services.runtime.config import build
from aeroperception.services.runtime.rotations import quat_to_rotmat

GROUND, OBSTACLE, OVERHEAD = 0, 1, 2
EVAL_RANGE_M = (0.5, 10.0)


@dataclass
class Scan:
    points: np.ndarray                 # (N, 3) sensor frame
    r_level_sensor: np.ndarray         # levelling rotation (the vehicle attitude x mount)
    sensor_above_vehicle_m: float = 0.0
    labels: np.ndarray | None = None   # truth per point (sim only)
    height_m: np.ndarray | None = None # true height of each point above the terrain (sim only)


@dataclass
class Counts:
    tp_g: int = 0
    fp_g: int = 0
    fn_g: int = 0
    marked: int = 0
    marked_wrong: int = 0
    true_obst: int = 0
    missed: int = 0
    ms: list[float] = field(default_factory=list)

    def add(self, pred_g: np.ndarray, pred_o: np.ndarray, truth: np.ndarray, in_band: np.ndarray) -> None:
        tg, to = truth == GROUND, truth == OBSTACLE
        self.tp_g += int((pred_g & tg).sum())
        self.fp_g += int((pred_g & ~tg).sum())
        self.fn_g += int((~pred_g & tg).sum())
        self.marked += int(pred_o.sum())
        self.marked_wrong += int((pred_o & ~to).sum())
        self.true_obst += int((to & in_band).sum())
        self.missed += int((to & in_band & ~pred_o).sum())

    def metrics(self) -> dict[str, float]:
        p = self.tp_g / max(1, self.tp_g + self.fp_g)
        r = self.tp_g / max(1, self.tp_g + self.fn_g)
        return {
            "ground_precision": p, "ground_recall": r, "ground_f1": 2 * p * r / max(1e-12, p + r),
            "obstacle_fp_rate": self.marked_wrong / max(1, self.marked),
            "obstacle_fn_rate": self.missed / max(1, self.true_obst),
            "obstacle_points": self.true_obst,
            "pipeline_ms_median": float(np.median(self.ms)) if self.ms else float("nan"),
        }


def sim_scans(scenario: str, n: int = 20, altitude_m: float = 4.0, seed: int = 0) -> list[Scan]:
    """`n` scans on a loop around the scenario's start at `altitude_m` above the terrain under
    each pose (on slope_forest's 10 deg slope a fixed height above the start would dip under
    the ground uphill), with the attitude oscillations of a flying vehicle (the sim's orbit)."""
    from aeroperception.services.sim.sensors.lidar import Lidar
    from aeroperception.services.sim.sensors.synthetic import orbit_truth
    from aeroperception.services.sim.world.scenario import load_scenario
    from aeroperception.services.sim.world.scene import Scene

    scn = load_scenario(scenario)
    scene = Scene(scn)
    lidar = Lidar(scene, scn.sensors.lidar, seed=scn.seed + seed)
    (x, y, z), _ = scn.start_pose()
    out = []
    for i in range(n):
        truth = orbit_truth(int(i * 0.5e9), center_enu_m=(x + 6.0, y, z + altitude_m), radius_m=6.0,
                            period_s=n * 0.5, roll_amp_rad=0.08, pitch_amp_rad=0.08)
        px, py = truth.position_enu_m[:2]
        truth.position_enu_m[2] = scn.ground_height_m(px, py) + altitude_m
        scan = lidar.scan(truth)
        r_wb = quat_to_rotmat(truth.q_enu_flu)
        r_ws = r_wb @ lidar.r_body_lidar
        world = scan.points_m @ r_ws.T + (truth.position_enu_m + r_wb @ lidar.t_body_lidar_m)
        terrain = np.array([scn.ground_height_m(px, py) for px, py in world[:, :2]])
        out.append(Scan(scan.points_m, r_ws, float((r_wb @ lidar.t_body_lidar_m)[2]), scan.labels,
                        world[:, 2] - terrain))
    return out


def evaluate(scans: list[Scan], cfg: PipelineConfig | None = None) -> dict[str, float]:
    cfg = cfg or build(PipelineConfig, contract.PARAMS)
    pipe = ObstaclePipeline(cfg)
    c = Counts()
    for s in scans:
        t0 = time.perf_counter()
        res = pipe.process(s.points, s.r_level_sensor, s.sensor_above_vehicle_m)
        c.ms.append((time.perf_counter() - t0) * 1e3)
        r = np.linalg.norm(s.points, axis=1)
        keep = np.isfinite(r) & (r >= EVAL_RANGE_M[0]) & (r <= EVAL_RANGE_M[1])
        pts = level(sanitize(s.points[keep], cfg.min_range_m, cfg.max_range_m, cfg.max_points), s.r_level_sensor)
        g, o = classify(pts, res.plane, cfg, s.sensor_above_vehicle_m)
        c.add(g, o, s.labels[keep], s.height_m[keep] >= cfg.min_obstacle_height_m)
    return c.metrics()


def kitti_scan(path: str | Path) -> Scan:
    """A SemanticKITTI .bin scan (float32 x, y, z, intensity; sensor level, z up)."""
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 4:
        raise ValueError(f"{path}: {raw.size} floats is not a whole number of (x, y, z, intensity) points")
    return Scan(raw.reshape(-1, 4)[:, :3].copy(), np.eye(3))


def compare_patchwork(scans: list[Scan], cfg: PipelineConfig | None = None) -> dict[str, float] | None:
    """Ground agreement (IoU and per-point agreement) with Patchwork++ and both speeds;
    None when pypatchworkpp is not installed."""
    try:
        import pypatchworkpp
    except ImportError:
        return None
    cfg = cfg or build(PipelineConfig, contract.PARAMS)
    params = pypatchworkpp.Parameters()
    params.verbose = False
    pw = pypatchworkpp.patchworkpp(params)
    pipe = ObstaclePipeline(cfg)
    ious, agree, ours_ms, pw_ms = [], [], [], []
    for s in scans:
        pts = sanitize(s.points, cfg.min_range_m, cfg.max_range_m, cfg.max_points)
        t0 = time.perf_counter()
        res = pipe.process(pts, s.r_level_sensor)
        ours_ms.append((time.perf_counter() - t0) * 1e3)
        ours, _ = classify(pts, res.plane, cfg)
        cloud = np.hstack([pts, np.zeros((len(pts), 1), np.float32)]).astype(np.float64)
        t0 = time.perf_counter()
        pw.estimateGround(cloud)
        pw_ms.append((time.perf_counter() - t0) * 1e3)
        theirs = np.zeros(len(pts), bool)
        theirs[np.asarray(pw.getGroundIndices(), dtype=np.int64)] = True
        ious.append((ours & theirs).sum() / max(1, (ours | theirs).sum()))
        agree.append(float((ours == theirs).mean()))
    return {"ground_iou": float(np.mean(ious)), "point_agreement": float(np.mean(agree)),
            "ours_ms_median": float(np.median(ours_ms)), "patchwork_ms_median": float(np.median(pw_ms))}


def run(scenarios: list[str], kitti: list[str], n: int, json_out: str | None,
        altitudes: list[float] = (4.0,)) -> int:
    report: dict[str, dict] = {}
    print(f"{'data':<22} {'ground P':>9} {'R':>7} {'F1':>7} {'obst FP':>8} {'obst FN':>8} {'ms':>7}")
    for name, alt in [(s, h) for s in scenarios for h in altitudes]:
        m = evaluate(sim_scans(name, n, altitude_m=alt))
        if len(altitudes) > 1:
            name = f"{name} @{alt:g} m"
        report[name] = m
        print(f"{name:<22} {m['ground_precision']:>9.3f} {m['ground_recall']:>7.3f} {m['ground_f1']:>7.3f} "
              f"{m['obstacle_fp_rate']:>8.3f} {m['obstacle_fn_rate']:>8.3f} {m['pipeline_ms_median']:>7.1f}")
    if kitti:
        cmp = compare_patchwork([kitti_scan(p) for p in kitti])
        if cmp is None:
            print("kitti: install pypatchworkpp for the Patchwork++ comparison")
        else:
            report["kitti_vs_patchwork++"] = cmp
            print(f"KITTI vs Patchwork++ ({len(kitti)} scans): ground IoU {cmp['ground_iou']:.3f}, "
                  f"agreement {cmp['point_agreement']:.3f}; ours {cmp['ours_ms_median']:.1f} ms, "
                  f"Patchwork++ {cmp['patchwork_ms_median']:.1f} ms")
    if json_out:
        Path(json_out).write_text(json.dumps(report, indent=2))
        print(f"wrote {json_out}")
    return 0
