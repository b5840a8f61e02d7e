"""LiDAR obstacle pipeline (requirement LID-1) on synthetic clouds with known answers, on real KITTI
scans, and against the simulator's truth labels (LID-4 targets)."""
import math

import numpy as np
import pytest

from aeroperception.services.lidar.pipeline import (
    ObstaclePipeline, PipelineConfig, ScanError, classify, fit_ground, grid_clusters, sanitize, voxel_downsample,
)
from aeroperception.services.lidar import contract
from aeroperception.services.runtime.config import build
from aeroperception.services.runtime.rotations import quat_from_euler, quat_to_rotmat
from aeroperception.services.runtime.data import kitti_scans

RNG = np.random.default_rng(7)


def plane_points(n=20000, size=20.0, z=-3.0, tilt_deg=0.0, noise=0.01):
    """Ground under a sensor at the origin: z = -3 m, optionally rising along +x by tilt_deg."""
    xy = RNG.uniform(-size / 2, size / 2, (n, 2))
    zz = z + xy[:, 0] * math.tan(math.radians(tilt_deg)) + RNG.normal(0, noise, n)
    return np.column_stack([xy, zz]).astype(np.float32)


def box_points(center, size, n=3000):
    c, s = np.asarray(center, float), np.asarray(size, float)
    return (c + RNG.uniform(-0.5, 0.5, (n, 3)) * s).astype(np.float32)


def test_voxel_grid_keeps_one_real_point_per_occupied_voxel():
    pts = np.array([[0.01, 0.01, 0.01], [0.02, 0.03, 0.04], [0.06, 0.0, 0.0], [1.0, 1.0, 1.0]], np.float32)
    out = voxel_downsample(pts, 0.05)
    assert len(out) == 3                                   # the first two share a 5 cm voxel
    assert all(any(np.array_equal(o, p) for p in pts) for o in out)
    big = RNG.uniform(-20, 20, (150_000, 3)).astype(np.float32)
    keys = np.floor(big / 0.05).astype(np.int64)
    assert len(voxel_downsample(big, 0.05)) == len(np.unique(keys, axis=0))


def test_flat_ground_and_boxes_are_separated():
    ground = plane_points()
    boxes = np.vstack([box_points((5, 0, -2.0), (1, 1, 2)), box_points((-4, 3, -2.5), (0.5, 0.5, 1))])
    pipe = ObstaclePipeline(build(PipelineConfig, contract.PARAMS))
    res = pipe.process(np.vstack([ground, boxes]), np.eye(3))
    assert res.plane.found and res.plane.tilt_deg < 1.0
    assert res.plane.d == pytest.approx(3.0, abs=0.02)     # plane z = -3 m: n.p + d = 0 -> d = 3
    g, o = classify(np.vstack([ground, boxes]), res.plane, pipe.cfg)
    assert g[: len(ground)].mean() > 0.99 and not g[len(ground):][boxes[:, 2] > -2.85].any()
    in_band = boxes[:, 2] >= -2.9                          # >= 0.1 m above the ground
    assert o[len(ground):][in_band].mean() > 0.99 and o[: len(ground)].mean() < 0.005


def test_tilted_ground_is_found_within_the_imu_seeded_cone():
    ground = plane_points(tilt_deg=8.0)
    res = ObstaclePipeline(build(PipelineConfig, contract.PARAMS)).process(ground, np.eye(3))
    assert res.plane.found and res.plane.tilt_deg == pytest.approx(8.0, abs=0.5)
    # A wall-like plane (60 deg) is never accepted as ground.
    wall = plane_points(tilt_deg=60.0)
    assert not fit_ground(wall, build(PipelineConfig, contract.PARAMS), np.random.default_rng(0)).found


def test_levelling_with_the_vehicle_attitude_undoes_a_tilted_sensor():
    ground = plane_points(z=-4.0)
    r = quat_to_rotmat(quat_from_euler(math.radians(12), math.radians(-7), 0.3))
    sensor_pts = ground @ r            # what a sensor rolled 12 deg / pitched -7 deg measures (R^T p)
    res = ObstaclePipeline(build(PipelineConfig, contract.PARAMS)).process(sensor_pts, r)
    assert res.plane.found and res.plane.tilt_deg < 1.0 and res.plane.d == pytest.approx(4.0, abs=0.03)


def test_canopy_below_the_vehicle_is_an_obstacle_and_above_it_is_not():
    """Sensor 6 m above the ground. A canopy slab at 3 m above ground (below us) is an obstacle;
    one at 9 m (3 m above us) is overhead."""
    ground = plane_points(z=-6.0)
    low = box_points((5, 0, -3.0), (4, 4, 0.2))
    high = box_points((-5, 0, 3.0), (4, 4, 0.2))
    pts = np.vstack([ground, low, high])
    pipe = ObstaclePipeline(build(PipelineConfig, contract.PARAMS))
    res = pipe.process(pts, np.eye(3))
    _, o = classify(pts, res.plane, pipe.cfg)
    n0, n1 = len(ground), len(ground) + len(low)
    assert o[n0:n1].all() and not o[n1:].any()


def test_empty_nan_and_absurd_scans():
    pipe = ObstaclePipeline(build(PipelineConfig, contract.PARAMS))
    res = pipe.process(np.zeros((0, 3), np.float32), np.eye(3))
    assert res.counts["obstacles"] == 0 and not res.plane.found
    garbage = np.vstack([plane_points(2000), np.full((500, 3), np.nan, np.float32),
                         np.full((500, 3), np.inf, np.float32)])
    res = pipe.process(garbage, np.eye(3))
    assert res.counts["valid"] == 2000 and res.plane.found
    with pytest.raises(ScanError, match="max_points"):
        sanitize(np.zeros((600_000, 3), np.float32), 0.5, 50, 500_000)
    with pytest.raises(ScanError, match=r"\(N, 3\)"):
        sanitize(np.zeros((10, 4), np.float32), 0.5, 50, 500_000)


def test_scan_with_no_ground_keeps_the_previous_plane_and_says_so():
    pipe = ObstaclePipeline(build(PipelineConfig, contract.PARAMS))
    first = pipe.process(plane_points(), np.eye(3))
    assert first.plane.found
    # Only a ceiling and a pole are in view (e.g. flying under a canopy): a level plane, but
    # above the sensor, so it is not ground.
    ceiling = plane_points(z=+3.0)
    pole = box_points((3, 0, 0), (0.1, 0.1, 5), 500)
    res = pipe.process(np.vstack([ceiling, pole]), np.eye(3))
    assert not res.plane.found and res.plane.d == pytest.approx(first.plane.d)


def test_grid_clusters_separate_objects():
    pts = np.vstack([box_points((0, 0, 0), (1, 1, 1), 500), box_points((5, 5, 0), (1, 1, 1), 300),
                     box_points((20, 0, 0), (0.05, 0.05, 0.05), 3)])
    clusters = grid_clusters(pts, 0.2, 10, 5000)
    assert sorted(len(c) for c in clusters) == [300, 500]


@pytest.mark.skipif(not kitti_scans(), reason="../shared/data/kitti not present")
@pytest.mark.parametrize("path", kitti_scans(), ids=lambda p: p.stem)
def test_real_kitti_scan_road_is_ground_and_cars_walls_are_obstacles(path):
    raw = np.fromfile(path, np.float32).reshape(-1, 4)[:, :3].copy()
    pipe = ObstaclePipeline(build(PipelineConfig, contract.PARAMS))
    res = pipe.process(raw, np.eye(3))
    assert res.plane.found and res.plane.tilt_deg < 3.0
    assert res.plane.d == pytest.approx(1.73, abs=0.15)    # HDL-64E ~1.73 m above the road
    pts = sanitize(raw, 0.5, 50, 10**6)
    g, o = classify(pts, res.plane, pipe.cfg)
    # Spot checks by region: the road just ahead of the car is ground; returns more than 0.5 m
    # above the road within 20 m (parked cars, walls, trees) are obstacles.
    road = (np.abs(pts[:, 1]) < 2.0) & (pts[:, 0] > 4) & (pts[:, 0] < 12) & (pts[:, 2] < -1.5)
    assert road.sum() > 500 and g[road].mean() > 0.9
    h = res.plane.height(pts)
    tall = (h > 0.5) & (h < 2.0) & (np.hypot(pts[:, 0], pts[:, 1]) < 20)
    assert tall.sum() > 1000 and o[tall].all()


@pytest.mark.parametrize("scenario, min_f1", [("open_field", 0.95), ("village", 0.95), ("slope_forest", 0.90)])
def test_seed_004_targets_against_simulator_truth(scenario, min_f1):
    from aeroperception.tools.eval.lidar import evaluate, sim_scans

    m = evaluate(sim_scans(scenario, 6))
    assert m["ground_f1"] >= min_f1
    assert m["obstacle_fp_rate"] < 0.05
    assert m["obstacle_fn_rate"] < 0.02
    assert m["obstacle_points"] > 500                      # the scans really contain obstacles
