"""Camera and LiDAR rendering in processes of their own.

Why processes: the LiDAR's Open3D RaycastingScene.cast_rays holds the GIL for the whole cast
(measured: a spinning thread got 7 % of its speed while a render ran: in the simulator's process
that starved the 400 Hz physics loop and the IMU/clock publishers). The cameras' numba kernels
release it, but a child process can run at a lower priority than the physics (RENDER_NICE).
The parent sends the exact truth of each frame's stamp over a pipe; the child keeps only the
newest request (older ones are counted as skipped), renders, publishes on Zenoh with its own
session, and reports each frame's render time back for the sim's diagnostics.

Only what someone subscribes to is rendered and published (Zenoh's matching status, checked per
frame): with no viewer the truth boxes and LiDAR labels cost nothing, a right camera nobody reads
is not rendered, and a frame nobody listens to at all is reported as unwatched, not rendered.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from aeroperception.schemas import Detection2D, Detection2DArray, Header, Image, NDArray, PointCloud

from .contract import CAMERAS, RENDERED

RATE_SLACK = 0.75  # a camera slower than the frame requests (the down camera) renders once 75 % of its period passed


class _CameraRenderer:
    def __init__(self, io, sensors, scenario):
        self.stereo, self.has_targets = sensors.stereo, bool(scenario.targets)
        built = sensors.cameras()
        unknown = sorted(set(built) - set(CAMERAS))
        if unknown:
            raise RuntimeError(f"camera {unknown[0]} is built but not declared in services/sim/contract.py OUTPUTS")
        self.cameras = {name: (cam, io[f"sensors/camera/{name}/image"]) for name, cam in built.items()}
        self.last_ns: dict[str, int] = {}
        self.request_hz = max((cam.rate_hz for cam in built.values()), default=0.0)   # the sim requests at this rate
        self.boxes = io["sim/truth/boxes"]
        # Compile the camera kernels (or load them from numba's cache, ~0.7 s CPU) before the child
        # says ready, not while the first frame someone waits for is due.
        for cam, _pub in list(self.cameras.values())[:1]:
            cam.render((np.zeros(3), (1.0, 0.0, 0.0, 0.0)))

    def _due(self, name: str, rate_hz: float, stamp_ns: int) -> bool:
        if rate_hz >= self.request_hz:
            return True
        last = self.last_ns.get(name)
        if last is not None and 0 <= stamp_ns - last < RATE_SLACK * 1e9 / rate_hz:
            return False
        self.last_ns[name] = stamp_ns
        return True

    def __call__(self, truth, stamp_ns: int, blackout: bool = False) -> bool:
        """Render and publish what is subscribed; False when nothing was."""
        from .sensors.truth_boxes import project_targets

        want = [(cam, pub) for name, (cam, pub) in self.cameras.items()
                if pub.matched and self._due(name, cam.rate_hz, stamp_ns)]
        want_boxes = self.has_targets and self.stereo is not None and self.boxes.matched
        if not (want or want_boxes):
            return False
        for cam, pub in want:
            # the SIM_CAM_BLACKOUT fault: frames keep coming, all black
            image = np.zeros((cam.height, cam.width), np.uint8) if blackout else cam.render(truth)
            encoding = "mono8" if image.ndim == 2 else "rgb8"
            pub.publish(Image.from_numpy(image, encoding, Header(stamp_ns=stamp_ns, frame_id=cam.frame_id)))
        if want_boxes:
            header = Header(stamp_ns=stamp_ns, frame_id=self.stereo.left.frame_id)
            info = self.stereo.infos()[0]
            dets = [Detection2D(center_x_px=(b.bbox_xyxy_px[0] + b.bbox_xyxy_px[2]) / 2,
                                center_y_px=(b.bbox_xyxy_px[1] + b.bbox_xyxy_px[3]) / 2,
                                size_x_px=b.bbox_xyxy_px[2] - b.bbox_xyxy_px[0],
                                size_y_px=b.bbox_xyxy_px[3] - b.bbox_xyxy_px[1],
                                class_id=b.class_id, class_name=b.class_name, score=b.visible_fraction)
                    for b in project_targets(self.stereo.left, truth)]
            self.boxes.publish(Detection2DArray(header=header, detections=dets,
                                                image_width=info.width, image_height=info.height))
        return True


class _LidarRenderer:
    def __init__(self, io, sensors, scenario):
        self.lidar = sensors.lidar
        self.lidar.compile()   # as the cameras: the kernel ready before the child says ready
        self.points = io["sensors/lidar/points"]
        self.labels = io["sim/truth/lidar_labels"]

    def __call__(self, truth, stamp_ns: int, blackout: bool = False) -> bool:
        """Render and publish what is subscribed; False when nothing was."""
        want_points, want_labels = self.points.matched, self.labels.matched
        if not (want_points or want_labels):
            return False
        scan = self.lidar.scan(truth, stamp_ns=stamp_ns)
        header = Header(stamp_ns=stamp_ns, frame_id=scan.frame_id)
        points = NDArray.from_numpy(scan.points_m.astype(np.float32, copy=False))
        if want_points:
            self.points.publish(PointCloud(header=header, points=points))
        if want_labels:
            self.labels.publish(PointCloud(header=header, points=points, labels=NDArray.from_numpy(scan.labels)))
        return True


RENDERERS = {"camera": _CameraRenderer, "lidar": _LidarRenderer}
# Rendering must never delay the control hot path: a realtime sim passes its policy to us at
# spawn, so drop it and run nicer than everything `aero up` starts (tools/profiles.yaml).
RENDER_NICE = 10
MAX_QUEUED = 4   # requests the parent lets wait in the pipe before skipping frames itself


def _child_main(sensor: str, scenario_ref: str, node_kwargs: dict, conn) -> None:
    """Entry point of the render process (spawned: no inherited Zenoh state)."""
    from aeroperception.services.runtime import Node

    from . import contract
    from aeroperception.services.runtime.supervision import lower_own_priority

    lower_own_priority(RENDER_NICE)  # before the Zenoh session starts its threads

    from .sensors.rig import build_sensors
    from .world.scenario import load_scenario

    node = Node(f"sim_{sensor}", **node_kwargs)
    if not node.connect(max_wait_s=15):
        conn.send(("error", "no Zenoh router"))
        return
    try:
        scenario = load_scenario(scenario_ref)
        # this process's part of the simulator's contract: the keys it renders (contract.RENDERED)
        io = node.bind(contract, None, inputs=(), outputs=RENDERED[sensor], services=())
        render = RENDERERS[sensor](io, build_sensors(scenario), scenario)
        conn.send(("ready", os.getpid()))
        parent = os.getppid()
        while True:
            if not conn.poll(0.5):
                if os.getppid() != parent:  # the sim died: do not linger
                    return
                continue
            request, skipped = None, 0
            while conn.poll():
                msg = conn.recv()
                if msg is None:
                    return
                skipped += request is not None
                request = msg
            truth, stamp_ns, blackout = request
            t0 = time.perf_counter()
            try:
                watched = render(truth, stamp_ns, blackout)
                conn.send(("frame", (time.perf_counter() - t0) * 1e3, skipped, None, watched))
            except Exception as e:  # noqa: BLE001 - keep rendering, report
                conn.send(("frame", (time.perf_counter() - t0) * 1e3, skipped, f"{type(e).__name__}: {e}", True))
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        return
    finally:
        node.close()


class RenderProcess:
    """Parent side: request(truth, stamp) never blocks the physics; stats for diagnostics."""

    def __init__(self, name: str, scenario_ref: str, node_kwargs: dict[str, Any]):
        self.name = name
        self.requested = self.rendered = self.skipped = self.errors = 0
        self.unwatched = 0      # frames due while nobody subscribed to anything this renderer makes
        self.watched = True     # the last frame had a subscriber (achieved_hz counts watched frames only)
        self.error, self.error_wall = "", 0.0
        self.render_ms: deque[float] = deque(maxlen=100)
        self.done_wall: deque[float] = deque(maxlen=50)
        self.ready = False      # the child said "ready": it reads requests from now on
        self._queued = 0        # requests sent that the child has not answered (rendered or skipped)
        ctx = mp.get_context("spawn")
        self._conn, child_conn = ctx.Pipe(duplex=True)
        self.proc = ctx.Process(target=_child_main, args=(name, scenario_ref, node_kwargs, child_conn),
                                name=f"sim-{name}", daemon=True)
        self.proc.start()
        child_conn.close()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, name=f"sim-{name}-stats", daemon=True)
        self._reader.start()

    def request(self, truth, stamp_ns: int, blackout: bool = False) -> None:
        """Queue a frame; skipped (counted) until the child is ready and while it is MAX_QUEUED
        behind: the pipe then never fills, so send() never blocks the physics thread (a child
        still starting up at load 20 once filled it in ~8 s and the vehicle's MAVLink stopped)."""
        self.requested += 1
        try:
            with self._send_lock:
                if not self.ready or self._queued >= MAX_QUEUED:
                    self.skipped += 1
                    return
                self._queued += 1
                self._conn.send((truth, stamp_ns, blackout))
        except (BrokenPipeError, OSError):
            self.errors += 1
            self.error, self.error_wall = "render process gone", time.monotonic()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                if not self._conn.poll(0.5):
                    continue
                kind, *rest = self._conn.recv()
            except (EOFError, OSError):
                return
            if kind == "ready":
                self.ready = True
            if kind == "frame":
                ms, skipped, err, watched = rest
                with self._send_lock:
                    self._queued = max(0, self._queued - 1 - skipped)
                self.skipped += skipped
                if err:
                    self.errors += 1
                    self.error, self.error_wall = err, time.monotonic()
                    continue
                if not watched:
                    self.unwatched += 1
                    if self.watched:            # the rate restarts with the next watched frame
                        self.watched = False
                        self.done_wall.clear()
                    continue
                self.watched = True
                self.done_wall.append(time.monotonic())
                self.render_ms.append(ms)
                self.rendered += 1
            elif kind == "error":
                self.errors += 1
                self.error, self.error_wall = rest[0], time.monotonic()

    def achieved_hz(self, speed: float) -> float:
        """Frames per sim second over the recent window (0 when it stopped delivering)."""
        if len(self.done_wall) < 2:
            return 0.0
        first, last, n = self.done_wall[0], self.done_wall[-1], len(self.done_wall) - 1
        span = last - first
        if time.monotonic() - last > 2.0 * span / n:
            span = time.monotonic() - first
        return n / span / max(speed, 1e-9) if span > 0 else 0.0

    def stop(self, timeout_s: float = 1.5) -> None:
        self._stop.set()
        try:
            with self._send_lock:
                self._conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self.proc.join(timeout_s)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(0.5)
        self._conn.close()
