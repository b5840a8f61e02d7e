"""`aero up --profile vehicle --sensors-file FILE`: what a real vehicle carries, where each
sensor sits on it and where its data comes from, turned into the drivers and the perception
services to start with their parameters.

    camera:                         # a camera or stereo pair: the camera driver (services/camera)
      driver: camera
      params: {source: /dev/video0, layout: side_by_side, calibration_path: camchain.yaml}
      mount: {x_m: 0.12, y_m: 0.0, z_m: -0.03, roll_deg: 0, pitch_deg: 0, yaw_deg: 0}
    lidar:                          # a Velodyne / Ouster: the lidar_driver (services/lidar_driver)
      driver: lidar_driver
      params: {device_ip: 192.168.1.201, port: 2368}
      mount: {x_m: 0.0, y_m: 0.0, z_m: 0.1}
    imu: fc                         # the flight controller's IMU, republished by fmu

A sensor whose vendor driver runs on ROS 2 (rmw_zenoh) comes in through ros2bridge instead:

    camera:
      driver: ros2
      topics: {left_image: /zed/left/image_rect, left_info: /zed/left/camera_info,
               right_image: /zed/right/image_rect, right_info: /zed/right/camera_info}
      mount: {x_m: 0.12}            # the left camera (CameraInfo does not say where it sits)
      mount_right: {x_m: 0.12, y_m: -0.12}
    lidar: {driver: ros2, topics: {points: /ouster/points}, mount: {z_m: 0.1}}
    imu: {driver: ros2, topics: {imu: /imu/data}}     # then fmu does not republish the FC's

`mount` is body (FLU) <- sensor, metres and degrees, the sensor's own x along its optical axis or
its forward: the camera driver's mount_* (unless its Kalibr calibration already places it: then no
mount), the lidar service's mount_* for the LiDAR. A camera brings vio (stereo, or klt_mono for
one camera), detector, objects and perception; a LiDAR brings lidar and perception. Relative paths
in `params` are the file's folder's. Decoded strictly: an unknown key, driver or parameter, a value
out of its range or a calibration that does not fit is refused in one line before anything starts.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from aeroperception.tools.common import CliError

MOUNT = ("x_m", "y_m", "z_m", "roll_deg", "pitch_deg", "yaw_deg")
DRIVERS = {"camera": ("camera", "ros2"), "lidar": ("lidar_driver", "ros2")}
# ros2: {section: {topics key: our key}}
ROS2_KEYS = {
    "camera": {"left_image": "sensors/camera/left/image", "left_info": "sensors/camera/left/info",
               "right_image": "sensors/camera/right/image", "right_info": "sensors/camera/right/info"},
    "lidar": {"points": "sensors/lidar/points"},
    "imu": {"imu": "sensors/imu"},
}
PATH_PARAMS = {"source", "source_right", "calibration_path", "calibration_path_right", "metadata_path"}
IMU_SOURCES = ("fc",)


@dataclass
class SensorPlan:
    """The services a sensors file adds (in start order) and the flags each gets."""

    services: list[str] = field(default_factory=list)
    args: dict[str, list[str]] = field(default_factory=dict)
    ros2_inputs: list[str] = field(default_factory=list)       # ros2bridge's inputs: "topic=key"

    def add(self, service: str, params: dict[str, Any] | None = None) -> None:
        if service not in self.services:
            self.services.append(service)
        flags = self.args.setdefault(service, [])
        for k, v in (params or {}).items():
            flags += ["--param", f"{k}={_text(v)}"]


def _text(v: Any) -> str:
    return ("true" if v else "false") if isinstance(v, bool) else str(v)


def plan_sensors(args) -> SensorPlan:
    """The sensors file's plan (empty without one); refused with a profile whose simulator renders
    the sensors (it would be a second source on the same keys)."""
    from .launch import load_profiles

    path = getattr(args, "sensors_file", None)
    if path is None:
        return SensorPlan()
    if "sim" in load_profiles().get(args.profile, {}).get("services", ["sim"]):
        raise CliError(f"--sensors-file: profile {args.profile} simulates its sensors; a real vehicle's sensors "
                       "go with --profile vehicle")
    return load(path)


def load(path: str | Path) -> SensorPlan:
    """The plan for a sensors file; CliError (one line, naming the file and the field) when it
    cannot be honoured in full."""
    path = Path(path)
    where = f"--sensors-file {path}"
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as e:
        raise CliError(f"{where}: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise CliError(f"{where}: not YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict) or not data:
        raise CliError(f"{where}: expected a mapping of camera / lidar / imu")
    unknown = sorted(set(data) - {"camera", "lidar", "imu"})
    if unknown:
        raise CliError(f"{where}: unknown key {unknown[0]!r} (camera, lidar, imu)")
    plan = SensorPlan()
    imu = data.get("imu", "fc")
    if isinstance(imu, dict):
        sec = _section({"imu": imu}, "imu", where, drivers=("ros2",), keys=("driver", "topics"))
        _ros2_topics(plan, sec, "imu", f"{where}: imu")
        plan.add("fmu", {"publish_imu": False})              # one IMU on sensors/imu
    elif imu not in IMU_SOURCES:
        raise CliError(f"{where}: imu: {imu!r}: fc (the flight controller's IMU via fmu) or "
                       "{driver: ros2, topics: {imu: TOPIC}}")
    if "camera" in data:
        sec = _section(data, "camera", where)
        (_camera_ros2 if sec["driver"] == "ros2" else _camera)(plan, sec, path.parent, f"{where}: camera")
    if "lidar" in data:
        sec = _section(data, "lidar", where)
        (_lidar_ros2 if sec["driver"] == "ros2" else _lidar)(plan, sec, path.parent, f"{where}: lidar")
    if plan.ros2_inputs:
        plan.add("ros2bridge", {"inputs": ",".join(plan.ros2_inputs)})
    if any(s in plan.services for s in ("vio", "lidar")):
        plan.add("perception")
    return plan


def _section(data: dict, name: str, where: str, drivers: tuple[str, ...] = (), keys: tuple[str, ...] = ()) -> dict:
    sec = data[name]
    drivers = drivers or DRIVERS[name]
    if not isinstance(sec, dict):
        raise CliError(f"{where}: {name}: expected a mapping with driver, ...")
    if sec.get("driver") not in drivers:
        raise CliError(f"{where}: {name}: driver {sec.get('driver')!r}: one of {', '.join(drivers)}")
    keys = keys or (("driver", "topics", "mount") + (("mount_right",) if name == "camera" else ())
                    if sec["driver"] == "ros2" else ("driver", "params", "mount"))
    unknown = sorted(set(sec) - set(keys))
    if unknown:
        raise CliError(f"{where}: {name}: unknown key {unknown[0]!r} for driver {sec['driver']} ({', '.join(keys)})")
    return sec


def _ros2_topics(plan: SensorPlan, sec: dict, name: str, where: str) -> dict[str, str]:
    """The section's ROS topics, each to our key, added to ros2bridge's inputs."""
    topics = sec.get("topics")
    allowed = ROS2_KEYS[name]
    if not isinstance(topics, dict) or not topics:
        raise CliError(f"{where}: topics: expected {{{', '.join(allowed)}: ROS topic}}")
    unknown = sorted(set(topics) - set(allowed))
    if unknown:
        raise CliError(f"{where}: topics: unknown key {unknown[0]!r} ({', '.join(allowed)})")
    for k, topic in topics.items():
        if not isinstance(topic, str) or not topic or any(c in topic for c in ",= "):
            raise CliError(f"{where}: topics: {k}: {topic!r} is not a ROS topic name")
        plan.ros2_inputs.append(f"{topic}={allowed[k]}")
    return topics


def _params(sec: dict, contract, folder: Path, where: str) -> dict[str, Any]:
    """The driver's parameters, each checked against its contract (name, type, range, choices)."""
    from aeroperception.services.runtime.params import ParamError, ParamSet

    raw = sec.get("params") or {}
    if not isinstance(raw, dict):
        raise CliError(f"{where}: params: expected a mapping of the driver's parameters")
    params = {k: (str((folder / v).resolve()) if k in PATH_PARAMS and isinstance(v, str) and v
                  and not v.startswith(("/dev/", "gst:")) and not v.isdigit() and not Path(v).is_absolute() else v)
              for k, v in raw.items()}
    mounted = sorted(k for k in params if k.startswith("mount_"))
    if mounted:
        raise CliError(f"{where}: params: {mounted[0]}: give where the sensor sits as mount: {{...}}")
    try:
        ParamSet.from_declarations(contract.PARAMS).update(params)
    except ParamError as e:
        raise CliError(f"{where}: params: {e}") from None
    return params


def _mount(sec: dict, where: str) -> dict[str, float]:
    """mount_* parameters: all six when the file gives a mount (a key left out is 0), none when not."""
    m = sec.get("mount")
    if m is None:
        return {}
    if not isinstance(m, dict):
        raise CliError(f"{where}: mount: expected {{{', '.join(MOUNT)}}}")
    unknown = sorted(set(m) - set(MOUNT))
    if unknown:
        raise CliError(f"{where}: mount: unknown key {unknown[0]!r} ({', '.join(MOUNT)})")
    out = {f"mount_{k}": 0.0 for k in MOUNT}
    for k, v in m.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise CliError(f"{where}: mount: {k}: {v!r} is not a number")
        out[f"mount_{k}"] = float(v)
    return out


def _camera(plan: SensorPlan, sec: dict, folder: Path, where: str) -> None:
    from aeroperception.services.camera import contract
    from aeroperception.services.camera.calibration import CalibrationError, load as load_calibration

    params = _params(sec, contract, folder, where)
    mount = _mount(sec, where)
    layout = params.get("layout", "mono")
    if not params.get("calibration_path"):
        raise CliError(f"{where}: params: calibration_path: the perception it brings needs the camera model")
    try:
        cal = load_calibration(params["calibration_path"], params.get("calibration_format", "auto"),
                               params.get("calibration_path_right") or None)
    except CalibrationError as e:
        raise CliError(f"{where}: params: calibration_path: {e}") from None
    if (cal.right is not None) != (layout != "mono"):
        raise CliError(f"{where}: params: calibration_path: {'a stereo' if cal.right is not None else 'a mono'} "
                       f"calibration for layout {layout}")
    if cal.t_body_left is not None and any(mount.values()):
        raise CliError(f"{where}: mount: the calibration ({cal.fmt}) already places the camera on the body "
                       "(T_cam_imu): leave mount out")
    plan.add("camera", params | {k: v for k, v in mount.items() if v})
    stereo = layout != "mono"
    plan.add("vio", {} if stereo else {"strategy": "klt_mono"})
    plan.add("detector")
    plan.add("objects", {} if stereo else {"stereo": False})


def _lidar(plan: SensorPlan, sec: dict, folder: Path, where: str) -> None:
    from aeroperception.services.lidar_driver import contract

    params = _params(sec, contract, folder, where)
    plan.add("lidar_driver", params)
    plan.add("lidar", _mount(sec, where))


def _camera_ros2(plan: SensorPlan, sec: dict, _folder: Path, where: str) -> None:
    topics = _ros2_topics(plan, sec, "camera", where)
    if "left_image" not in topics or "left_info" not in topics:
        raise CliError(f"{where}: topics: left_image and left_info are needed (the camera model too)")
    stereo = "right_image" in topics
    if stereo != ("right_info" in topics):
        raise CliError(f"{where}: topics: right_image and right_info go together")
    if stereo and sec.get("mount_right") is None:
        raise CliError(f"{where}: mount_right: where the right camera sits (CameraInfo does not say)")
    if not stereo and "mount_right" in sec:
        raise CliError(f"{where}: mount_right: a mono camera (no right_image topic) would ignore it")
    mounts = {f"left_{k}": v for k, v in _mount(sec, where).items()}
    if stereo:
        mounts |= {f"right_{k}": v for k, v in _mount({"mount": sec["mount_right"]}, f"{where}: mount_right").items()}
    plan.add("ros2bridge", mounts)
    plan.add("vio", {} if stereo else {"strategy": "klt_mono"})
    plan.add("detector")
    plan.add("objects", {} if stereo else {"stereo": False})


def _lidar_ros2(plan: SensorPlan, sec: dict, _folder: Path, where: str) -> None:
    _ros2_topics(plan, sec, "lidar", where)
    plan.add("lidar", _mount(sec, where))
