"""Detection ground truth: detector-target 3D boxes projected into a camera.

Boxes are in the COCO/YOLO continuous pixel convention (the image spans [0, W] x [0, H], pixel i
covers [i, i + 1)), i.e. the pinhole projection (pixel centres at integers) shifted by +0.5, so
they compare directly with detector output. Visibility is checked by casting rays from the
camera to sample points inside the box: a sample counts as visible when it is in the image and
the first thing the ray hits is the target itself (or nothing before the sample).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..world.scenario import COCO_CLASSES
from .camera import Camera

NEAR_M = 0.1
_SAMPLES = np.array([[0, 0, 0]] + [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
                    + [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * 0.35


@dataclass(frozen=True)
class TruthBox2D:
    class_name: str
    class_id: int                               # COCO-80 index, as YOLO reports it
    bbox_xyxy_px: tuple[float, float, float, float]
    visible_fraction: float                     # 0..1 of the in-box samples seen
    distance_m: float                           # camera to box centre
    target_index: int                           # index into scenario.targets
    name: str


def project_targets(camera: Camera, truth_or_pose, min_visible_fraction: float = 0.1,
                    min_size_px: float = 2.0) -> list[TruthBox2D]:
    """2D truth boxes of the targets in front of `camera` at this pose, nearest first."""
    sc = camera.scene
    r_wc, origin = camera.world_pose(truth_or_pose)
    w, h = camera.width, camera.height
    out = []
    for box in sc.target_boxes:
        corners = box.corners_enu_m()
        uv, z = camera.project(truth_or_pose, corners)
        if np.any(z < NEAR_M):
            continue    # partly behind the camera: not a meaningful 2D box
        x0, y0 = np.clip(uv.min(axis=0) + 0.5, 0, [w, h])
        x1, y1 = np.clip(uv.max(axis=0) + 0.5, 0, [w, h])
        if x1 - x0 < min_size_px or y1 - y0 < min_size_px:
            continue
        c, s = np.cos(box.yaw_rad), np.sin(box.yaw_rad)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        pts = (_SAMPLES * box.size_m) @ rot.T + box.center_enu_m
        suv, _ = camera.project(truth_or_pose, pts)
        in_img = (suv[:, 0] >= -0.5) & (suv[:, 0] < w - 0.5) & (suv[:, 1] >= -0.5) & (suv[:, 1] < h - 0.5)
        t, plane = sc.cast(origin, pts - origin)        # t == 1 at the sample point
        seen = (np.take(sc.plane_entity, plane) == box.entity) | (t >= 1.0 - 1e-4)
        frac = float(np.mean(seen & in_img))
        if frac < min_visible_fraction:
            continue
        name = sc.entities[box.entity].name
        out.append(TruthBox2D(box.class_name, COCO_CLASSES.index(box.class_name),
                              (float(x0), float(y0), float(x1), float(y1)), frac,
                              float(np.linalg.norm(box.center_enu_m - origin)), box.target_index, name))
    return sorted(out, key=lambda b: b.distance_m)
