"""One detection frame in, tracks and events out: the objects service without Zenoh.

`ObjectsPipeline` holds what a frame needs besides its boxes (the pose history, the camera
calibration, the recent stereo pairs by stamp, the FC's home) and counts every detection it could
not place, by reason, so diagnostics say why a box never became an object.
"""
from __future__ import annotations

import time
from collections import Counter, OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from aeroperception.schemas import (
    CameraInfo, Detection2DArray, Header, HomePosition, Image, ObjectEvent, TrackedObject, TrackedObjectArray,
    Vector3, VehicleState,
)
from aeroperception.services.lib.geo import MapProjection
from aeroperception.services.lib.pose_history import PoseHistory
from aeroperception.services.runtime import param, section

from . import contract
from .projection import (
    Camera, GrayView, Noise, box_disparity, box_scale, centre_aims, fuse, locate_many_by_disparity,
    locate_many_on_ground, to_centre,
)
from .tracker import ObjectTrackerConfig, Observation, Track, Tracker


@dataclass(frozen=True)
class ObjectsConfig:
    """Every parameter of contract.PARAMS, referenced once (rebuilt on a live change)."""

    tracker: ObjectTrackerConfig = section(ObjectTrackerConfig)
    stereo: bool = param("stereo")
    stereo_max_range_m: float = param("stereo_max_range_m")
    max_range_m: float = param("max_range_m")
    ground_z_m: float = param("ground_z_m")
    pose_tolerance_s: float = param("pose_tolerance_s")
    min_score: float = param("min_score")
    pixel_sigma_px: float = param("pixel_sigma_px")
    disparity_sigma_px: float = param("disparity_sigma_px")
    height_sigma_m: float = param("height_sigma_m")
    position_sigma_m: float = param("position_sigma_m")
    pose_time_sigma_s: float = param("pose_time_sigma_s")
    attitude_sigma_rad: float = param("attitude_sigma_rad")


def noise(p: ObjectsConfig, turn_px: float = 0.0) -> Noise:
    """The placement noise; `turn_px` (the pixels the camera turns through in the pose's timing
    uncertainty) adds to the box centre's: a ray's direction is what an attitude error moves, so
    the ground path's range takes it amplified at a shallow angle, as it does the pixel noise."""
    return Noise(pixel_px=float(np.hypot(p.pixel_sigma_px, turn_px)), disparity_px=p.disparity_sigma_px,
                 height_m=p.height_sigma_m, position_m=p.position_sigma_m, attitude_rad=p.attitude_sigma_rad)


class StereoFrames:
    """The last few left/right images by stamp, so a detection (which arrives after its image)
    finds its pair. Decoded images own their payload: kept as they are, converted only where a box
    needs it."""

    def __init__(self, keep: int = 20):
        self.keep = keep
        self.sides: dict[str, OrderedDict[int, Image]] = {"left": OrderedDict(), "right": OrderedDict()}

    def add(self, side: str, img: Image) -> None:
        frames = self.sides[side]
        frames[img.header.stamp_ns] = img
        while len(frames) > self.keep:
            frames.popitem(last=False)

    def pair(self, stamp_ns: int) -> tuple[GrayView, GrayView] | None:
        left, right = self.sides["left"].get(stamp_ns), self.sides["right"].get(stamp_ns)
        if left is None or right is None:
            return None
        return gray(left), gray(right)


def _cut(d, dets: Detection2DArray, margin_px: float = 2.0) -> bool:
    """Whether the box touches the image's edge (part of the object lies outside the image)."""
    w, h = dets.image_width, dets.image_height
    return bool(w and h) and (d.center_x_px - d.size_x_px / 2 <= margin_px or d.center_y_px - d.size_y_px / 2 <= margin_px
                              or d.center_x_px + d.size_x_px / 2 >= w - margin_px
                              or d.center_y_px + d.size_y_px / 2 >= h - margin_px)


_TO_GRAY = {"rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY,
            "bgra8": cv2.COLOR_BGRA2GRAY}


def gray(img: Image) -> GrayView:
    """The image as 8-bit gray, converted where a box's strip is cut (not the whole frame: 0.4 ms
    a colour image, every frame, however few boxes)."""
    a = img.to_numpy()
    return GrayView(a, None if a.ndim == 2 else _TO_GRAY[img.encoding])


@dataclass
class FrameResult:
    objects: TrackedObjectArray
    events: list[ObjectEvent]
    elapsed_ms: float                   # wall clock
    cpu_ms: float                       # this thread's CPU: the cost, whatever else shares the cores


class ObjectsPipeline:
    """Feed it state, home, camera infos and images as they come; `process(detections)` per frame."""

    def __init__(self, cfg: ObjectsConfig):
        self.cfg = cfg
        self.poses = PoseHistory()
        self.frames = StereoFrames()
        self.infos: dict[str, CameraInfo | None] = {"left": None, "right": None}
        self.camera: Camera | None = None
        self.home: HomePosition | None = None
        self.projection: MapProjection | None = None
        self.tracker = Tracker(cfg.tracker)
        self.dropped = Counter()               # detections (or frames) not placed, by reason
        self.placed = Counter()                # detections placed, by method
        self.last_stamp_ns = 0
        self.last_frame_mono_s = 0.0           # when the frame of last_stamp_ns was placed (monotonic)

    # ------------------------------------------------------------ inputs besides detections

    def on_state(self, msg: VehicleState) -> None:
        self.poses.add(msg)

    def on_home(self, msg: HomePosition) -> None:
        self.home = msg
        self.projection = MapProjection(msg.latitude_deg, msg.longitude_deg)

    def on_info(self, side: str, msg: CameraInfo) -> None:
        self.infos[side] = msg
        if self.infos["left"] is not None:
            self.camera = Camera.from_infos(self.infos["left"], self.infos["right"])

    def on_image(self, side: str, msg: Image) -> None:
        self.frames.add(side, msg)

    def reconfigure(self, cfg: ObjectsConfig) -> None:
        self.cfg = cfg
        self.tracker.configure(cfg.tracker)

    # ------------------------------------------------------------ one frame

    def ground_z_m(self) -> float:
        return self.home.position_m.z if self.home is not None else self.cfg.ground_z_m

    def process(self, dets: Detection2DArray) -> FrameResult | None:
        """Place, associate, publishable result; None when the frame cannot be used (counted)."""
        t0 = (time.perf_counter(), time.thread_time())
        stamp = dets.header.stamp_ns
        if stamp <= self.last_stamp_ns:
            self.dropped["frame_out_of_order"] += 1
            return None
        if self.camera is None:
            self.dropped["frame_no_camera_info"] += 1
            return None
        pose = self.poses.at(stamp, self.cfg.pose_tolerance_s)
        if pose is None:
            self.dropped["frame_no_pose"] += 1
            return None
        self.last_stamp_ns, self.last_frame_mono_s = stamp, time.monotonic()
        obs = self._observations(dets, pose)
        ev = self.tracker.update(stamp, obs)
        return self._result(stamp, ev, t0)

    def expire(self, now_mono_s: float) -> list[ObjectEvent]:
        """Lost events for tracks unseen for their timeout while no detection frame came. Time runs
        on from the last frame's stamp (the image clock: sim time lags the wall clock when the sim
        runs slower than real time, and a wall-clock deadline would drop live tracks)."""
        if not self.last_stamp_ns:
            return []
        stamp_ns = self.last_stamp_ns + int((now_mono_s - self.last_frame_mono_s) * 1e9)
        ev = self.tracker.expire(stamp_ns)
        return [self._event(ObjectEvent.LOST, t, stamp_ns) for t in ev.lost]

    def _observations(self, dets: Detection2DArray, pose) -> list[Observation]:
        p, cam = self.cfg, self.camera
        nz = noise(p, cam.fx * pose.rate_radps * p.pose_time_sigma_s)
        pair = self.frames.pair(dets.header.stamp_ns) if p.stereo and cam.baseline_m > 0 else None
        max_disp = int(np.ceil(cam.fx * cam.baseline_m / p.stereo_max_range_m)) if pair else 0
        ground = self.ground_z_m()
        view = cam.world_pose(pose)
        boxes = [d for d in dets.detections if d.score >= p.min_score]
        if not boxes:
            return []
        sizes = [contract.TYPICAL_SIZE_M.get(d.class_name, contract.DEFAULT_SIZE_M) for d in boxes]
        # Objects longer than tall (vehicles, bicycles): their box's centre lies measurably off their
        # centre's projection. Both paths aim at the centre's bearing (u); the ground ray at its
        # mid-height too (v), while stereo takes its range from the disparity. Stereo aimed at the raw
        # box centre put the village's truck 0.3 m to the side of the ground's, and the two thin
        # ellipses, at a small angle, fused short.
        uvz = np.array([(d.center_x_px, d.center_y_px, ground + s[2] / 2) for d, s in zip(boxes, sizes)])
        aims = centre_aims(cam, view, uvz, [s if (s[0] + s[1]) / 2 >= s[2] else None for s in sizes])
        grounds = locate_many_on_ground(cam, view, uvz - np.c_[aims, np.zeros(len(boxes))], nz, p.max_range_m)
        stereos: list = [None] * len(boxes)
        if pair is not None:
            seen = {}
            for i, d in enumerate(boxes):
                u, v, w, h = d.center_x_px, d.center_y_px, d.size_x_px, d.size_y_px
                disp = box_disparity(pair[0], pair[1], (u - w / 2, v - h / 2, u + w / 2, v + h / 2), max_disp)
                if disp is not None:
                    seen[i] = (u - aims[i, 0], v, disp)
            if seen:
                for i, m in zip(seen, locate_many_by_disparity(cam, view, list(seen.values()), nz)):
                    length, width, _ = sizes[i]
                    stereos[i] = m and to_centre(m, view[1], (length + width) / 4, abs(length - width) / 4)
        out = []
        for d, size, m_ground, m_stereo in zip(boxes, sizes, grounds, stereos):
            m = fuse(m_stereo, m_ground, view[1])
            if m is None or m.range_m > p.max_range_m:
                self.dropped["detection_not_placed"] += 1
                continue
            self.placed[m.method] += 1
            scale = box_scale(cam, view[1], m, d.size_y_px, size)
            out.append(Observation(m, d.class_id, d.class_name, d.score, scale, cut=_cut(d, dets), length_m=max(size[:2])))
        return out

    # ------------------------------------------------------------ messages

    def tracked_object(self, t: Track) -> TrackedObject:
        x = t.x
        lat = lon = alt = None
        if self.home is not None and self.projection is not None:
            h = self.home.position_m
            lat, lon = self.projection.reproject(float(x[1] - h.y), float(x[0] - h.x))
            alt = self.home.altitude_amsl_m + float(x[2] - h.z)
        return TrackedObject(
            track_id=t.track_id, class_name=t.class_name, class_id=t.class_id, confirmed=t.confirmed,
            position_m=Vector3.from_array(x[:3]), position_covariance_m2=[float(c) for c in t.P[:3, :3].ravel()],
            velocity_mps=Vector3.from_array(x[3:]), first_seen_ns=t.first_seen_ns, last_seen_ns=t.last_seen_ns,
            hits=t.hits, best_score=float(t.best_score), range_m=float(t.range_m),
            latitude_deg=lat, longitude_deg=lon, altitude_amsl_m=alt)

    def _event(self, kind: str, t: Track, stamp_ns: int) -> ObjectEvent:
        return ObjectEvent(header=Header(stamp_ns=stamp_ns, frame_id="map"), event=kind, object=self.tracked_object(t))

    def _result(self, stamp: int, ev, t0: tuple[float, float]) -> FrameResult:
        objs = TrackedObjectArray(header=Header(stamp_ns=stamp, frame_id="map"),
                                  objects=[self.tracked_object(t) for t in self.tracker.tracks])
        events = ([self._event(ObjectEvent.CONFIRMED, t, stamp) for t in ev.confirmed]
                  + [self._event(ObjectEvent.REACQUIRED, t, stamp) for t in ev.reacquired]
                  + [self._event(ObjectEvent.LOST, t, stamp) for t in ev.lost])
        return FrameResult(objs, events, (time.perf_counter() - t0[0]) * 1e3, (time.thread_time() - t0[1]) * 1e3)
