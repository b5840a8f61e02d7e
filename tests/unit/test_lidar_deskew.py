"""Deskewing a sweep with the vehicle's motion, on the geometry of a real VLP-16 rotation: the
captured points are the world as the sensor saw it at the scan's stamp; the same world measured
by a sensor moving at 10 m/s and turning at 1 rad/s (each point at its own real firing time) is
smeared by up to a metre, and deskew() brings every point back within a centimetre."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.schemas import Header, Quaternion, Vector3, VehicleState
from aeroperception.services.lib.lidar.deskew import Mount, deskew
from aeroperception.services.lib.lidar.pcap import read_udp
from aeroperception.services.lib.lidar.velodyne import VelodyneDecoder
from aeroperception.services.lib.pose_history import PoseHistory
from aeroperception.services.runtime.data import shared_data_dir
from aeroperception.services.runtime.rotations import quat_from_euler, quat_from_rotmat, quat_to_rotmat

DATA = shared_data_dir()
VLP16 = DATA / "lidar_pcap" / "velodyne" / "vlp16_velodyne_example.pcap" if DATA else None
STAMP_NS = 1_000_000_000_000
MOUNT = Mount(quat_to_rotmat(quat_from_euler(0.0, np.radians(20.0), np.radians(90.0))), np.array([0.1, 0.0, -0.1]))
V_MPS, YAW_RATE = np.array([10.0, 2.0, 0.5]), 1.0


@pytest.fixture(scope="module")
def sweep() -> tuple[np.ndarray, np.ndarray]:
    """The capture's points (sensor frame) and their firing times after the first (s)."""
    if VLP16 is None or not VLP16.is_file():
        pytest.skip("../shared/data/lidar_pcap absent")
    dec = VelodyneDecoder()
    parts = [dec.decode(d.payload) for d in read_udp(VLP16) if d.dst[1] == 2368]
    xyz = np.concatenate([p.xyz_m for p in parts])
    t = np.concatenate([(p.stamp_us - parts[0].stamp_us) * 1e-6 + p.time_offset_s for p in parts])
    keep = t <= 0.1                          # one 10 Hz sweep
    return xyz[keep], t[keep]


def pose(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The vehicle's (R_world_body, position) t_s after the stamp: moving and turning."""
    return quat_to_rotmat(quat_from_euler(0.0, 0.0, 0.3 + YAW_RATE * t_s)), np.array([5.0, -3.0, 10.0]) + V_MPS * t_s


def history(step_s: float = 0.02, span=(-0.1, 0.25)) -> PoseHistory:
    h = PoseHistory()
    for t in np.arange(span[0], span[1], step_s):
        r, p = pose(float(t))
        h.add(VehicleState(header=Header(stamp_ns=STAMP_NS + int(round(t * 1e9))), position_m=Vector3.from_array(p),
                           orientation=Quaternion.from_array(quat_from_rotmat(r))))
    return h


def skewed(xyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    """What the moving sensor measures: each world point in the sensor frame at its firing time."""
    r0, p0 = pose(0.0)
    world = (r0 @ MOUNT.r_body_sensor @ xyz.T).T + p0 + r0 @ MOUNT.t_body_sensor
    out = np.empty_like(xyz)
    for i, (w, ti) in enumerate(zip(world, t)):
        r, p = pose(float(ti))
        out[i] = (r @ MOUNT.r_body_sensor).T @ (w - p - r @ MOUNT.t_body_sensor)
    return out


def test_a_moving_sweep_is_brought_back_to_its_stamp_within_a_centimetre(sweep):
    xyz, t = sweep
    measured = skewed(xyz, t)
    smear = np.linalg.norm(measured - xyz, axis=1)
    assert len(xyz) > 20_000 and smear.max() > 0.9          # the motion smears the far end by ~1 m
    out, why = deskew(measured, t, STAMP_NS, history(), MOUNT)
    assert why == "" and out is not None
    err = np.linalg.norm(out - xyz, axis=1)
    assert err.max() < 0.01, (err.max(), smear.max())


def test_a_still_vehicle_leaves_the_points_as_measured(sweep):
    xyz, t = sweep
    h = PoseHistory()
    for k in range(-5, 15):
        h.add(VehicleState(header=Header(stamp_ns=STAMP_NS + k * 20_000_000), position_m=Vector3(x=1.0, y=2.0, z=3.0)))
    out, why = deskew(xyz, t, STAMP_NS, h, MOUNT)
    assert why == "" and np.allclose(out, xyz, atol=1e-9)


@pytest.mark.parametrize("span, words", [
    ((0.05, 0.3), "no vehicle pose at the scan's stamp"),
    ((-0.1, 0.04), "no vehicle pose"),
])
def test_poses_that_do_not_cover_the_sweep_are_said_not_guessed(sweep, span, words):
    xyz, t = sweep
    out, why = deskew(xyz, t, STAMP_NS, history(span=span), MOUNT, tolerance_s=0.02)
    assert out is None and words in why


def test_garbage_time_offsets_are_refused():
    xyz = np.zeros((3, 3), np.float32)
    assert deskew(xyz, np.array([0.0, np.nan, 0.1]), STAMP_NS, history(), MOUNT)[0] is None
    assert "not one sweep" in deskew(xyz, np.array([0.0, 0.05, 5.0]), STAMP_NS, history(), MOUNT)[1]
    assert "one finite per point" in deskew(xyz, np.zeros(2), STAMP_NS, history(), MOUNT)[1]
