"""Our schemas -> Rerun archetypes: one small converter per kind of data, and the registry that
maps each input key to its converter, sampling rate and slot. A new key is one `Adapter` entry.

Converters are plain functions (or tiny objects when they must remember something, e.g. a
trajectory or the last mission state) returning `Log`s; they never touch Zenoh or a recording,
so tests feed them messages and look at the archetypes.

Frames: the 3D scene is "world" = ENU "map" (x East, y North, z Up), the frame every pose and
cloud on Zenoh already uses; nothing is converted here. Quaternions go from our (w, x, y, z)
to Rerun's (x, y, z, w). Images are 2D spaces of their own under camera/<side>.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import numpy as np
import rerun as rr

from aeroperception.schemas import (
    BatteryState, Detection2DArray, DiagnosticStatus, GetMissionReply, Image, MissionStatus, Message,
    MissionGoal, OccupancyGrid, Odometry, PointCloud, Quaternion, SafetyStatus, TrajectorySetpoint,
    TrackedObjectArray, TrajectoryStatus, VehicleState, VioHealth, WaypointReached, parse_mission,
)
from aeroperception.services.runtime.rotations import quat_from_rotmat

if TYPE_CHECKING:
    from .config import VizConfig

WORLD = "world"
TIMELINE = "stamp"          # header.stamp_ns of every message (sim time in sim, epoch-anchored)

VEHICLE_COLOR = (40, 140, 255)
TRUTH_COLOR = (60, 200, 90)
VIO_COLOR = (255, 150, 30)
DETECTION_COLOR = (255, 220, 0)
TRUTH_BOX_COLOR = (60, 200, 90)
OBSTACLE_COLOR = (230, 60, 60)
GROUND_COLOR = (150, 130, 100)
GOAL_COLOR = (255, 0, 200)
SETPOINT_COLOR = (255, 0, 200)
TENTATIVE_COLOR = (160, 160, 160)


class Log(NamedTuple):
    """One rr.log call: entity path, archetypes, static (timeless) or at the message's stamp."""
    path: str
    archetypes: tuple
    static: bool = False


def log(path: str, *archetypes: Any, static: bool = False) -> Log:
    return Log(path, archetypes, static)


def rr_quat(q: Quaternion) -> rr.Quaternion:
    return rr.Quaternion(xyzw=[q.x, q.y, q.z, q.w])


# ------------------------------------------------------------------ static scene


def static_scene() -> list[Log]:
    """What is logged once: ENU axes, and the vehicle body models (a quadrotor X, nose = +x FLU)."""
    return [
        log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True),
        log(f"{WORLD}/vehicle/body/model", *quad_model(VEHICLE_COLOR), static=True),
        log(f"{WORLD}/truth/vehicle/model", *quad_model(TRUTH_COLOR, scale=0.9), static=True),
    ]


def quad_model(color, scale: float = 1.0) -> tuple:
    """Two crossed arms, four rotor discs and a red nose arrow, in the body frame (FLU), ~0.5 m."""
    arm = 0.25 * scale
    diag = arm / math.sqrt(2)
    rotors = [[diag, diag, 0.03], [diag, -diag, 0.03], [-diag, diag, 0.03], [-diag, -diag, 0.03]]
    return (
        rr.Boxes3D(half_sizes=[[arm, 0.015, 0.01], [arm, 0.015, 0.01], [0.06, 0.05, 0.03]],
                   quaternions=[rr.Quaternion(xyzw=[0, 0, math.sin(math.pi / 8), math.cos(math.pi / 8)]),
                                rr.Quaternion(xyzw=[0, 0, -math.sin(math.pi / 8), math.cos(math.pi / 8)]),
                                rr.Quaternion.identity()],
                   colors=[color], fill_mode="solid"),
        rr.Ellipsoids3D(centers=rotors, half_sizes=[[0.09 * scale, 0.09 * scale, 0.005]] * 4,
                        colors=[color], fill_mode="solid"),
        rr.Arrows3D(origins=[[0, 0, 0]], vectors=[[0.35 * scale, 0, 0]], colors=[(255, 40, 40)], radii=0.012),
    )


# ------------------------------------------------------------------ pose and trajectory


class Trail:
    """A trajectory as one line strip: positions kept (bounded, decimated by distance) and the
    strip re-sent at most every `period_s` of stamp time, so a long flight costs O(max_points)."""

    def __init__(self, path: str, color, period_s: float = 0.5, max_points: int = 5000,
                 min_step_m: float = 0.05):
        self.path, self.color = path, color
        self.period_ns = int(period_s * 1e9)
        self.min_step_m = min_step_m
        self.points: deque[tuple[float, float, float]] = deque(maxlen=max_points)
        self.last_sent_ns: int | None = None

    def __call__(self, stamp_ns: int, p) -> list[Log]:
        pt = (float(p.x), float(p.y), float(p.z))
        if not all(math.isfinite(v) for v in pt):
            return []
        if not self.points or math.dist(pt, self.points[-1]) >= self.min_step_m:
            self.points.append(pt)
        if self.last_sent_ns is not None and 0 <= stamp_ns - self.last_sent_ns < self.period_ns:
            return []
        self.last_sent_ns = stamp_ns
        return [log(self.path, rr.LineStrips3D([list(self.points)], colors=[self.color], radii=0.03))]


def vehicle_pose(msg: VehicleState, root: str = f"{WORLD}/vehicle") -> list[Log]:
    """Translation on `root` (ENU), attitude on root/body, so children of `root` (the setpoint
    arrow) stay in ENU axes while the body model turns."""
    p = msg.position_m
    return [log(root, rr.Transform3D(translation=[p.x, p.y, p.z])),
            log(f"{root}/body", rr.Transform3D(quaternion=rr_quat(msg.orientation)))]


def vehicle_series(msg: VehicleState, source: str) -> list[Log]:
    return [log(f"series/altitude_m/{source}", rr.Scalars(msg.position_m.z)),
            log(f"series/speed_mps/{source}", rr.Scalars(float(np.linalg.norm(msg.velocity_mps.to_array()))))]


class VehicleAdapter:
    """state/vehicle: pose + body, trajectory, altitude / speed / battery series."""

    def __init__(self, trail_period_s: float = 0.5, trail_max_points: int = 5000):
        self.trail = Trail(f"{WORLD}/trajectory/vehicle", VEHICLE_COLOR, trail_period_s, trail_max_points)

    def __call__(self, msg: VehicleState) -> list[Log]:
        return [*vehicle_pose(msg), *self.trail(msg.header.stamp_ns, msg.position_m), *vehicle_series(msg, "vehicle")]


class TruthAdapter:
    """sim/truth/state: the true pose (green model), true track and series beside the estimate."""

    def __init__(self, trail_period_s: float = 0.5, trail_max_points: int = 5000):
        self.trail = Trail(f"{WORLD}/trajectory/truth", TRUTH_COLOR, trail_period_s, trail_max_points)

    def __call__(self, msg: VehicleState) -> list[Log]:
        p = msg.position_m
        return [log(f"{WORLD}/truth/vehicle", rr.Transform3D(translation=[p.x, p.y, p.z], quaternion=rr_quat(msg.orientation))),
                *self.trail(msg.header.stamp_ns, p), *vehicle_series(msg, "truth")]


def covariance_ellipsoid(cov3: np.ndarray, n_sigma: float = 2.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Half-sizes (n_sigma standard deviations along the principal axes) and the (w, x, y, z)
    rotation of those axes, from a 3x3 position covariance; None when it is not finite."""
    cov3 = np.asarray(cov3, float)
    if cov3.shape != (3, 3) or not np.all(np.isfinite(cov3)):
        return None
    vals, vecs = np.linalg.eigh(0.5 * (cov3 + cov3.T))
    if np.linalg.det(vecs) < 0:
        vecs[:, 2] = -vecs[:, 2]
    return n_sigma * np.sqrt(np.clip(vals, 0.0, None)), quat_from_rotmat(vecs)


class VioAdapter:
    """state/visual_odometry: pose axes, track and the 2-sigma position covariance ellipsoid."""

    def __init__(self, trail_period_s: float = 0.5, trail_max_points: int = 5000):
        self.trail = Trail(f"{WORLD}/trajectory/vio", VIO_COLOR, trail_period_s, trail_max_points)

    def __call__(self, msg: Odometry) -> list[Log]:
        p = msg.pose.position
        out = [log(f"{WORLD}/vio", rr.Transform3D(translation=[p.x, p.y, p.z], quaternion=rr_quat(msg.pose.orientation)),
                   rr.TransformAxes3D(axis_length=0.4)),
               *self.trail(msg.header.stamp_ns, p)]
        if msg.pose_covariance is not None:
            cov = msg.pose_covariance.to_numpy()
            ell = covariance_ellipsoid(cov[:3, :3]) if cov.shape == (6, 6) else None
            if ell is not None:
                half, q = ell
                out.append(log(f"{WORLD}/vio_covariance", rr.Ellipsoids3D(
                    centers=[[p.x, p.y, p.z]], half_sizes=[half], quaternions=[rr.Quaternion(xyzw=[q[1], q[2], q[3], q[0]])],
                    colors=[(*VIO_COLOR, 90)], fill_mode="solid")))
                out.append(log("series/vio/position_sigma_m", rr.Scalars(float(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))))
        return out


VIO_STATES = {0: "INIT", 1: "TRACKING", 2: "DEGRADED", 3: "LOST"}
VIO_LEVELS = {0: rr.TextLogLevel.INFO, 1: rr.TextLogLevel.INFO, 2: rr.TextLogLevel.WARN, 3: rr.TextLogLevel.ERROR}


class VioHealthAdapter:
    """state/vio_health: tracked features as a series; each state change as a text line."""

    def __init__(self):
        self.last: int | None = None

    def __call__(self, msg: VioHealth) -> list[Log]:
        out = [log("series/vio/tracked_features", rr.Scalars(msg.tracked_features))]
        if msg.state != self.last:
            self.last = msg.state
            name = VIO_STATES.get(msg.state, str(msg.state))
            out.append(log("logs/vio", rr.TextLog(f"VIO {name}: {msg.message}", level=VIO_LEVELS.get(msg.state, "INFO"))))
        return out


# ------------------------------------------------------------------ cameras and detections


def camera_of(frame_id: str) -> str:
    return "right" if "right" in frame_id else "left"


class ImageAdapter:
    """sensors/camera/<side>/image -> camera/<side>/image; JPEG (quality > 0, needs OpenCV) keeps
    the viewer's memory and the link small: ~60 KB instead of 900 KB for 640x480 RGB."""

    def __init__(self, side: str, jpeg_quality: int = 75):
        self.path = f"camera/{side}/image"
        self.jpeg_quality = jpeg_quality

    def __call__(self, msg: Image) -> list[Log]:
        return [log(self.path, image_archetype(msg, self.jpeg_quality))]


def image_archetype(msg: Image, jpeg_quality: int = 0):
    px = msg.to_numpy()
    enc = msg.encoding
    if enc in ("16UC1", "32FC1"):
        return rr.DepthImage(px, meter=1000.0 if enc == "16UC1" else 1.0)
    if jpeg_quality > 0 and enc in ("mono8", "rgb8", "bgr8"):
        jpeg = _jpeg(px, enc, jpeg_quality)
        if jpeg is not None:
            return rr.EncodedImage(contents=jpeg, media_type="image/jpeg")
    color_model = {"mono8": "L", "mono16": "L", "rgb8": "RGB", "bgr8": "BGR", "rgba8": "RGBA", "bgra8": "BGRA"}[enc]
    return rr.Image(np.ascontiguousarray(px), color_model=color_model)


def _jpeg(px: np.ndarray, encoding: str, quality: int) -> bytes | None:
    try:
        import cv2
    except ImportError:     # tools extra without OpenCV: raw pixels
        return None
    if encoding == "rgb8":
        px = px[..., ::-1]    # OpenCV writes BGR
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(px), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return buf.tobytes() if ok else None


class BoxesAdapter:
    """Detection2DArray -> Boxes2D over camera/<side>/image (side from header.frame_id), labelled
    "class score"; `name` separates the detector's boxes from the sim's truth boxes."""

    def __init__(self, name: str, color):
        self.name, self.color = name, color

    def __call__(self, msg: Detection2DArray) -> list[Log]:
        d = msg.detections
        path = f"camera/{camera_of(msg.header.frame_id)}/image/{self.name}"
        if not d:
            return [log(path, rr.Clear(recursive=False))]
        return [log(path, rr.Boxes2D(
            centers=[[b.center_x_px, b.center_y_px] for b in d], sizes=[[b.size_x_px, b.size_y_px] for b in d],
            labels=[f"{b.class_name or b.class_id} {b.score:.2f}" for b in d], class_ids=[b.class_id for b in d],
            colors=[self.color], show_labels=True))]


# ------------------------------------------------------------------ LiDAR and costmap


def cloud_adapter(name: str, color, radius: float) -> Callable[[PointCloud], list[Log]]:
    def convert(msg: PointCloud) -> list[Log]:
        if msg.header.frame_id not in ("map", "world", ""):
            return []     # not placed in the world yet (e.g. lidar "lidar_level" without a pose)
        return [log(f"{WORLD}/perception/{name}", rr.Points3D(msg.points.to_numpy(), colors=[color], radii=radius))]
    return convert


def costmap(msg: OccupancyGrid) -> list[Log]:
    """The rolling costmap as a GridMap on the ground plane: row 0 at the origin, columns along x
    (the OccupancyGrid convention GridMap shares); -1 unknown becomes 255 as ROS viewers do."""
    grid = msg.data.to_numpy()
    o = msg.origin
    return [log(f"{WORLD}/perception/costmap", rr.GridMap(
        data=np.ascontiguousarray(grid).view(np.uint8).tobytes(),
        format=rr.components.ImageFormat(width=msg.width, height=msg.height, color_model="L", channel_datatype="U8"),
        cell_size=msg.resolution_m, translation=[o.position.x, o.position.y, 0.02],
        quaternion=rr_quat(o.orientation), colormap=rr.components.Colormap.Costmap, opacity=0.6))]


# ------------------------------------------------------------------ mission and planner


class MissionStatusAdapter:
    """mission/status: every state change (and its message) as a text line; distance to goal."""

    def __init__(self):
        self.last: tuple | None = None

    def __call__(self, msg: MissionStatus) -> list[Log]:
        out = []
        if msg.distance_to_goal_m is not None:
            out.append(log("series/mission/distance_to_goal_m", rr.Scalars(msg.distance_to_goal_m)))
        now = (msg.state, msg.mission_id, msg.active_waypoint, msg.message)
        if now != self.last:
            self.last = now
            wp = f" waypoint {msg.active_waypoint + 1}/{msg.total_waypoints}" if msg.active_waypoint >= 0 else ""
            text = f"{msg.state}{wp}" + (f" [{msg.mission_id}]" if msg.mission_id else "") + (f": {msg.message}" if msg.message else "")
            out.append(log("logs/mission", rr.TextLog(text, level=rr.TextLogLevel.INFO)))
        return out


def active_goal(msg: MissionGoal) -> list[Log]:
    path = f"{WORLD}/mission/active_goal"
    if msg.header.frame_id == MissionGoal.HOLD_FRAME:
        return [log(path, rr.Clear(recursive=False))]
    p = msg.pose.position
    return [log(path, rr.Points3D([[p.x, p.y, p.z]], colors=[GOAL_COLOR], radii=0.25, labels=["goal"]))]


def mission_waypoints(reply: GetMissionReply) -> list[Log]:
    """The loaded mission (mission/srv/get) as numbered points joined by a line."""
    path = f"{WORLD}/mission/waypoints"
    if not reply.success or not reply.mission_json:
        return [log(path, rr.Clear(recursive=True))]
    m = parse_mission(reply.mission_json)
    pts = [[w.x, w.y, w.z] for w in m.waypoints]
    return [log(path, rr.Points3D(pts, colors=[(255, 255, 255)], radii=0.15, labels=[str(i + 1) for i in range(len(pts))]),
                rr.LineStrips3D([pts], colors=[(200, 200, 200)], radii=0.02))]


class WaypointReachedAdapter:
    """mission/waypoint_reached: where each waypoint was reached (kept for the whole flight)."""

    def __init__(self, max_points: int = 1000):
        self.points: deque[list[float]] = deque(maxlen=max_points)

    def __call__(self, msg: WaypointReached) -> list[Log]:
        p = msg.position_m
        self.points.append([p.x, p.y, p.z])
        return [log(f"{WORLD}/mission/reached", rr.Points3D(list(self.points), colors=[TRUTH_COLOR], radii=0.12)),
                log("logs/mission", rr.TextLog(f"waypoint {msg.index + 1} reached at ({p.x:.1f}, {p.y:.1f}, {p.z:.1f})",
                                               level=rr.TextLogLevel.INFO))]


class ObjectsAdapter:
    """perception/objects: each live track as a labelled point where it is ("person #7 0.91";
    tentative tracks grey), and every track's history as a line (bounded per track, and tracks
    gone for `forget_after` messages are dropped from the view's memory)."""

    def __init__(self, max_points: int = 200, forget_after: int = 600):
        self.max_points, self.forget_after = max_points, forget_after
        self.history: dict[int, deque[list[float]]] = {}
        self.last_seen: dict[int, int] = {}
        self.count = 0

    def __call__(self, msg: TrackedObjectArray) -> list[Log]:
        self.count += 1
        points, labels, colors, class_ids = [], [], [], []
        for o in msg.objects:
            p = [o.position_m.x, o.position_m.y, o.position_m.z]
            if not all(math.isfinite(v) for v in p):
                continue
            points.append(p)
            labels.append(f"{o.class_name} #{o.track_id} {o.best_score:.2f}")
            colors.append(DETECTION_COLOR if o.confirmed else TENTATIVE_COLOR)
            class_ids.append(o.class_id)
            if o.confirmed:
                self.history.setdefault(o.track_id, deque(maxlen=self.max_points)).append(p)
                self.last_seen[o.track_id] = self.count
        for tid in [t for t, seen in self.last_seen.items() if self.count - seen > self.forget_after]:
            del self.history[tid], self.last_seen[tid]
        path = f"{WORLD}/objects"
        out = [log(f"{path}/tracks", rr.Points3D(points, colors=colors, radii=0.25, labels=labels,
                                                 class_ids=class_ids) if points else rr.Clear(recursive=False))]
        lines = [list(h) for h in self.history.values() if len(h) > 1]
        if lines:
            out.append(log(f"{path}/history", rr.LineStrips3D(lines, colors=[DETECTION_COLOR], radii=0.04)))
        return out


def setpoint(msg: TrajectorySetpoint) -> list[Log]:
    """The planner's velocity command as an ENU arrow from the vehicle (world/vehicle carries only
    the translation); a position setpoint as a point in the world."""
    out = []
    if msg.velocity_valid or not msg.position_valid:
        v = msg.velocity_mps
        out.append(log(f"{WORLD}/vehicle/setpoint", rr.Arrows3D(origins=[[0, 0, 0]], vectors=[[v.x, v.y, v.z]],
                                                               colors=[SETPOINT_COLOR], radii=0.025)))
    if msg.position_valid:
        p = msg.position_m
        out.append(log(f"{WORLD}/planner/setpoint_position", rr.Points3D([[p.x, p.y, p.z]], colors=[SETPOINT_COLOR], radii=0.08)))
    return out


class PlannerStatusAdapter:
    """planner/status: position error series; obstacle verdict changes as text."""

    def __init__(self):
        self.last: tuple | None = None

    def __call__(self, msg: TrajectoryStatus) -> list[Log]:
        out = [log("series/planner/position_error_m", rr.Scalars(msg.position_error_m))]
        now = (msg.status, msg.obstacle_state, msg.message)
        if now != self.last:
            self.last = now
            level = rr.TextLogLevel.WARN if msg.obstacle_state in ("blocked", "unreachable") else rr.TextLogLevel.INFO
            out.append(log("logs/planner", rr.TextLog(f"status {msg.status} obstacles {msg.obstacle_state or '-'}"
                                                      + (f": {msg.message}" if msg.message else ""), level=level)))
        return out


def battery(msg: BatteryState) -> list[Log]:
    """Charge (%) and voltage as separate series: one axis for both would flatten the charge."""
    out = [log("series/battery_voltage_v", rr.Scalars(msg.voltage_v))]
    if msg.remaining_fraction is not None:
        out.append(log("series/battery_pct/remaining", rr.Scalars(100.0 * msg.remaining_fraction)))
    return out


class SafetyAdapter:
    """safety/status: level, recommended action, warnings and errors as text when they change."""

    LEVELS = ("NOMINAL", "WARNING", "CAUTION", "EMERGENCY")
    ACTIONS = ("NONE", "WARN", "HOLD", "RTH", "LAND", "EMERGENCY_STOP")

    def __init__(self):
        self.last: tuple | None = None

    def __call__(self, msg: SafetyStatus) -> list[Log]:
        now = (msg.safety_level, msg.recommended_action, tuple(msg.active_warnings), tuple(msg.active_errors))
        if now == self.last:
            return []
        self.last = now
        level = (rr.TextLogLevel.INFO, rr.TextLogLevel.WARN, rr.TextLogLevel.WARN, rr.TextLogLevel.ERROR)[min(msg.safety_level, 3)]
        name = self.LEVELS[msg.safety_level] if 0 <= msg.safety_level < len(self.LEVELS) else str(msg.safety_level)
        act = self.ACTIONS[msg.recommended_action] if 0 <= msg.recommended_action < len(self.ACTIONS) else str(msg.recommended_action)
        issues = "; ".join([*msg.active_errors, *msg.active_warnings])
        return [log("logs/safety", rr.TextLog(f"{name} action {act}" + (f": {issues}" if issues else ""), level=level))]


DIAG_LEVELS = {0: rr.TextLogLevel.INFO, 1: rr.TextLogLevel.WARN, 2: rr.TextLogLevel.ERROR, 3: rr.TextLogLevel.WARN}
LOOP_STATS = ("work_p99_ms", "period_error_p99_ms")


class DiagnosticsAdapter:
    """diagnostics/<service>: a text line per service when its level changes (messages carry
    live numbers, e.g. achieved rates, so every message would be a line a second); the runtime's loop
    timing (loop[<name>].work_p99_ms ...) and stage timings (*_ms_p99) as series, one series
    per "<service>.<loop>" under the statistic, so a plot compares services on one axis."""

    def __init__(self):
        self.last: dict[str, int] = {}

    def __call__(self, msg: DiagnosticStatus) -> list[Log]:
        svc = msg.name or "unknown"
        out = []
        for k, v in msg.values.items():
            name = None
            if k.startswith("loop[") and "]." in k:
                loop, _, stat = k[5:].partition("].")
                if stat in LOOP_STATS:
                    name = f"series/loop_{stat}/{svc}.{loop}"
            elif k.endswith("_ms_p99"):
                name = f"series/stage_ms_p99/{svc}.{k.removesuffix('_ms_p99')}"
            if name is not None:
                try:
                    out.append(log(name, rr.Scalars(float(v))))
                except (TypeError, ValueError):
                    pass
        if self.last.get(svc) != msg.level:
            self.last[svc] = msg.level
            out.append(log(f"logs/diagnostics/{svc}", rr.TextLog(f"{svc}: {msg.message}",
                                                                 level=DIAG_LEVELS.get(msg.level, rr.TextLogLevel.INFO))))
        return out


# ------------------------------------------------------------------ the registry


@dataclass
class Adapter:
    """How one input key reaches the viewer.

    rate_param: the parameter holding its sampling rate in Hz (0 = not subscribed), or None for
    low-rate / event keys taken as they come. truth: sim ground truth (dropped when show_truth is
    off). follows: only messages whose stamp matches a frame sampled on that image key (boxes
    drawn on the very image they belong to). slot: newest-wins slot per message (diagnostics:
    one per service, so services do not displace each other).
    """
    key: str
    schema: type[Message]
    convert: Callable[[Any], list[Log]]
    rate_param: str | None = None
    truth: bool = False
    follows: str | None = None
    slot: Callable[[Any], str] | None = field(default=None)


def build_adapters(p: "VizConfig") -> list[Adapter]:
    """The registry, with fresh converter state, configured from the viz config `p`."""
    trail = dict(trail_period_s=p.trail_period_s, trail_max_points=p.trail_max_points)
    left, right = "sensors/camera/left/image", "sensors/camera/right/image"
    return [
        Adapter("state/vehicle", VehicleState, VehicleAdapter(**trail), "pose_rate_hz"),
        Adapter("sim/truth/state", VehicleState, TruthAdapter(**trail), "pose_rate_hz", truth=True),
        Adapter("state/visual_odometry", Odometry, VioAdapter(**trail), "pose_rate_hz"),
        Adapter("state/vio_health", VioHealth, VioHealthAdapter()),
        Adapter(left, Image, ImageAdapter("left", p.image_jpeg_quality), "image_rate_hz"),
        Adapter(right, Image, ImageAdapter("right", p.image_jpeg_quality), "image_rate_hz"),
        Adapter("perception/detections", Detection2DArray, BoxesAdapter("detections", DETECTION_COLOR),
                "image_rate_hz", follows=left),
        Adapter("sim/truth/boxes", Detection2DArray, BoxesAdapter("truth_boxes", TRUTH_BOX_COLOR),
                "image_rate_hz", truth=True, follows=left),
        Adapter("perception/obstacles", PointCloud, cloud_adapter("obstacles", OBSTACLE_COLOR, 0.06), "cloud_rate_hz"),
        Adapter("perception/ground", PointCloud, cloud_adapter("ground", GROUND_COLOR, 0.03), "cloud_rate_hz"),
        Adapter("perception/costmap", OccupancyGrid, costmap, "costmap_rate_hz"),
        Adapter("perception/objects", TrackedObjectArray, ObjectsAdapter(), "objects_rate_hz"),
        Adapter("mission/status", MissionStatus, MissionStatusAdapter()),
        Adapter("mission/active_goal", MissionGoal, active_goal),
        Adapter("mission/waypoint_reached", WaypointReached, WaypointReachedAdapter()),
        Adapter("planner/status", TrajectoryStatus, PlannerStatusAdapter()),
        Adapter("fmu/in/trajectory_setpoint", TrajectorySetpoint, setpoint, "setpoint_rate_hz"),
        Adapter("fmu/out/battery_status", BatteryState, battery),
        Adapter("safety/status", SafetyStatus, SafetyAdapter()),
        Adapter("diagnostics/*", DiagnosticStatus, DiagnosticsAdapter(), slot=lambda m: f"diagnostics/{m.name}"),
    ]
