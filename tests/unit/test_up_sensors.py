"""`aero up --profile vehicle --sensors-file FILE`: a vehicle's sensors file decoded strictly into
the drivers and perception services to start and their flags; what it cannot honour is refused
in one line naming the field, before anything starts."""
from __future__ import annotations

import argparse

import pytest
import yaml

from aeroperception.services.runtime.data import shared_data_dir
from aeroperception.tools.cli.up import sensors
from aeroperception.tools.common import CliError
from aerotest import euroc_camchain

DATA = shared_data_dir()
MAV = DATA / "euroc" / "V1_01_easy_start" / "mav0" if DATA else None
pytestmark = pytest.mark.skipif(MAV is None or not MAV.is_dir(), reason="../shared/data absent")


def camchain(folder, stereo=True) -> str:
    euroc_camchain(MAV, folder / "camchain.yaml", stereo)
    return "camchain.yaml"


def plan(tmp_path, data):
    path = tmp_path / "sensors.yaml"
    path.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return sensors.load(path)


def native(tmp_path, **camera):
    cal = camchain(tmp_path)
    return {"camera": {"driver": "camera", "params": {"source": "/dev/video0", "layout": "side_by_side",
                                                      "calibration_path": cal, **camera}},
            "lidar": {"driver": "lidar_driver", "params": {"device_ip": "192.168.1.201"}, "mount": {"z_m": 0.1}},
            "imu": "fc"}


def flags(p, service) -> dict[str, str]:
    a = p.args[service]
    return dict(a[i + 1].split("=", 1) for i in range(0, len(a), 2))


def test_native_drivers_bring_the_perception_they_feed_with_their_mounts(tmp_path):
    p = plan(tmp_path, native(tmp_path))
    assert p.services == ["camera", "vio", "detector", "objects", "lidar_driver", "lidar", "perception"]
    cam = flags(p, "camera")
    assert cam["calibration_path"] == str((tmp_path / "camchain.yaml").resolve())   # relative to the file
    assert cam["source"] == "/dev/video0" and cam["layout"] == "side_by_side"
    assert flags(p, "lidar") == {"mount_x_m": "0.0", "mount_y_m": "0.0", "mount_z_m": "0.1", "mount_roll_deg": "0.0",
                                 "mount_pitch_deg": "0.0", "mount_yaw_deg": "0.0"}
    assert flags(p, "lidar_driver") == {"device_ip": "192.168.1.201"}
    assert "ros2bridge" not in p.services


def test_a_mono_camera_gets_mono_vio_and_objects(tmp_path):
    cal = camchain(tmp_path, stereo=False)
    p = plan(tmp_path, {"camera": {"driver": "camera", "params": {"source": "0", "calibration_path": cal}}})
    assert flags(p, "vio") == {"strategy": "klt_mono"} and flags(p, "objects") == {"stereo": "false"}
    assert flags(p, "camera")["source"] == "0"


def test_ros2_sensors_come_through_the_bridge_and_the_fc_imu_steps_aside(tmp_path):
    p = plan(tmp_path, {
        "camera": {"driver": "ros2", "topics": {"left_image": "/zed/left/image_rect", "left_info": "/zed/left/camera_info",
                                                "right_image": "/zed/right/image_rect", "right_info": "/zed/right/camera_info"},
                   "mount": {"x_m": 0.12}, "mount_right": {"x_m": 0.12, "y_m": -0.12}},
        "lidar": {"driver": "ros2", "topics": {"points": "/ouster/points"}, "mount": {"z_m": 0.1}},
        "imu": {"driver": "ros2", "topics": {"imu": "/imu/data"}}})
    bridge = flags(p, "ros2bridge")
    assert bridge["inputs"].split(",") == [
        "/imu/data=sensors/imu", "/zed/left/image_rect=sensors/camera/left/image",
        "/zed/left/camera_info=sensors/camera/left/info", "/zed/right/image_rect=sensors/camera/right/image",
        "/zed/right/camera_info=sensors/camera/right/info", "/ouster/points=sensors/lidar/points"]
    assert bridge["left_mount_x_m"] == "0.12" and bridge["right_mount_y_m"] == "-0.12"
    assert flags(p, "fmu") == {"publish_imu": "false"}
    assert {"vio", "detector", "objects", "lidar", "perception"} <= set(p.services)


@pytest.mark.parametrize("change, words", [
    (lambda d: d.update(radar={}), "unknown key 'radar' (camera, lidar, imu)"),
    (lambda d: d["camera"].update(driver="zed"), "camera: driver 'zed': one of camera, ros2"),
    (lambda d: d["camera"]["params"].update(rate_hz=500.0), "camera: params: "),
    (lambda d: d["camera"]["params"].update(fps=30), "camera: params: unknown parameter 'fps'"),
    (lambda d: d["camera"]["params"].update(mount_x_m=0.1), "give where the sensor sits as mount"),
    (lambda d: d["camera"].update(mount={"x_m": 0.1}), "already places the camera on the body (T_cam_imu)"),
    (lambda d: d["camera"]["params"].update(layout="mono"), "a stereo calibration for layout mono"),
    (lambda d: d["camera"]["params"].pop("calibration_path"), "calibration_path: the perception it brings needs"),
    (lambda d: d["lidar"].update(mount={"z_m": "high"}), "lidar: mount: z_m: 'high' is not a number"),
    (lambda d: d["lidar"].update(mount={"height": 1}), "lidar: mount: unknown key 'height'"),
    (lambda d: d["lidar"]["params"].update(port=70000), "lidar: params: "),
    (lambda d: d["lidar"].update(topics={}), "unknown key 'topics' for driver lidar_driver"),
    (lambda d: d.update(imu="vectornav"), "imu: 'vectornav': fc"),
])
def test_what_a_sensors_file_cannot_have_honoured_is_refused_naming_it(tmp_path, change, words):
    data = native(tmp_path)
    change(data)
    with pytest.raises(CliError, match=None) as e:
        plan(tmp_path, data)
    assert words in str(e.value) and "\n" not in str(e.value), str(e.value)


@pytest.mark.parametrize("data, words", [
    ("camera: [unclosed", "not YAML"),
    ("[]", "expected a mapping of camera / lidar / imu"),
    ({"camera": {"driver": "ros2", "topics": {"left_image": "/a"}}}, "left_image and left_info are needed"),
    ({"camera": {"driver": "ros2", "topics": {"left_image": "/a", "left_info": "/b", "right_image": "/c",
                                              "right_info": "/d"}}}, "mount_right: where the right camera sits"),
    ({"lidar": {"driver": "ros2", "topics": {"points": "/a b"}}}, "is not a ROS topic name"),
])
def test_malformed_files_are_refused(tmp_path, data, words):
    with pytest.raises(CliError) as e:
        plan(tmp_path, data)
    assert words in str(e.value), str(e.value)


def test_a_simulated_profile_refuses_a_sensors_file(tmp_path):
    args = argparse.Namespace(sensors_file=str(tmp_path / "s.yaml"), profile="sim")
    with pytest.raises(CliError, match="profile sim simulates its sensors"):
        sensors.plan_sensors(args)
    with pytest.raises(CliError, match="profile px4 simulates its sensors"):
        sensors.plan_sensors(argparse.Namespace(sensors_file="x", profile="px4"))
    assert sensors.plan_sensors(argparse.Namespace(sensors_file=None, profile="sim")).services == []
