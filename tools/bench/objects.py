"""`aero bench objects`: what one detection frame costs the objects service on this machine
(placement by stereo and the ground ray, association, track upkeep: `ObjectsPipeline.process`, CPU
time), for 1 to 20 boxes a frame. The frame is a village render from the search flight's height,
its boxes the scenario's targets in view (repeated for larger counts). The baseline, measured
interleaved in the same run on the same pair, is one full-frame block-matched disparity map
(cv2.StereoBM, the same block and search range): what a per-pixel depth the service avoids would
cost before any box is placed.
"""
from __future__ import annotations

import time

import cv2
import numpy as np

WARMUP = 3


def _scene(scenario: str):
    """(left, right) grayscale pair, camera infos, the vehicle's pose and the boxes of the targets
    in view (u, v, w, h, class) from 7 m up at the street's start, looking along it."""
    from aeroperception.services.objects.projection import Camera, PoseSample
    from aeroperception.services.sim.main import camera_info_msg
    from aeroperception.services.sim.sensors.rig import build_sensors
    from aeroperception.services.sim.sensors.synthetic import hover_truth
    from aeroperception.services.sim.world.scenario import load_scenario
    from aeroperception.services.sim.world.scene import get_scene

    scn = load_scenario(scenario)
    rig = build_sensors(scn).stereo
    (x, y, _), _ = scn.start_pose()
    truth = hover_truth((x, y - 2.0, 7.0))
    left, right = rig.render(truth)
    gray = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in (left, right)]
    infos = [camera_info_msg(i, 0) for i in rig.infos()]
    cam = Camera.from_infos(*infos)
    pose = PoseSample(0, np.asarray(truth.position_enu_m, float), np.asarray(truth.q_enu_flu, float))
    r_wc, origin = cam.world_pose(pose)
    boxes = []
    for tb in get_scene(scn).target_boxes:
        length, width, height = tb.size_m
        c, s = np.cos(tb.yaw_rad), np.sin(tb.yaw_rad)
        corners = np.array([tb.center_enu_m + [c * dx - s * dy, s * dx + c * dy, dz] for dx in (-length / 2, length / 2)
                            for dy in (-width / 2, width / 2) for dz in (-height / 2, height / 2)])
        pc = (corners - origin) @ r_wc
        if (pc[:, 2] <= 0.5).any():
            continue
        u = cam.cx + 0.5 + cam.fx * pc[:, 0] / pc[:, 2]
        v = cam.cy + 0.5 + cam.fy * pc[:, 1] / pc[:, 2]
        if u.min() > 0 and v.min() > 0 and u.max() < left.shape[1] and v.max() < left.shape[0]:
            boxes.append(((u.min() + u.max()) / 2, (v.min() + v.max()) / 2, u.max() - u.min(), v.max() - v.min(),
                          tb.class_name))
    return gray, infos, truth, boxes


def run(n: int = 50, scenario: str = "village", counts: tuple[int, ...] = (1, 5, 10, 20)) -> int:
    from aeroperception.schemas import (
        Detection2D, Detection2DArray, Header, Image, Quaternion, Vector3, VehicleState,
    )
    from aeroperception.services.objects import contract
    from aeroperception.services.objects.logic import ObjectsConfig, ObjectsPipeline
    from aeroperception.services.objects.projection import box_disparity
    from aeroperception.services.runtime.config import build

    (left, right), infos, truth, boxes = _scene(scenario)
    if not boxes:
        print(f"aero bench objects: no target of {scenario} in view")
        return 2
    classes = {"person": 0, "bicycle": 1, "car": 2, "truck": 7}
    print(f"{n} frames per row ({WARMUP} warm-up), {left.shape[1]}x{left.shape[0]} {scenario} stereo pair from 7 m, "
          f"{len(boxes)} targets in view; CPU ms per detection frame")
    print(f"{'boxes':>5} | {'objects p50':>11} {'p99':>6} | {'full-frame disparity p50':>24} {'p99':>6} | {'x baseline':>10}")
    max_range = next(p.default for p in contract.PARAMS if p.name == "stereo_max_range_m")
    cam = ObjectsPipeline(build(ObjectsConfig, contract.PARAMS))
    cam.on_info("left", infos[0])
    cam.on_info("right", infos[1])
    max_disp = int(np.ceil(cam.camera.fx * cam.camera.baseline_m / max_range))     # as the service searches
    for count in counts:
        chosen = [boxes[i % len(boxes)] for i in range(count)]
        pl = ObjectsPipeline(build(ObjectsConfig, contract.PARAMS))
        pl.on_info("left", infos[0])
        pl.on_info("right", infos[1])
        ours, base = [], []
        for k in range(n + WARMUP):
            stamp = 1_000_000_000 + k * 100_000_000
            h = Header(stamp_ns=stamp, frame_id="camera_left_optical")
            for t in (stamp - 20_000_000, stamp, stamp + 20_000_000):
                pl.on_state(VehicleState(header=Header(stamp_ns=t), position_m=Vector3.from_array(truth.position_enu_m),
                                         orientation=Quaternion.from_array(truth.q_enu_flu)))
            pl.on_image("left", Image.from_numpy(left, "mono8", h))
            pl.on_image("right", Image.from_numpy(right, "mono8", h))
            dets = Detection2DArray(header=h, image_width=left.shape[1], image_height=left.shape[0], detections=[
                Detection2D(center_x_px=u, center_y_px=v, size_x_px=w, size_y_px=hh, class_id=classes.get(c, 0),
                            class_name=c, score=0.9) for u, v, w, hh, c in chosen])
            r = pl.process(dets)
            t0 = time.thread_time()
            box_disparity(left, right, (0.0, 0.0, float(left.shape[1]), float(left.shape[0])), max_disp, 1.0)
            t1 = time.thread_time()
            if k >= WARMUP:
                ours.append(r.cpu_ms)
                base.append((t1 - t0) * 1e3)
        o50, o99, b50, b99 = (float(np.percentile(a, q)) for a, q in ((ours, 50), (ours, 99), (base, 50), (base, 99)))
        print(f"{count:>5} | {o50:>11.2f} {o99:>6.2f} | {b50:>24.2f} {b99:>6.2f} | {o50 / b50:>10.2f}")
    print("x baseline: objects p50 / full-frame disparity p50, same pair, interleaved (the goal: < 5 ms a frame)")
    return 0
