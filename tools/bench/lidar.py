"""`aero bench lidar`: a 150k-point scan -> obstacles -> costmap, per stage, against the
as-specified Open3D pipeline (voxel_down_sample, segment_plane, height filter, grid) measured in
the same run as the baseline; and the same on a real KITTI scan when ../shared/data is there.
"""
from __future__ import annotations

import time
import numpy as np

from aeroperception.services.lidar.costmap import CostmapConfig, RollingCostmap
from aeroperception.services.lidar.pipeline import ObstaclePipeline, PipelineConfig, sanitize
from aeroperception.services.runtime.data import kitti_scans



def _dense_sim_scan(scenario: str) -> tuple[np.ndarray, np.ndarray, float]:
    from aeroperception.services.runtime.rotations import quat_to_rotmat
    from aeroperception.services.sim.sensors.lidar import Lidar
    from aeroperception.services.sim.sensors.synthetic import orbit_truth
    from aeroperception.services.sim.world.scenario import load_scenario
    from aeroperception.services.sim.world.scene import Scene

    scn = load_scenario(scenario)
    lidar = Lidar(Scene(scn), scn.sensors.lidar.dense_150k(), seed=scn.seed)
    (x, y, z), _ = scn.start_pose()
    truth = orbit_truth(0, center_enu_m=(x + 6.0, y, z + 4.0), radius_m=6.0)
    scan = lidar.scan(truth)
    r_wb = quat_to_rotmat(truth.q_enu_flu)
    return scan.points_m, r_wb @ lidar.r_body_lidar, float((r_wb @ lidar.t_body_lidar_m)[2])


def _open3d_baseline(points: np.ndarray, r: np.ndarray, cfg: PipelineConfig, cm: RollingCostmap) -> None:
    """The LID-1 pipeline as the source specified it, with Open3D doing each PCL step; the costmap marking is shared."""
    import open3d as o3d

    pts = sanitize(points, cfg.min_range_m, cfg.max_range_m, cfg.max_points) @ r.T
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    pc = pc.voxel_down_sample(cfg.voxel_leaf_m)
    model, inliers = pc.segment_plane(cfg.ground_distance_threshold_m, 3, cfg.ground_max_iterations)
    a, b, c, d = model
    xyz = np.asarray(pc.points)
    h = (xyz @ np.array([a, b, c]) + d) * (1 if c >= 0 else -1)
    obst = xyz[(h >= cfg.min_obstacle_height_m) & (h <= cfg.max_obstacle_height_m)]
    cm.update((0.0, 0.0), obst[:, :2], xyz[:, :2])


def _stats(ms: list[float]) -> tuple[float, float]:
    a = np.asarray(ms)
    return float(np.median(a)), float(np.percentile(a, 99))


def _bench(name: str, points: np.ndarray, r: np.ndarray, above: float, n: int) -> list[tuple]:
    cfg = PipelineConfig()
    pipe = ObstaclePipeline(cfg)
    cm = RollingCostmap(CostmapConfig())
    cm.recenter(0.0, 0.0)
    stages: dict[str, list[float]] = {}
    total, base = [], []
    for i in range(n + 2):
        t0 = time.perf_counter()
        res = pipe.process(points, r, above)
        t1 = time.perf_counter()
        cm.update((0.0, 0.0), res.obstacles[:, :2], res.downsampled[:, :2], res.ground[:, :2])
        cm.inflated()
        t2 = time.perf_counter()
        if i >= 2:                                  # the first runs warm caches and allocators
            for k, v in res.timings_ms.items():
                stages.setdefault(k, []).append(v)
            stages.setdefault("costmap", []).append((t2 - t1) * 1e3)
            total.append((t2 - t0) * 1e3)
        t3 = time.perf_counter()
        _open3d_baseline(points, r, cfg, RollingCostmap(CostmapConfig()))
        if i >= 2:
            base.append((time.perf_counter() - t3) * 1e3)
    rows = [(f"{name}: {k}", *_stats(v), None) for k, v in stages.items()]
    b50, b99 = _stats(base)
    t50, t99 = _stats(total)
    rows.append((f"{name}: TOTAL scan -> costmap ({len(points)} pts)", t50, t99, t50 / b50))
    rows.append((f"{name}: baseline Open3D pipeline (as specified)", b50, b99, 1.0))
    return rows


def run(n: int = 20, scenario: str = "village") -> int:
    points, r, above = _dense_sim_scan(scenario)
    rows = _bench(f"sim {scenario}", points, r, above, n)
    kitti = kitti_scans()
    if kitti:
        raw = np.fromfile(kitti[0], np.float32).reshape(-1, 4)[:, :3].copy()
        rows += _bench(f"KITTI {kitti[0].stem}", raw, np.eye(3), 0.0, n)
    print(f"{'stage':<58} {'median ms':>10} {'p99 ms':>8} {'x baseline':>11}")
    for name, med, p99, ratio in rows:
        print(f"{name:<58} {med:>10.2f} {p99:>8.2f} {'' if ratio is None else f'{ratio:.2f}':>11}")
    print("target (requirement LID-4): scan -> costmap < 50 ms median")
    return 0
