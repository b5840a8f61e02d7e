"""`aero bench sim`: how fast the simulated sensors render on this machine.

Renders every sensor of a scenario's rig over N poses along an orbit and prints, per sensor, the
median / p99 wall time, the median and p99 CPU time (the cost on an idle core: wall time also counts
time the OS gave to other processes), a camera's or the LiDAR's CPU as a ratio to casting every ray
with Open3D (same run),
the highest rate it could sustain alone and its rated rate. The cameras are rasterised and the LiDAR's sweep cast per triangle (numba); the
reference rows cast every ray with Open3D (`exact=True`), and `x ref` is a row's CPU over its
reference in the same run. The header says what the first render cost (compiling the camera
kernels, or loading them from numba's cache).
The last line sums rate x CPU cost over the default rig: the share of one core the sensors need.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class _Row:
    name: str
    rated_hz: float
    wall_ms: np.ndarray
    cpu_ms: np.ndarray
    in_rig: bool = True
    ref: "_Row | None" = None    # the same render casting every ray with Open3D

    @property
    def max_hz(self) -> float:
        return 1000.0 / float(np.median(self.wall_ms))


def _time(fn: Callable[[int], object], n: int) -> tuple[np.ndarray, np.ndarray]:
    fn(0)   # warm-up (first-touch allocations, caches)
    wall, cpu = [], []
    for i in range(n):
        w0, c0 = time.perf_counter(), time.process_time()
        fn(i)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return np.array(wall) * 1e3, np.array(cpu) * 1e3


def run(n_frames: int = 50, scenario: str = "village") -> int:
    from aeroperception.services.sim.sensors.camera import StereoCamera
    from aeroperception.services.sim.sensors.imu import ImuModel
    from aeroperception.services.sim.sensors.lidar import Lidar
    from aeroperception.services.sim.sensors.synthetic import orbit_truth
    from aeroperception.services.sim.sensors.truth_boxes import project_targets
    from aeroperception.services.sim.world.scenario import load_scenario
    from aeroperception.services.sim.world.scene import Scene, texture_bank

    scn = load_scenario(scenario)
    rig = scn.sensors
    t0 = time.perf_counter()
    texture_bank()
    t1 = time.perf_counter()
    scene = Scene(scn)
    t2 = time.perf_counter()
    (x, y, z), _ = scn.start_pose()
    # Orbit ahead of the start point so views sweep across the scene.
    poses = [orbit_truth(int(i * 50e6), center_enu_m=(x + 15.0, y, z + 3.0), radius_m=8.0, period_s=10.0)
             for i in range(n_frames)]
    cam = StereoCamera(scene, rig.camera)
    lidar = Lidar(scene, rig.lidar, seed=scn.seed)
    dense = Lidar(scene, rig.lidar.dense_150k(), seed=scn.seed)
    imu = ImuModel(rig.imu, seed=scn.seed)
    imu_truths = [orbit_truth(int(i * 5e6)) for i in range(max(n_frames, 200))]

    t3 = time.perf_counter()
    cam.render(poses[0])
    first_ms = 1e3 * (time.perf_counter() - t3)

    c = rig.camera
    res = f"{c.width}x{c.height} {c.encoding}"
    n_ref = max(5, n_frames // 5)
    ref_left = _Row("  (reference: left, a ray per pixel)", c.rate_hz,
                    *_time(lambda i: cam.left.render(poses[i], exact=True), n_ref), in_rig=False)
    ref_pair = None
    rows = [_Row(f"camera left  {res}", c.rate_hz, *_time(lambda i: cam.left.render(poses[i]), n_frames),
                 in_rig=False, ref=ref_left)]
    if cam.right is not None:
        rows.append(_Row(f"camera right {res}", c.rate_hz,
                         *_time(lambda i: cam.right.render(poses[i]), n_frames), in_rig=False, ref=ref_left))
        ref_pair = _Row("  (reference: stereo pair, a ray per pixel)", c.rate_hz,
                        *_time(lambda i: cam.render(poses[i], exact=True), n_ref), in_rig=False)
        rows.append(_Row("stereo pair (left+right)", c.rate_hz, *_time(lambda i: cam.render(poses[i]), n_frames),
                         ref=ref_pair))
    else:
        rows[0].in_rig = True
    ref_lidar = _Row("  (reference: lidar, Open3D every ray)", rig.lidar.rate_hz,
                     *_time(lambda i: lidar.scan(poses[i], exact=True), n_ref), in_rig=False)
    rows += [
        _Row(f"lidar {rig.lidar.beams}x{rig.lidar.azimuth_steps} ({lidar.num_rays} rays)", rig.lidar.rate_hz,
             *_time(lambda i: lidar.scan(poses[i]), n_frames), ref=ref_lidar),
        _Row(f"lidar 150k mode ({dense.num_rays} rays)", rig.lidar.rate_hz,
             *_time(lambda i: dense.scan(poses[i]), n_frames), in_rig=False),
        _Row("imu sample", rig.imu.rate_hz, *_time(lambda i: imu.sample(imu_truths[i]), len(imu_truths))),
        _Row("truth boxes (left camera)", c.rate_hz, *_time(lambda i: project_targets(cam.left, poses[i]), n_frames)),
    ]
    rows += [r for r in (ref_pair, ref_left, ref_lidar) if r is not None]

    print(f"sim sensor benchmark: scenario {scenario}, {n_frames} frames, "
          f"textures {1e3 * (t1 - t0):.0f} ms, scene build {1e3 * (t2 - t1):.0f} ms "
          f"({len(scene.triangles)} triangles, {scene.num_planes} planes), first stereo render {first_ms:.0f} ms "
          f"(camera kernels compiled or loaded from numba's cache)")
    head = (f"{'sensor':44s} {'wall med':>9s} {'wall p99':>9s} {'cpu med':>9s} {'cpu p99':>9s} {'x ref':>6s} "
            f"{'max Hz':>8s} {'rated':>7s}  ok")
    print(head)
    print("-" * len(head))
    load = 0.0
    for r in rows:
        cpu = float(np.median(r.cpu_ms))
        ok = "yes" if r.max_hz >= r.rated_hz else "NO"
        ratio = f"{cpu / float(np.median(r.ref.cpu_ms)):6.2f}" if r.ref is not None else " " * 6
        print(f"{r.name:44s} {np.median(r.wall_ms):8.2f}ms {np.percentile(r.wall_ms, 99):8.2f}ms "
              f"{cpu:8.2f}ms {np.percentile(r.cpu_ms, 99):8.2f}ms {ratio} {r.max_hz:8.1f} {r.rated_hz:6.0f}Hz  {ok}")
        if r.in_rig:
            load += r.rated_hz * cpu / 1000.0
    print(f"default rig at rated rates (stereo + lidar + imu + truth boxes): {100 * load:.0f}% of one core")
    print("cpu = this process's CPU time per frame (what rendering costs the machine, whatever else runs); "
          f"x ref = CPU over casting every ray with Open3D, same run; load average {os.getloadavg()[0]:.1f} "
          f"on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    raise SystemExit(run())
