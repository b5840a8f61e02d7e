"""The camera driver's calibration files, written from the real EuRoC MH_01 calibration (the
VI-Sensor's cam0/cam1 intrinsics, radtan distortion and body <- camera extrinsics T_BS) in each
tool's format: Kalibr camchain, OpenCV stereoCalibrate FileStorage, ROS camera_info. Each is read
back into the same camera models; what a file cannot say is refused by name."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from aeroperception.services.camera.calibration import CalibrationError, load
from aeroperception.services.runtime.data import shared_data_dir
from aeroperception.services.runtime.rotations import quat_to_rotmat
from aeroperception.services.vio.euroc import EurocDataset

DATA = shared_data_dir()
MH01 = DATA / "euroc" / "MH_01_clip" if DATA else None
pytestmark = pytest.mark.skipif(MH01 is None or not (MH01 / "mav0").is_dir(), reason="../shared/data absent")


def euroc() -> dict:
    out = {}
    for cam in ("cam0", "cam1"):
        y = yaml.safe_load((MH01 / "mav0" / cam / "sensor.yaml").read_text())
        out[cam] = dict(intr=y["intrinsics"], dist=y["distortion_coefficients"], res=y["resolution"],
                        T_BS=np.array(y["T_BS"]["data"]).reshape(4, 4))
    return out


def pose(info) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = quat_to_rotmat(info.T_body_camera.orientation.to_array())
    t[:3, 3] = info.T_body_camera.position.to_array()
    return t


def k_of(c: dict) -> np.ndarray:
    fu, fv, cu, cv = c["intr"]
    return np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])


def test_a_kalibr_camchain_gives_both_cameras_where_euroc_says_they_sit(tmp_path):
    e = euroc()
    t_c1_c0 = np.linalg.inv(e["cam1"]["T_BS"]) @ e["cam0"]["T_BS"]
    chain = {"cam0": dict(camera_model="pinhole", intrinsics=e["cam0"]["intr"], distortion_model="radtan",
                          distortion_coeffs=e["cam0"]["dist"], resolution=e["cam0"]["res"],
                          T_cam_imu=np.linalg.inv(e["cam0"]["T_BS"]).tolist(), rostopic="/cam0/image_raw"),
             "cam1": dict(camera_model="pinhole", intrinsics=e["cam1"]["intr"], distortion_model="radtan",
                          distortion_coeffs=e["cam1"]["dist"], resolution=e["cam1"]["res"],
                          T_cn_cnm1=t_c1_c0.tolist(), rostopic="/cam1/image_raw")}
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(yaml.safe_dump(chain))
    cal = load(path)
    assert cal.fmt == "kalibr" and cal.t_body_left is not None
    left, right = cal.infos(cal.t_body_left)
    for info, cam in ((left, "cam0"), (right, "cam1")):
        np.testing.assert_allclose(info.K.to_numpy(), k_of(e[cam]))
        np.testing.assert_allclose(info.D.to_numpy(), e[cam]["dist"])
        assert (info.width, info.height) == tuple(e[cam]["res"])
        np.testing.assert_allclose(pose(info), e[cam]["T_BS"], atol=1e-9)
    # the same models the EuRoC reader gives the VIO
    ref_left, ref_right = EurocDataset(MH01).camera_infos()
    np.testing.assert_allclose(pose(right), pose(ref_right), atol=1e-9)


def test_an_opencv_stereo_calibration_places_the_right_camera_from_the_left(tmp_path):
    e = euroc()
    right_T_left = np.linalg.inv(e["cam1"]["T_BS"]) @ e["cam0"]["T_BS"]
    path = tmp_path / "stereo.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 752)
    fs.write("image_height", 480)
    fs.write("M1", k_of(e["cam0"]))
    fs.write("D1", np.array(e["cam0"]["dist"]))
    fs.write("M2", k_of(e["cam1"]))
    fs.write("D2", np.array(e["cam1"]["dist"]))
    fs.write("R", right_T_left[:3, :3])
    fs.write("T", right_T_left[:3, 3].reshape(3, 1))
    fs.release()
    cal = load(path)
    assert cal.fmt == "opencv" and cal.t_body_left is None      # OpenCV does not say where the rig sits
    left, right = cal.infos(e["cam0"]["T_BS"])                 # the mount gives the left camera
    np.testing.assert_allclose(pose(right), e["cam1"]["T_BS"], atol=1e-9)
    np.testing.assert_allclose(right.K.to_numpy(), k_of(e["cam1"]))


def test_ros_camera_info_files_give_a_rectified_pair_its_baseline(tmp_path):
    e = euroc()

    def ost(name: str, tx: float) -> str:
        k = k_of(e["cam0"])
        p = np.hstack([k, [[tx], [0], [0]]])
        return yaml.safe_dump(dict(image_width=752, image_height=480, camera_name=name,
                                   camera_matrix=dict(rows=3, cols=3, data=k.ravel().tolist()),
                                   distortion_model="plumb_bob",
                                   distortion_coefficients=dict(rows=1, cols=5, data=[0.0] * 5),
                                   rectification_matrix=dict(rows=3, cols=3, data=np.eye(3).ravel().tolist()),
                                   projection_matrix=dict(rows=3, cols=4, data=p.ravel().tolist())))
    (tmp_path / "left.yaml").write_text(ost("narrow_stereo/left", 0.0))
    (tmp_path / "right.yaml").write_text(ost("narrow_stereo/right", -458.654 * 0.11))
    cal = load(tmp_path / "left.yaml", right_path=tmp_path / "right.yaml")
    left, right = cal.infos(np.eye(4))
    assert cal.fmt == "ros" and right.header.frame_id == "camera_right_optical"
    np.testing.assert_allclose(pose(right)[:3, 3], [0.11, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("text, words", [
    ("cam0: {camera_model: pinhole, intrinsics: [1, 1, 1, 1], distortion_model: equidistant, "
     "distortion_coeffs: [0, 0, 0, 0], resolution: [10, 10]}", "distortion model 'equidistant' is not read"),
    ("cam0: {camera_model: omni, intrinsics: [1, 1, 1, 1], resolution: [10, 10]}", "camera_model 'omni'"),
    ("cam0: {camera_model: pinhole, intrinsics: [1, 1, 1, 1], distortion_coeffs: [0, 0, 0, 0], resolution: [10, 10]}\n"
     "cam1: {camera_model: pinhole, intrinsics: [1, 1, 1, 1], distortion_coeffs: [0, 0, 0, 0], resolution: [10, 10]}",
     "cam1 has neither T_cn_cnm1 nor T_cam_imu"),
    ("cam0: {camera_model: pinhole, intrinsics: [1, 1, 1, 1], distortion_coeffs: [0, 0, 0, 0], resolution: [10, 10], "
     "T_cam_imu: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}", "T_cam_imu is not a 4x4 rigid transform"),
    ("cam0: {camera_model: pinhole, intrinsics: [1, 1], resolution: [10, 10]}", "not a kalibr calibration"),
    ("a: [unclosed", "not YAML"),
    ("just: a mapping", "neither OpenCV FileStorage, Kalibr camchain nor ROS camera_info"),
])
def test_what_a_file_cannot_say_is_refused_naming_it(tmp_path, text, words):
    path = tmp_path / "cal.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=words):
        load(path)


def test_a_missing_file_and_an_unknown_format_are_refused(tmp_path):
    with pytest.raises(CalibrationError, match="No such file"):
        load(tmp_path / "nope.yaml")
    (tmp_path / "c.yaml").write_text("cam0: {}")
    with pytest.raises(CalibrationError, match="format 'matlab'"):
        load(tmp_path / "c.yaml", "matlab")
