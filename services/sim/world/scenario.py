"""Scenario files: the simulated world and sensor rig, as YAML.

A scenario is validated when loaded, and every error names the file and the field
(`village.yaml: objects[3].size_m: must be 3 positive numbers`) so a typo never turns into a
silently different world. Unknown fields are errors for the same reason.

Frames: positions are ENU metres. Object and target `position_m` is the (x, y) of the base
centre; the base sits on the ground (sloped or not) plus `elevation_m`. Yaw is ENU yaw in degrees
(0 = facing East, counter-clockwise positive). Body-mounted sensor positions are FLU metres.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import MISSING, dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any, Callable

import yaml

MAX_SLOPE_DEG = 10.0

# YOLO / COCO-80 order: the index is the class id detectors report.
COCO_CLASSES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange",
    "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch", "potted plant",
    "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard", "cell phone",
    "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
    "teddy bear", "hair drier", "toothbrush",
)

# Default target sizes (length along the target's yaw, width, height) in metres; classes not
# listed here must give size_m explicitly.
DEFAULT_TARGET_SIZE_M: dict[str, tuple[float, float, float]] = {
    "person": (0.45, 0.5, 1.75), "bicycle": (1.75, 0.6, 1.1), "car": (4.5, 1.85, 1.5),
    "motorcycle": (2.1, 0.8, 1.2), "bus": (12.0, 2.55, 3.2), "truck": (8.0, 2.5, 3.4),
    "dog": (0.9, 0.3, 0.6), "horse": (2.4, 0.7, 1.7), "cow": (2.4, 0.8, 1.5),
    "bench": (1.8, 0.6, 0.9), "chair": (0.5, 0.5, 0.9), "fire hydrant": (0.3, 0.3, 0.8),
    "stop sign": (0.1, 0.75, 2.5), "potted plant": (0.5, 0.5, 0.8),
}

# Material names -> (base RGB, texture family, texel size m). Textures live in scene.py; the
# table is here so scenario validation knows the valid names.
MATERIALS: dict[str, tuple[tuple[int, int, int], str, float]] = {
    "grass": ((95, 140, 60), "natural", 0.03),
    "dirt": ((135, 105, 75), "natural", 0.03),
    "forest_floor": ((100, 85, 60), "natural", 0.025),
    "asphalt": ((105, 105, 110), "natural", 0.02),
    "concrete": ((170, 170, 165), "urban", 0.03),
    "brick": ((165, 90, 65), "urban", 0.02),
    "facade": ((195, 185, 165), "urban", 0.03),
    "metal": ((150, 155, 160), "natural", 0.01),
    # bicycles: grey "metal" boxes were invisible on asphalt (no detector could find them)
    "bike_paint": ((30, 160, 170), "natural", 0.01),
    "crate": ((165, 125, 75), "urban", 0.015),
    "bark": ((105, 80, 55), "natural", 0.01),
    "foliage": ((60, 110, 50), "natural", 0.015),
    "clothing": ((70, 80, 150), "natural", 0.008),
    "car_paint": ((180, 45, 40), "urban", 0.01),
    "truck_paint": ((220, 220, 205), "urban", 0.015),
    "paint": ((200, 170, 60), "urban", 0.01),
    "plain": ((200, 200, 200), "flat", 0.05),
    "marker": ((255, 0, 255), "flat", 0.05),
}

CLASS_MATERIAL = {"person": "clothing", "car": "car_paint", "truck": "truck_paint",
                  "bus": "truck_paint", "bicycle": "bike_paint", "motorcycle": "metal"}


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the file and the field."""


class _FieldError(Exception):
    def __init__(self, path: str, message: str):
        super().__init__(f"{path}: {message}")
        self.path, self.message = path, message


# ---- field declarations: each carries its own parser/validator in metadata ----

_SCI = re.compile(r"[-+]?\d+(\.\d*)?[eE][-+]?\d+")


def _number(value: Any, path: str) -> float:
    if isinstance(value, str) and _SCI.fullmatch(value):
        value = float(value)   # PyYAML (YAML 1.1) reads 4e-6 as a string; accept it as meant
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _FieldError(path, f"must be a number, got {value!r}")
    return float(value)


def num(default: Any = MISSING, *, lo: float | None = None, hi: float | None = None,
        positive: bool = False, integer: bool = False, key: str | None = None) -> Any:
    """A number field, optionally bounded; `positive` means > 0."""
    def parse(value: Any, path: str) -> float | int:
        if integer and (isinstance(value, bool) or not isinstance(value, int)):
            raise _FieldError(path, f"must be an integer, got {value!r}")
        x = _number(value, path)
        if positive and x <= 0:
            raise _FieldError(path, f"must be > 0, got {value!r}")
        if (lo is not None and x < lo) or (hi is not None and x > hi):
            raise _FieldError(path, f"must be in [{lo}, {hi}], got {value!r}")
        return int(x) if integer else x
    return field(default=default, metadata={"parse": parse, "key": key})


def vec(n: int, default: Any = MISSING, *, positive: bool = False, key: str | None = None) -> Any:
    """A list of exactly n numbers, stored as a tuple (keeps scenarios hashable/cacheable)."""
    what = f"{n} positive numbers" if positive else f"{n} numbers"

    def parse(value: Any, path: str) -> tuple[float, ...]:
        if not isinstance(value, (list, tuple)) or len(value) != n:
            raise _FieldError(path, f"must be {what}, got {value!r}")
        try:
            out = tuple(_number(v, path) for v in value)
        except _FieldError:
            raise _FieldError(path, f"must be {what}, got {value!r}") from None
        if positive and min(out) <= 0:
            raise _FieldError(path, f"must be {what}, got {value!r}")
        return out
    return field(default=default, metadata={"parse": parse, "key": key})


def text(default: Any = MISSING, *, choices: tuple[str, ...] | None = None,
         key: str | None = None) -> Any:
    def parse(value: Any, path: str) -> str:
        if not isinstance(value, str):
            raise _FieldError(path, f"must be a string, got {value!r}")
        if choices is not None and value not in choices:
            shown = ", ".join(choices) if len(choices) <= 20 else "see COCO_CLASSES"
            raise _FieldError(path, f"unknown value {value!r} (expected one of: {shown})")
        return value
    return field(default=default, metadata={"parse": parse, "key": key})


def flag(default: bool) -> Any:
    def parse(value: Any, path: str) -> bool:
        if not isinstance(value, bool):
            raise _FieldError(path, f"must be true or false, got {value!r}")
        return value
    return field(default=default, metadata={"parse": parse})


def section(cls: type) -> Any:
    return field(default_factory=cls, metadata={"parse": lambda v, p: _build(cls, v, p)})


def _build(cls: type, data: Any, path: str) -> Any:
    """Construct dataclass `cls` from a YAML mapping, then run its `_check` cross-field rules."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise _FieldError(path or "<root>", f"must be a mapping, got {type(data).__name__}")
    prefix = f"{path}." if path else ""
    known = {(f.metadata.get("key") or f.name): f for f in fields(cls) if "parse" in f.metadata}
    for k in data:
        if k not in known:
            raise _FieldError(f"{prefix}{k}", f"unknown field (expected one of: {', '.join(known)})")
    kwargs = {}
    for k, f in known.items():
        if k in data:
            kwargs[f.name] = f.metadata["parse"](data[k], f"{prefix}{k}")
        elif f.default is MISSING and f.default_factory is MISSING:
            raise _FieldError(f"{prefix}{k}", "missing required field")
    obj = cls(**kwargs)
    check: Callable[[], list[tuple[str, str]]] | None = getattr(obj, "_check", None)
    for sub, msg in (check() if check else []):
        raise _FieldError(f"{prefix}{sub}", msg)
    return obj


# ---- the scenario model ----

@dataclass(frozen=True)
class Ground:
    """A flat plane, or tilted by slope_deg so that it rises towards slope_azimuth_deg
    (compass bearing: 0 = North, 90 = East)."""
    size_m: tuple[float, float] = vec(2, (300.0, 300.0), positive=True)
    slope_deg: float = num(0.0, lo=0.0, hi=MAX_SLOPE_DEG)
    slope_azimuth_deg: float = num(0.0, lo=-360.0, hi=360.0)
    material: str = text("grass", choices=tuple(MATERIALS))


@dataclass(frozen=True)
class Lighting:
    sun_azimuth_deg: float = num(135.0, lo=-360.0, hi=360.0)   # compass bearing of the sun
    sun_elevation_deg: float = num(50.0, lo=0.0, hi=90.0)
    ambient: float = num(0.35, lo=0.0, hi=1.0)                  # fraction of light not from the sun
    sky_rgb: tuple[float, float, float] = vec(3, (175.0, 205.0, 235.0))

    def _check(self) -> list[tuple[str, str]]:
        return [("sky_rgb", "must be 3 numbers in [0, 255]")] if not all(
            0 <= c <= 255 for c in self.sky_rgb) else []


@dataclass(frozen=True)
class Wind:
    """Consumed by the vehicle dynamics: a mean wind plus gusts (std per axis)."""
    mean_enu_mps: tuple[float, float, float] = vec(3, (0.0, 0.0, 0.0))
    gust_std_mps: float = num(0.0, lo=0.0, hi=20.0)


@dataclass(frozen=True)
class Start:
    position_m: tuple[float, float] = vec(2, (0.0, 0.0))  # ENU x, y
    height_agl_m: float = num(0.0, lo=0.0, hi=500.0)      # above the ground at (x, y)
    yaw_deg: float = num(0.0, lo=-360.0, hi=360.0)


@dataclass(frozen=True)
class BoxObject:
    """box / building / wall: an oriented box. elevation_m > 0 lifts it off the ground
    (canopies, bridges: overhead structure for the LiDAR labels)."""
    type: str = text(choices=("box", "building", "wall"))
    position_m: tuple[float, float] = vec(2)
    size_m: tuple[float, float, float] = vec(3, positive=True)
    yaw_deg: float = num(0.0, lo=-360.0, hi=360.0)
    elevation_m: float = num(0.0, lo=0.0, hi=200.0)
    material: str = text("", choices=("",) + tuple(MATERIALS))
    name: str = text("")

    def material_name(self) -> str:
        return self.material or {"box": "crate", "building": "facade", "wall": "concrete"}[self.type]


@dataclass(frozen=True)
class PoleObject:
    type: str = text(choices=("pole",))
    position_m: tuple[float, float] = vec(2)
    height_m: float = num(positive=True, hi=200.0)
    radius_m: float = num(0.1, positive=True, hi=5.0)
    material: str = text("metal", choices=tuple(MATERIALS))
    name: str = text("")


@dataclass(frozen=True)
class TreeObject:
    """Trunk cylinder plus a cone crown starting at crown_base_m: gives overhead returns."""
    type: str = text(choices=("tree",))
    position_m: tuple[float, float] = vec(2)
    height_m: float = num(8.0, positive=True, hi=100.0)
    trunk_radius_m: float = num(0.2, positive=True, hi=3.0)
    crown_radius_m: float = num(2.0, positive=True, hi=20.0)
    crown_base_m: float = num(3.0, lo=0.0, hi=100.0)
    name: str = text("")

    def _check(self) -> list[tuple[str, str]]:
        return [("crown_base_m", "must be below height_m")] if self.crown_base_m >= self.height_m else []


@dataclass(frozen=True)
class Target:
    """A detector target: an object with a COCO class and a 3D box used for ground truth."""
    class_name: str = text(choices=COCO_CLASSES, key="class")
    position_m: tuple[float, float] = vec(2)
    yaw_deg: float = num(0.0, lo=-360.0, hi=360.0)
    size_m: tuple[float, float, float] | None = vec(3, None, positive=True)
    material: str = text("", choices=("",) + tuple(MATERIALS))
    name: str = text("")

    def _check(self) -> list[tuple[str, str]]:
        if self.size_m is None and self.class_name not in DEFAULT_TARGET_SIZE_M:
            return [("size_m", f"required for class {self.class_name!r} (no default size)")]
        return []

    @property
    def size(self) -> tuple[float, float, float]:
        return self.size_m or DEFAULT_TARGET_SIZE_M[self.class_name]

    def material_name(self) -> str:
        return self.material or CLASS_MATERIAL.get(self.class_name, "paint")


@dataclass(frozen=True)
class CameraConfig:
    """Forward stereo pair (or a single camera with stereo: false). position_body_m is the rig
    centre in FLU; the left camera sits baseline_m/2 to the left. pitch_down_deg > 0 tilts the
    optical axis below the body x axis."""
    enabled: bool = flag(True)
    width: int = num(640, integer=True, lo=16, hi=4096)
    height: int = num(480, integer=True, lo=16, hi=4096)
    rate_hz: float = num(20.0, positive=True, hi=200.0)
    hfov_deg: float = num(90.0, lo=10.0, hi=150.0)
    stereo: bool = flag(True)
    baseline_m: float = num(0.08, lo=0.05, hi=0.12)
    encoding: str = text("rgb8", choices=("rgb8", "mono8"))
    pitch_down_deg: float = num(10.0, lo=-90.0, hi=90.0)
    position_body_m: tuple[float, float, float] = vec(3, (0.12, 0.0, 0.03))


@dataclass(frozen=True)
class DownCameraConfig:
    """Optional single camera looking straight down; image top = body forward."""
    enabled: bool = flag(False)
    width: int = num(320, integer=True, lo=16, hi=4096)
    height: int = num(240, integer=True, lo=16, hi=4096)
    rate_hz: float = num(10.0, positive=True, hi=200.0)
    hfov_deg: float = num(80.0, lo=10.0, hi=150.0)
    encoding: str = text("mono8", choices=("rgb8", "mono8"))
    position_body_m: tuple[float, float, float] = vec(3, (0.0, 0.0, -0.05))


@dataclass(frozen=True)
class ImuConfig:
    """Noise densities default to requirement VIO-2 (the values VIO is configured with)."""
    rate_hz: float = num(200.0, positive=True, hi=2000.0)
    gyro_noise_density: float = num(0.005, lo=0.0)      # rad/s/sqrt(Hz)
    accel_noise_density: float = num(0.01, lo=0.0)      # m/s^2/sqrt(Hz)
    gyro_random_walk: float = num(4.0e-6, lo=0.0)       # rad/s^2/sqrt(Hz)
    accel_random_walk: float = num(2.0e-4, lo=0.0)      # m/s^3/sqrt(Hz)
    initial_gyro_bias_radps: tuple[float, float, float] = vec(3, (0.0, 0.0, 0.0))
    initial_accel_bias_mps2: tuple[float, float, float] = vec(3, (0.0, 0.0, 0.0))
    noiseless: bool = flag(False)


@dataclass(frozen=True)
class LidarConfig:
    """Spinning 3D LiDAR: `beams` rows evenly over vfov_deg, `azimuth_steps` columns over 360°.
    Mount: position_body_m (FLU) and rpy_deg of the sensor frame (x forward, z up) in the body."""
    enabled: bool = flag(True)
    rate_hz: float = num(10.0, positive=True, hi=50.0)
    beams: int = num(64, integer=True, lo=1, hi=512)
    azimuth_steps: int = num(2048, integer=True, lo=8, hi=8192)
    vfov_deg: tuple[float, float] = vec(2, (-25.0, 15.0))
    min_range_m: float = num(0.5, lo=0.0)
    max_range_m: float = num(50.0, positive=True, hi=500.0)
    range_noise_std_m: float = num(0.02, lo=0.0, hi=1.0)
    position_body_m: tuple[float, float, float] = vec(3, (0.0, 0.0, 0.1))
    rpy_deg: tuple[float, float, float] = vec(3, (0.0, 0.0, 0.0))
    overhead_margin_m: float = num(1.0, lo=0.0)   # hits this far above the vehicle are "overhead"

    def _check(self) -> list[tuple[str, str]]:
        lo, hi = self.vfov_deg
        if not -90 <= lo < hi <= 90:
            return [("vfov_deg", f"must be [low, high] with -90 <= low < high <= 90, got {list(self.vfov_deg)}")]
        if self.min_range_m >= self.max_range_m:
            return [("min_range_m", "must be below max_range_m")]
        return []

    def dense_150k(self) -> "LidarConfig":
        """The ~150k-point scan of requirement LID-1 (128 beams x 1172 steps = 150,016 rays)."""
        return replace(self, beams=128, azimuth_steps=1172)


@dataclass(frozen=True)
class SensorRig:
    camera: CameraConfig = section(CameraConfig)
    down_camera: DownCameraConfig = section(DownCameraConfig)
    imu: ImuConfig = section(ImuConfig)
    lidar: LidarConfig = section(LidarConfig)


ObjectSpec = BoxObject | PoleObject | TreeObject
_OBJECT_TYPES: dict[str, type] = {"box": BoxObject, "building": BoxObject, "wall": BoxObject,
                                  "pole": PoleObject, "tree": TreeObject}


def _object_list(value: Any, path: str) -> tuple[ObjectSpec, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise _FieldError(path, "must be a list")
    out = []
    for i, item in enumerate(value):
        p = f"{path}[{i}]"
        kind = item.get("type") if isinstance(item, dict) else None
        if kind not in _OBJECT_TYPES:
            raise _FieldError(f"{p}.type", f"must be one of {', '.join(_OBJECT_TYPES)}, got {kind!r}")
        out.append(_build(_OBJECT_TYPES[kind], item, p))
    return tuple(out)


def _target_list(value: Any, path: str) -> tuple[Target, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise _FieldError(path, "must be a list")
    return tuple(_build(Target, item, f"{path}[{i}]") for i, item in enumerate(value))


@dataclass(frozen=True)
class Scenario:
    name: str = text()
    description: str = text("")
    seed: int = num(0, integer=True, lo=0)
    ground: Ground = section(Ground)
    lighting: Lighting = section(Lighting)
    wind: Wind = section(Wind)
    start: Start = section(Start)
    objects: tuple[ObjectSpec, ...] = field(default=(), metadata={"parse": _object_list})
    targets: tuple[Target, ...] = field(default=(), metadata={"parse": _target_list})
    sensors: SensorRig = section(SensorRig)
    source: str = ""  # file the scenario came from (not a YAML field)

    def _check(self) -> list[tuple[str, str]]:
        hx, hy = self.ground.size_m[0] / 2, self.ground.size_m[1] / 2
        items = [("objects", o) for o in self.objects] + [("targets", t) for t in self.targets]
        counters = {"objects": 0, "targets": 0}
        errors = []
        for kind, item in items:
            i = counters[kind]
            counters[kind] += 1
            x, y = item.position_m
            if abs(x) > hx or abs(y) > hy:
                errors.append((f"{kind}[{i}].position_m",
                               f"[{x:g}, {y:g}] is outside the ground (±{hx:g}, ±{hy:g} m)"))
        x, y = self.start.position_m
        if abs(x) > hx or abs(y) > hy:
            errors.append(("start.position_m", "is outside the ground"))
        return errors

    # ---- geometry helpers shared by the scene builder and the vehicle dynamics ----

    def ground_normal(self) -> tuple[float, float, float]:
        """Unit normal (ENU) of the ground plane."""
        g = math.tan(math.radians(self.ground.slope_deg))
        dx, dy = _uphill(self.ground.slope_azimuth_deg)
        n = (-g * dx, -g * dy, 1.0)
        s = math.sqrt(sum(c * c for c in n))
        return (n[0] / s, n[1] / s, n[2] / s)

    def ground_height_m(self, x_m: float, y_m: float) -> float:
        """Ground z (ENU) under (x, y); the plane passes through the origin."""
        g = math.tan(math.radians(self.ground.slope_deg))
        dx, dy = _uphill(self.ground.slope_azimuth_deg)
        return g * (dx * x_m + dy * y_m)

    def start_pose(self) -> tuple[tuple[float, float, float], float]:
        """((x, y, z) ENU m, yaw rad) of the vehicle at start."""
        x, y = self.start.position_m
        return (x, y, self.ground_height_m(x, y) + self.start.height_agl_m), math.radians(self.start.yaw_deg)


def _uphill(azimuth_deg: float) -> tuple[float, float]:
    """ENU unit vector of a compass bearing."""
    a = math.radians(azimuth_deg)
    return math.sin(a), math.cos(a)


def scenario_dir() -> Path:
    return Path(str(resources.files(__package__) / "scenarios"))


def available_scenarios() -> list[str]:
    return sorted(p.stem for p in scenario_dir().glob("*.yaml"))


def parse_scenario(data: Any, source: str = "<scenario>") -> Scenario:
    """Validate an already-parsed YAML document. `source` prefixes every error message."""
    try:
        scn = _build(Scenario, data, "")
    except _FieldError as e:
        raise ScenarioError(f"{source}: {e.path}: {e.message}") from None
    return replace(scn, source=source)


def load_scenario(path_or_name: str | os.PathLike) -> Scenario:
    """Load a scenario file, or a shipped scenario by name ("village")."""
    path = Path(path_or_name)
    if not path.exists() and path.parent == Path("."):
        path = scenario_dir() / (path.name if path.suffix == ".yaml" else f"{path.name}.yaml")
        if not path.exists():
            raise ScenarioError(f"unknown scenario {str(path_or_name)!r}: not a file and not one of "
                                f"{', '.join(available_scenarios())}")
    label = path.name
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as e:
        raise ScenarioError(f"{label}: cannot read: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise ScenarioError(f"{label}: not valid YAML: {e}") from None
    return replace(parse_scenario(data, label), source=str(path))
