"""Detector images with truth boxes, rendered offline by the simulator's own camera model.

One home for what both the training script (tools/training/train_detector.py) and `aero eval detector`
(offline mode) render: the same renderer and truth-box projection the running sim publishes on
sensors/camera/left/image and sim/truth/boxes, at camera poses a drone takes (on the ground up
to 25 m, looking at the targets from any bearing, with body pitch/roll).

Training uses procedurally generated scenarios (random layouts, materials, sun) plus the village
with training-only seeds; held-out sets are the village with other seeds and the shipped
scenarios that training never sees (open_field, slope_forest). Deterministic: every set is a
function of its seeds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterator

import numpy as np

# The classes the simulator renders as detector targets (scenario.py DEFAULT_TARGET_SIZE_M /
# scene.py _target_shape), in the bundled model's class-id order.
SIM_CLASSES: tuple[str, ...] = ("person", "bicycle", "car", "truck")

# Scenario seeds of the village used for training; held-out village sets use seeds >= 1000.
TRAIN_VILLAGE_SEEDS = (2, 11, 12, 13)
HELDOUT_VILLAGE_SEEDS = (1001, 1002)
HELDOUT_SCENARIOS = ("open_field", "slope_forest")   # never rendered for training


@dataclass
class Sample:
    image: np.ndarray                  # (H, W, 3) uint8 RGB as published on sensors/camera/left/image
    boxes: np.ndarray                  # (M, 4) float xyxy px, COCO continuous convention
    classes: list[str]                 # class name per box
    visible: np.ndarray                # (M,) visible fraction per box (sim/truth/boxes score)
    scenario: str = ""


# ---------------------------------------------------------------- procedural scenarios

_GROUND = ("grass", "dirt", "forest_floor", "asphalt", "concrete")
_BUILDING = ("facade", "brick", "concrete")
_CLASS_P = {"person": 0.35, "bicycle": 0.25, "car": 0.22, "truck": 0.18}
# Not "metal": in this world grey metal boxes are bicycles (and thin cylinders are poles).
_TARGET_MATERIALS = ("clothing", "car_paint", "truck_paint", "paint", "brick", "crate")


def _free(xy, footprints, margin: float) -> bool:
    return all(abs(xy[0] - x) > hx + margin or abs(xy[1] - y) > hy + margin for x, y, hx, hy in footprints)


def random_scenario(seed: int):
    """A random world: buildings, trees, poles, crates, walls and 6-16 targets of the sim's
    classes (default materials mostly, 10 % another material so shape is learnt too)."""
    from aeroperception.services.sim.world.scenario import parse_scenario

    rng = np.random.default_rng(seed)
    objects, footprints = [], []
    for _ in range(rng.integers(2, 12)):
        sx, sy, sz = rng.uniform(8, 16), rng.uniform(8, 14), rng.uniform(4, 12)
        xy = rng.uniform(-60, 60, 2)
        if not _free(xy, footprints, 2.0):
            continue
        footprints.append((xy[0], xy[1], sx / 2 * 1.42, sy / 2 * 1.42))
        objects.append({"type": "building", "position_m": xy.tolist(), "size_m": [sx, sy, sz],
                        "yaw_deg": float(rng.choice([0.0, rng.uniform(-45, 45)])),
                        "material": str(rng.choice(_BUILDING))})
    for _ in range(rng.integers(0, 16)):
        xy = rng.uniform(-70, 70, 2)
        if _free(xy, footprints, 3.0):
            h = rng.uniform(5, 14)
            objects.append({"type": "tree", "position_m": xy.tolist(), "height_m": h,
                            "crown_radius_m": rng.uniform(1.2, 3.0), "crown_base_m": h * rng.uniform(0.25, 0.5)})
    for _ in range(rng.integers(0, 8)):
        xy = rng.uniform(-60, 60, 2)
        if _free(xy, footprints, 1.0):
            objects.append({"type": "pole", "position_m": xy.tolist(), "height_m": rng.uniform(2, 8),
                            "radius_m": rng.uniform(0.08, 0.2)})
    for _ in range(rng.integers(0, 6)):
        xy = rng.uniform(-60, 60, 2)
        if _free(xy, footprints, 1.5):
            size = rng.uniform([0.6, 0.6, 0.5], [2.5, 2.0, 2.0])
            rock = min(size[:2]) >= 1.2 and rng.random() < 0.5     # concrete rocks, never bicycle-thin
            objects.append({"type": "box", "position_m": xy.tolist(), "size_m": size.tolist(),
                            "yaw_deg": rng.uniform(-90, 90), "material": "concrete" if rock else "crate"})
    for _ in range(rng.integers(0, 3)):
        xy = rng.uniform(-60, 60, 2)
        if _free(xy, footprints, 1.0):
            objects.append({"type": "wall", "position_m": xy.tolist(),
                            "size_m": [rng.uniform(4, 12), 0.3, rng.uniform(1, 2.5)], "yaw_deg": rng.uniform(-90, 90)})
    targets, placed = [], []
    names, p = list(_CLASS_P), np.array(list(_CLASS_P.values()))
    for _ in range(rng.integers(6, 17)):
        for _try in range(20):
            xy = rng.uniform(-45, 45, 2)
            if _free(xy, footprints, 2.0) and all(np.hypot(*(xy - q)) > 4.5 for q in placed):
                break
        else:
            continue
        placed.append(xy)
        t = {"class": str(rng.choice(names, p=p)), "position_m": xy.tolist(), "yaw_deg": rng.uniform(-180, 180)}
        if rng.random() < 0.1:
            t["material"] = str(rng.choice(_TARGET_MATERIALS))
        targets.append(t)
    doc = {
        "name": f"procedural_{seed}", "seed": int(seed),
        "ground": {"size_m": [300, 300], "material": str(rng.choice(_GROUND)),
                   "slope_deg": float(rng.choice([0.0, rng.uniform(0, 10)])), "slope_azimuth_deg": rng.uniform(0, 360)},
        "lighting": {"sun_azimuth_deg": rng.uniform(0, 360), "sun_elevation_deg": rng.uniform(20, 80),
                     "ambient": rng.uniform(0.25, 0.6),
                     "sky_rgb": np.clip(np.array([175, 205, 235]) + rng.normal(0, 20, 3), 0, 255).tolist()},
        "objects": objects, "targets": targets,
        "sensors": {"camera": {"stereo": False, "pitch_down_deg": 10}, "lidar": {"enabled": False}},
    }
    return parse_scenario(doc, f"procedural_{seed}")


def _scenario_doc(name: str, seed: int, rng, ground: str, slope: float, objects: list, targets: list) -> dict:
    return {
        "name": name, "seed": int(seed),
        "ground": {"size_m": [300, 300], "material": ground, "slope_deg": slope, "slope_azimuth_deg": rng.uniform(0, 360)},
        "lighting": {"sun_azimuth_deg": rng.uniform(0, 360), "sun_elevation_deg": rng.uniform(20, 80),
                     "ambient": rng.uniform(0.25, 0.6),
                     "sky_rgb": np.clip(np.array([175, 205, 235]) + rng.normal(0, 20, 3), 0, 255).tolist()},
        "objects": objects, "targets": targets,
        "sensors": {"camera": {"stereo": False, "pitch_down_deg": 10}, "lidar": {"enabled": False}},
    }


def random_street_scenario(seed: int):
    """A village-like street: two rows of buildings (facade/brick/concrete, some truck-sized
    sheds and concrete blocks as look-alike negatives), street lights, walls, and targets parked
    along the street and in front of the facades, trucks twice as often as in random_scenario."""
    from aeroperception.services.sim.world.scenario import parse_scenario

    rng = np.random.default_rng(seed)
    objects, footprints = [], []
    for side in (-1, 1):
        x = rng.uniform(-40, -20)
        while x < 110:
            sx, sy, sz = rng.uniform(8, 18), rng.uniform(8, 12), rng.uniform(5, 12)
            y = side * (rng.uniform(13, 18) + sy / 2 - 5)
            objects.append({"type": "building", "position_m": [x + sx / 2, y], "size_m": [sx, sy, sz],
                            "material": str(rng.choice(_BUILDING))})
            footprints.append((x + sx / 2, y, sx / 2, sy / 2))
            x += sx + rng.uniform(1, 8)
        for px in np.arange(rng.uniform(-10, 10), 100, rng.uniform(12, 25)):
            objects.append({"type": "pole", "position_m": [float(px), side * 7.0], "height_m": 6.0, "radius_m": 0.12})
    for _ in range(rng.integers(1, 5)):                  # truck-sized look-alikes: sheds, blocks
        xy = np.array([rng.uniform(-20, 100), rng.choice([-1, 1]) * rng.uniform(7.5, 10)])
        size = [rng.uniform(3, 9), rng.uniform(2, 4), rng.uniform(1.5, 3.5)]
        if _free(xy, footprints, 1.0):
            footprints.append((xy[0], xy[1], size[0] / 2 * 1.42, size[0] / 2 * 1.42))
            objects.append({"type": "box", "position_m": xy.tolist(), "size_m": size, "yaw_deg": rng.uniform(-15, 15),
                            "material": str(rng.choice(["concrete", "facade", "brick", "crate"]))})
    for _ in range(rng.integers(0, 3)):
        xy = np.array([rng.uniform(-20, 100), rng.choice([-1, 1]) * rng.uniform(7.5, 9)])
        if _free(xy, footprints, 1.0):
            objects.append({"type": "wall", "position_m": xy.tolist(), "size_m": [rng.uniform(4, 12), 0.3, rng.uniform(1, 2.5)]})
    for _ in range(rng.integers(0, 5)):
        xy = np.array([rng.uniform(-20, 100), rng.choice([-1, 1]) * rng.uniform(7.5, 9)])
        if _free(xy, footprints, 2.0):
            h = rng.uniform(5, 9)
            objects.append({"type": "tree", "position_m": xy.tolist(), "height_m": h, "crown_radius_m": rng.uniform(1.2, 2.5),
                            "crown_base_m": h * rng.uniform(0.3, 0.5)})
    targets, placed = [], []
    p = {"person": 0.35, "bicycle": 0.2, "car": 0.2, "truck": 0.25}
    for _ in range(rng.integers(8, 17)):
        for _try in range(20):
            xy = np.array([rng.uniform(-15, 95), rng.uniform(-8, 8)])
            if _free(xy, footprints, 1.5) and all(np.hypot(*(xy - q)) > 4.5 for q in placed):
                break
        else:
            continue
        placed.append(xy)
        cls = str(rng.choice(list(p), p=list(p.values())))
        yaw = float(rng.choice([0.0, 180.0]) + rng.normal(0, 8)) if cls in ("car", "truck") else rng.uniform(-180, 180)
        targets.append({"class": cls, "position_m": xy.tolist(), "yaw_deg": yaw})
    doc = _scenario_doc(f"street_{seed}", seed, rng, str(rng.choice(["asphalt", "asphalt", "concrete", "dirt"])),
                        0.0, objects, targets)
    return parse_scenario(doc, f"street_{seed}")


def random_forest_scenario(seed: int):
    """A sloped forest with rocks and poles (slope_forest-like, never slope_forest itself): tree
    crowns and rocks as hard negatives; few targets, mostly people."""
    from aeroperception.services.sim.world.scenario import parse_scenario

    rng = np.random.default_rng(seed)
    objects = []
    for _ in range(rng.integers(25, 60)):
        h = rng.uniform(6, 16)
        objects.append({"type": "tree", "position_m": rng.uniform(-60, 60, 2).tolist(), "height_m": h,
                        "trunk_radius_m": rng.uniform(0.15, 0.35), "crown_radius_m": rng.uniform(1.4, 3.0),
                        "crown_base_m": h * rng.uniform(0.2, 0.45)})
    for _ in range(rng.integers(2, 10)):
        objects.append({"type": "box", "position_m": rng.uniform(-40, 40, 2).tolist(),
                        "size_m": rng.uniform([0.8, 0.8, 0.5], [4.0, 2.5, 2.0]).tolist(), "yaw_deg": rng.uniform(-90, 90),
                        "material": str(rng.choice(["concrete", "concrete", "crate"]))})
    for _ in range(rng.integers(0, 6)):
        objects.append({"type": "pole", "position_m": rng.uniform(-40, 40, 2).tolist(), "height_m": rng.uniform(2, 6),
                        "radius_m": rng.uniform(0.08, 0.2)})
    p = {"person": 0.6, "bicycle": 0.15, "car": 0.15, "truck": 0.1}
    targets = [{"class": str(rng.choice(list(p), p=list(p.values()))), "position_m": rng.uniform(-35, 35, 2).tolist(),
                "yaw_deg": rng.uniform(-180, 180)} for _ in range(rng.integers(3, 8))]
    doc = _scenario_doc(f"forest_{seed}", seed, rng, str(rng.choice(["forest_floor", "grass", "dirt"])),
                        rng.uniform(0, 12), objects, targets)
    return parse_scenario(doc, f"forest_{seed}")


def reseeded(name: str, seed: int):
    """A shipped scenario with another seed (texture offsets; the layout stays)."""
    from aeroperception.services.sim.world.scenario import load_scenario

    scn = load_scenario(name)
    return replace(scn, seed=seed, name=f"{scn.name}@{seed}")


# ---------------------------------------------------------------- camera poses

def _inside_box(scn, xyz, margin: float) -> bool:
    from aeroperception.services.sim.world.scenario import BoxObject

    boxes = [(o.position_m, o.size_m, o.yaw_deg, o.elevation_m) for o in scn.objects if isinstance(o, BoxObject)]
    boxes += [(t.position_m, t.size, t.yaw_deg, 0.0) for t in scn.targets]
    for (x, y), (l, w, h), yaw, elev in boxes:
        c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        dx, dy = xyz[0] - x, xyz[1] - y
        u, v = c * dx + s * dy, -s * dx + c * dy
        z = xyz[2] - scn.ground_height_m(x, y) - elev
        if abs(u) < l / 2 + margin and abs(v) < w / 2 + margin and -margin < z < h + margin:
            return True
    return False


def sample_poses(scn, scene, rng: np.random.Generator, n: int, class_weight: dict[str, float] | None = None,
                 negatives: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """`n` (position ENU, q_enu_flu) poses looking at the scenario's targets from 2-40 m, at
    0.1-25 m above the ground (a third near the ground, as a landed vehicle sees), heading
    +-25 deg off the target, pitched so it is roughly in view, with roll. class_weight: how often
    each class is the aimed-at target (default all 1); negatives: the fraction of poses aimed at a
    non-target object (buildings, walls, rocks, trees: look-alike negatives). The defaults draw
    exactly the random numbers they always did (the held-out sets stay the same images)."""
    from aeroperception.services.sim.sensors.frames import rot_to_quat, rpy_to_rot

    mount = math.radians(scn.sensors.camera.pitch_down_deg)
    anchors = [t.position_m for t in scn.targets] or [scn.start.position_m]
    others = [o.position_m for o in scn.objects]
    w = None
    if class_weight and scn.targets:
        w = np.array([class_weight.get(t.class_name, 1.0) for t in scn.targets], float)
        w /= w.sum()
    out: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(50 * n):
        if len(out) == n:
            break
        if negatives and others and rng.random() < negatives:
            ax, ay = others[rng.integers(len(others))]
        elif rng.random() < 0.85:
            ax, ay = anchors[rng.choice(len(anchors), p=w) if w is not None else rng.integers(len(anchors))]
        else:
            ax, ay = rng.uniform(-50, 50, 2)
        d, bearing = rng.uniform(2.0, 40.0), rng.uniform(-math.pi, math.pi)
        x, y = ax + d * math.cos(bearing), ay + d * math.sin(bearing)
        agl = rng.uniform(0.1, 1.0) if rng.random() < 0.3 else math.exp(rng.uniform(0.0, math.log(25.0)))
        z = scn.ground_height_m(x, y) + agl
        pos = np.array([x, y, z])
        if _inside_box(scn, pos, 0.6) or scene.obstacle_distance_m(pos[None])[0] < 0.5:
            continue
        yaw = math.atan2(ay - y, ax - x) + math.radians(rng.normal(0, 25))
        look_down = math.atan2(z - scn.ground_height_m(ax, ay) - 0.8, d)
        pitch = float(np.clip(look_down - mount + math.radians(rng.normal(0, 8)), math.radians(-15), math.radians(60)))
        roll = math.radians(rng.normal(0, 5))
        out.append((pos, rot_to_quat(rpy_to_rot(roll, pitch, yaw))))
    return out


# ---------------------------------------------------------------- rendering

def render_samples(scn, n: int, pose_seed: int, **pose_kw) -> Iterator[Sample]:
    """`n` left-camera images of `scn` with their truth boxes (what sim/truth/boxes carries);
    pose_kw go to sample_poses."""
    from aeroperception.services.sim.sensors.camera import StereoCamera
    from aeroperception.services.sim.sensors.truth_boxes import project_targets
    from aeroperception.services.sim.world.scene import Scene

    scene = Scene(scn)
    cam = StereoCamera(scene, replace(scn.sensors.camera, stereo=False)).left
    rng = np.random.default_rng(pose_seed)
    for pose in sample_poses(scn, scene, rng, n, **pose_kw):
        image = cam.render(pose)
        tb = project_targets(cam, pose)
        boxes = np.array([b.bbox_xyxy_px for b in tb], float).reshape(-1, 4)
        yield Sample(image, boxes, [b.class_name for b in tb], np.array([b.visible_fraction for b in tb]), scn.name)


def heldout_sets() -> dict[str, tuple]:
    """Held-out evaluation scenarios: name -> (scenario, pose seed). Seeds and scenarios here
    never appear in training."""
    from aeroperception.services.sim.world.scenario import load_scenario

    sets = {f"village@{s}": (reseeded("village", s), 5000 + s) for s in HELDOUT_VILLAGE_SEEDS}
    for i, name in enumerate(HELDOUT_SCENARIOS):
        sets[name] = (load_scenario(name), 7000 + i)
    return sets


def heldout_samples(n_per_set: int, names: list[str] | None = None) -> dict[str, list[Sample]]:
    sets = heldout_sets()
    unknown = sorted(set(names or ()) - set(sets))
    if unknown:
        raise ValueError(f"unknown held-out set(s) {', '.join(unknown)}: expected {', '.join(sets)}")
    return {name: list(render_samples(scn, n_per_set, seed))
            for name, (scn, seed) in sets.items() if names is None or name in names}
