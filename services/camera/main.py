"""Process shell: the capture loop on its own thread, frames and camera models onto Zenoh."""
from __future__ import annotations

import math
import threading

import numpy as np

from aeroperception.schemas import CameraInfo, DiagnosticStatus, Header, Image
from aeroperception.services.lib.optical import r_body_optical
from aeroperception.services.runtime import Health, ParamError, Service, run

from . import contract
from .calibration import CalibrationError, load
from .driver import CameraConfig, CameraDriver, Frame

LEVEL = {"streaming": DiagnosticStatus.OK, "waiting": DiagnosticStatus.WARN, "opening": DiagnosticStatus.WARN,
         "stalled": DiagnosticStatus.WARN, "ended": DiagnosticStatus.WARN, "failed": DiagnosticStatus.ERROR}


class CameraService(Service):
    """A camera (or stereo pair) into sensors/camera/{left,right}/image + info."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = CameraConfig

    def bind_selection(self) -> dict:
        """The sides the layout has; camera models only with a calibration (served and published
        only when there is one to give)."""
        c = self.cfg
        sides = ["left"] if c.layout == "mono" else ["left", "right"]
        infos = [f"sensors/camera/{s}/info" for s in sides] if c.calibration_path else []
        return dict(outputs=[f"sensors/camera/{s}/image" for s in sides] + infos, services=infos)

    def start(self) -> None:
        c = self.cfg
        try:
            self.driver = CameraDriver(c)
        except ValueError as e:
            raise ParamError(str(e)) from None
        self.infos: dict[str, CameraInfo] = {}
        if c.calibration_path:
            self.infos = self._load_infos(c)
        elif c.calibration_path_right:
            raise ParamError("calibration_path_right is set without calibration_path: it would be ignored")
        self.node.every(1.0, self._publish_infos, name="info")
        self.reader = threading.Thread(target=self._loop, name="camera-capture", daemon=True)
        self.reader.start()
        self.log.info("capturing", source=c.source, layout=c.layout, calibrated=bool(self.infos))

    def _load_infos(self, c: CameraConfig) -> dict[str, CameraInfo]:
        try:
            cal = load(c.calibration_path, c.calibration_format, c.calibration_path_right or None,
                       (c.width, c.height) if c.width and c.height else None)
        except CalibrationError as e:
            raise ParamError(f"calibration_path: {e}") from None
        mounted = [n for n in contract.MOUNT_PARAMS if getattr(c, n) != 0.0]
        if cal.t_body_left is not None:
            if mounted:
                raise ParamError(f"{', '.join(mounted)}: the calibration ({cal.fmt}) already places the camera "
                                 "on the body (T_cam_imu); leave the mount parameters at 0")
            t_body_left = cal.t_body_left
        else:
            t_body_left = np.eye(4)
            t_body_left[:3, :3] = r_body_optical(*np.radians([c.mount_roll_deg, c.mount_pitch_deg, c.mount_yaw_deg]))
            t_body_left[:3, 3] = [c.mount_x_m, c.mount_y_m, c.mount_z_m]
        left, right = cal.infos(t_body_left)
        if (right is None) != (c.layout == "mono"):
            raise ParamError(f"calibration_path: {'a stereo' if right is not None else 'a mono'} calibration for "
                             f"layout {c.layout}")
        return {"left": left} | ({"right": right} if right is not None else {})

    def on_config(self, cfg: CameraConfig) -> None:
        self.driver.cfg = cfg

    def stop(self) -> None:
        self.node.stop_event.set()
        if hasattr(self, "reader"):
            self.reader.join(2.0)
        if hasattr(self, "driver"):
            self.driver.close()

    # ------------------------------------------------------------ capture thread

    def _loop(self) -> None:
        stop = self.node.stop_event
        while not stop.is_set():
            wait = self.driver.wait_s()
            if wait > 0:
                stop.wait(min(wait, 0.1) if math.isfinite(wait) else 0.1)
                continue
            frame = self.driver.poll()
            if frame is not None:
                self.node.run_callback("camera", self._publish, frame)

    def _publish(self, f: Frame) -> None:
        enc = self.cfg.encoding
        for side, pixels in (("left", f.left), ("right", f.right)):
            if pixels is not None:
                self.io[f"sensors/camera/{side}/image"].publish(Image.from_numpy(
                    pixels, enc, Header(stamp_ns=f.stamp_ns, frame_id=f"camera_{side}_optical")))

    def _publish_infos(self) -> None:
        for side, info in self.infos.items():
            info.header.stamp_ns = self.node.now_ns()
            self.io[f"sensors/camera/{side}/info"].publish(info)

    def on_sensors_camera_left_info(self, _req) -> CameraInfo:
        return self.infos["left"]

    def on_sensors_camera_right_info(self, _req) -> CameraInfo:
        return self.infos["right"]

    def health(self) -> Health:
        d = self.driver
        values = dict(sorted(d.counts.items())) | {"state": d.state, "source": self.cfg.source}
        level = LEVEL.get(d.state, DiagnosticStatus.WARN)
        if d.state == "streaming" and not self.infos:
            return Health(DiagnosticStatus.WARN, "uncalibrated: images only, no camera model (calibration_path)", values)
        msg = d.why or {"streaming": f"{d.counts['frames']} frames", "waiting": "opened: waiting for the first frame",
                        "opening": "opening"}.get(d.state, d.state)
        return Health(level, msg, values)


def main(argv=None) -> int:
    return run(CameraService, argv)
