"""Objects: a known box + pose + depth -> a known ENU point, by stereo disparity and by the ray to
the ground; covariances grow with range (the pose history: test_pose_history.py)."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.schemas import CameraInfo, NDArray, Pose, Quaternion, Vector3
from aeroperception.services.lib.pose_history import PoseSample
from aeroperception.services.objects.projection import (
    Camera, Measurement, Noise, box_disparity, fuse, locate_by_disparity, locate_on_ground,
    to_centre,
)
from aeroperception.services.runtime.rotations import quat_from_euler, quat_from_rotmat, quat_to_rotmat

FX, CX, CY, W, H = 320.0, 319.5, 239.5, 640, 480
# Optical (x right, y down, z forward) axes in body FLU: forward-looking camera.
R_BODY_OPT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BODY_CAM = np.array([0.1, 0.04, -0.05])
BASELINE = 0.08


def infos(pitch_down_rad: float = 0.0) -> tuple[CameraInfo, CameraInfo]:
    r_pitch = quat_to_rotmat(quat_from_euler(0.0, pitch_down_rad, 0.0))     # FLU pitch +: nose down
    r = r_pitch @ R_BODY_OPT
    q = Quaternion.from_array(quat_from_rotmat(r))
    left = CameraInfo.pinhole(W, H, FX, FX, CX, CY, T_body_camera=Pose(position=Vector3.from_array(T_BODY_CAM), orientation=q))
    right = CameraInfo.pinhole(W, H, FX, FX, CX, CY, T_body_camera=Pose(
        position=Vector3.from_array(T_BODY_CAM + r[:, 0] * BASELINE), orientation=q))
    p = right.P.to_numpy().copy()
    p[0, 3] = -FX * BASELINE
    right.P = NDArray.from_numpy(p)
    return left, right


def project(point_enu, pose: PoseSample, pitch_down_rad: float = 0.0) -> tuple[float, float, float]:
    """Independent pinhole projection: (u, v) in the continuous pixel convention and depth z."""
    r_wb = quat_to_rotmat(pose.q_enu_flu)
    r_bc = quat_to_rotmat(quat_from_euler(0.0, pitch_down_rad, 0.0)) @ R_BODY_OPT
    cam_origin = pose.position_m + r_wb @ T_BODY_CAM
    pc = (r_wb @ r_bc).T @ (np.asarray(point_enu, float) - cam_origin)
    return CX + FX * pc[0] / pc[2] + 0.5, CY + FX * pc[1] / pc[2] + 0.5, float(pc[2])


def pose_at(position, roll=0.0, pitch=0.0, yaw=0.0, stamp_ns=0) -> PoseSample:
    return PoseSample(stamp_ns, np.asarray(position, float), quat_from_euler(roll, pitch, yaw))


NO_NOISE = Noise(pixel_px=0.5, disparity_px=0.05, height_m=0.05, position_m=0.0, attitude_rad=0.0)


@pytest.mark.parametrize("yaw, roll, pitch_cam", [(0.0, 0.0, 0.3), (1.2, 0.05, 0.5), (-2.5, -0.1, 0.2)])
def test_ground_path_puts_a_box_centre_at_the_objects_mid_height(yaw, roll, pitch_cam):
    left, right = infos(pitch_cam)
    cam = Camera.from_infos(left, right)
    pose = pose_at([3.0, -2.0, 12.0], roll=roll, yaw=yaw)
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    truth = np.array([3.0 + 20 * fwd[0], -2.0 + 20 * fwd[1], 0.875])         # a person's centre, ground z = 0
    u, v, _ = project(truth, pose, pitch_cam)
    m = locate_on_ground(cam, cam.world_pose(pose), u, v, 0.875, NO_NOISE, 100.0)
    assert m is not None and m.method == "ground"
    np.testing.assert_allclose(m.position_m, truth, atol=1e-6)
    assert m.range_m == pytest.approx(np.linalg.norm(truth - cam.world_pose(pose)[1]))


def test_ground_path_refuses_a_ray_at_or_above_the_horizon():
    cam = Camera.from_infos(*infos(0.0))
    pose = pose_at([0.0, 0.0, 10.0])
    assert locate_on_ground(cam, cam.world_pose(pose), 320.0, 100.0, 0.875, NO_NOISE, 100.0) is None     # above the horizon
    assert locate_on_ground(cam, cam.world_pose(pose), 320.0, 250.0, 0.875, NO_NOISE, 50.0) is None      # beyond max range


def test_stereo_path_puts_the_box_at_its_disparitys_depth():
    left, right = infos(0.2)
    cam = Camera.from_infos(left, right)
    assert cam.baseline_m == pytest.approx(BASELINE)
    pose = pose_at([1.0, 2.0, 5.0], yaw=0.7)
    truth = np.array([1.0 + 6 * np.cos(0.7), 2.0 + 6 * np.sin(0.7), 3.5])
    u, v, z = project(truth, pose, 0.2)
    m = locate_by_disparity(cam, cam.world_pose(pose), u, v, FX * BASELINE / z, NO_NOISE)
    assert m is not None and m.method == "stereo"
    np.testing.assert_allclose(m.position_m, truth, atol=1e-6)


def test_baseline_from_the_extrinsics_when_the_projection_has_none():
    left, right = infos(0.0)
    right.P = CameraInfo.pinhole(W, H, FX, FX, CX, CY).P
    assert Camera.from_infos(left, right).baseline_m == pytest.approx(BASELINE)


def test_covariance_grows_with_range():
    cam = Camera.from_infos(*infos(0.3))
    pose = pose_at([0.0, 0.0, 10.0])
    noise = Noise()
    traces = {}
    for dist in (8.0, 16.0, 32.0):
        u, v, z = project([dist, 0.0, 0.875], pose, 0.3)
        g = locate_on_ground(cam, cam.world_pose(pose), u, v, 0.875, noise, 200.0)
        s = locate_by_disparity(cam, cam.world_pose(pose), u, v, FX * BASELINE / z, noise)
        traces[dist] = (np.trace(g.covariance_m2), np.trace(s.covariance_m2))
    assert traces[8.0][0] < traces[16.0][0] < traces[32.0][0]
    assert traces[8.0][1] < traces[16.0][1] < traces[32.0][1]
    # An 8 cm baseline seen from 10 m up: the ray to the ground is the tighter one far out.
    assert traces[32.0][1] > traces[32.0][0]


def test_fuse_weights_by_information_and_keeps_the_tighter_one_when_they_disagree():
    a = Measurement(np.array([10.0, 0.0, 1.0]), np.eye(3) * 0.01, 10.0, "stereo")
    b = Measurement(np.array([10.3, 0.0, 1.0]), np.eye(3) * 0.09, 10.0, "ground")
    origin = np.array([0.0, 0.0, 1.0])
    f = fuse(a, b, origin)
    assert f.method == "stereo+ground" and f.position_m[0] == pytest.approx(10.03)
    assert f.range_m == pytest.approx(10.03)                    # the fused point's, not either's
    far = Measurement(np.array([14.0, 0.0, 1.0]), np.eye(3) * 0.09, 14.0, "ground")
    assert fuse(a, far, origin) is a and fuse(None, far, origin) is far
    vague = Measurement(np.array([30.0, 0.0, 1.0]), np.eye(3) * 100.0, 30.0, "stereo")     # far stereo: metres uncertain
    assert fuse(vague, b, origin).range_m == pytest.approx(10.3, abs=0.05)


def textured_pair(disparity_px: int, box) -> tuple[np.ndarray, np.ndarray]:
    """Background at disparity 1, the box's region at `disparity_px`: right[x] = left[x + d]."""
    rng = np.random.default_rng(3)
    scene = (rng.random((H, W + 64)) * 255).astype(np.uint8)
    left = scene[:, :W].copy()
    right = scene[:, 1:W + 1].copy()
    x0, y0, x1, y1 = box
    obj = (rng.random((y1 - y0, x1 - x0 + 64)) * 255).astype(np.uint8)
    left[y0:y1, x0:x1] = obj[:, :x1 - x0]
    right[y0:y1, x0 - disparity_px:x1 - disparity_px] = obj[:, :x1 - x0]
    return left, right


def test_box_disparity_is_the_median_in_the_boxs_inner_region():
    box = (300, 200, 360, 320)
    left, right = textured_pair(6, box)
    assert box_disparity(left, right, box, 20) == pytest.approx(6.0, abs=0.1)
    # The box drawn 30 % too wide (background at disparity 1 in its margins): the inner region decides.
    wide = (282.0, 200.0, 378.0, 320.0)
    assert box_disparity(left, right, wide, 20) == pytest.approx(6.0, abs=0.1)


def test_box_disparity_none_without_texture_or_room():
    flat = np.full((H, W), 128, np.uint8)
    assert box_disparity(flat, flat, (300, 200, 360, 320), 20) is None
    left, right = textured_pair(6, (300, 200, 360, 320))
    assert box_disparity(left, right, (0.0, 0.0, 1.0, 1.0), 20) is None


def test_stereos_near_face_is_moved_half_a_footprint_farther_to_the_centre():
    face = Measurement(np.array([3.0, 4.0, 0.7]), np.eye(3) * 0.01, 5.0, "stereo")
    c = to_centre(face, np.array([0.0, 0.0, 10.0]), 1.0, 0.5)
    np.testing.assert_allclose(c.position_m, [3.6, 4.8, 0.7])                # along the horizontal line of sight
    along = np.array([0.6, 0.8, 0.0])
    assert along @ c.covariance_m2 @ along == pytest.approx(0.01 + 0.25)
    assert c.range_m == pytest.approx(6.0)


def test_box_scale_is_one_for_a_whole_view_from_any_height_and_less_for_a_partial_one():
    """A person's box (its side and, seen from above, its top) fills the height the class's typical
    size predicts, from 7 m up at 10 m or 30 m alike; a box showing half of it scales 0.5."""
    from aeroperception.services.objects.projection import box_scale

    cam = Camera.from_infos(*infos(0.0))
    size = (0.45, 0.5, 1.75)
    for dist, alt in ((10.0, 7.0), (30.0, 7.0), (15.0, 1.0)):
        origin = np.array([0.0, 0.0, alt])
        centre = np.array([dist, 0.0, 0.875])
        d = centre - origin
        down = np.arctan2(-d[2], np.hypot(d[0], d[1]))
        extent = 1.75 * np.cos(down) + 0.475 * abs(np.sin(down))
        rng = float(np.linalg.norm(d))
        m = Measurement(centre, np.eye(3) * 0.01, rng, "ground")
        whole_px = FX * extent / rng
        assert box_scale(cam, origin, m, whole_px, size) == pytest.approx(1.0)
        assert box_scale(cam, origin, m, whole_px / 2, size) == pytest.approx(0.5)


def box_centre_drawn(centre, size, yaw, pose: PoseSample, pitch_down_rad: float) -> tuple[float, float]:
    """(u, v) of the centre of the box drawn around an object of `size` (length, width, height) at
    `centre` (ENU), heading `yaw`: its eight corners' projections' extent."""
    c, s = np.cos(yaw), np.sin(yaw)
    half = np.asarray(size, float) / 2
    corners = [np.asarray(centre, float) + np.array([c * dx - s * dy, s * dx + c * dy, dz])
               for dx in (-half[0], half[0]) for dy in (-half[1], half[1]) for dz in (-half[2], half[2])]
    uv = np.array([project(p, pose, pitch_down_rad)[:2] for p in corners])
    u, v = (uv.min(0) + uv.max(0)) / 2
    return float(u), float(v)


def test_a_long_objects_box_centre_is_aimed_back_at_its_centre():
    """A car 17 m ahead, seen from 7 m up: its box spans its near bottom and far top edges, so the
    box centre's ray meets the mid-height plane ~0.45 m short (end-on). The offset, over headings,
    brings the ground placement of the box it would draw back to within 0.35 m of its centre."""
    from aeroperception.services.objects.projection import box_centre_offset_px

    cam = Camera.from_infos(*infos(0.17))
    pose = pose_at([0.0, 0.0, 7.0])
    view = cam.world_pose(pose)
    size = (4.5, 1.85, 1.5)
    centre = np.array([17.0, 0.0, 0.75])
    for yaw in (0.0, np.pi / 4, np.pi / 2):
        u, v = box_centre_drawn(centre, size, yaw, pose, 0.17)
        raw = locate_on_ground(cam, view, u, v, 0.75, NO_NOISE, 100.0)
        aimed = locate_on_ground(cam, view, u, v, 0.75, NO_NOISE, 100.0, size)
        assert np.linalg.norm(aimed.position_m[:2] - centre[:2]) < 0.35                 # the heading is unknown
        if yaw == 0.0:
            assert raw.position_m[0] < centre[0] - 0.3                       # short without the offset
    behind = box_centre_offset_px(cam, view, np.array([-5.0, 0.0, 0.75]), size)
    assert behind is None


def test_a_long_objects_stereo_ray_takes_the_ground_rays_bearing():
    """A truck 28 m ahead and 7 m to the left, seen from 7 m up: its box centre's bearing is not
    its centre's (its near end is seen farther out). Aimed by centre_aims' u, as the ground ray is,
    the stereo point (here at the centre's depth) lies on the ground placement's bearing at every
    heading, so the two agree on where across the line of sight it is; end-on, the box centre's
    own bearing put it 0.35 m to the side."""
    from aeroperception.services.objects.projection import centre_aims

    cam = Camera.from_infos(*infos(0.17))
    pose = pose_at([0.0, 0.0, 7.0])
    view = cam.world_pose(pose)
    size, centre = (8.0, 2.5, 3.4), np.array([28.0, 7.0, 1.7])
    sight = centre[:2] / np.linalg.norm(centre[:2])

    def across(p: np.ndarray) -> float:          # m to the left of the line of sight to the centre
        d = p[:2] - view[1][:2]
        return float(sight[0] * d[1] - sight[1] * d[0])

    for yaw in (0.0, np.pi / 4, np.pi / 2):
        u, v = box_centre_drawn(centre, size, yaw, pose, 0.17)
        disparity = FX * BASELINE / project(centre, pose, 0.17)[2]
        aim_u, _ = centre_aims(cam, view, np.array([[u, v, 1.7]]), [size])[0]
        stereo = locate_by_disparity(cam, view, u - aim_u, v, disparity, NO_NOISE)
        ground = locate_on_ground(cam, view, u, v, 1.7, NO_NOISE, 100.0, size)
        assert across(stereo.position_m) == pytest.approx(across(ground.position_m), abs=0.02)
        assert abs(across(stereo.position_m)) < 0.4
        if yaw == 0.0:
            assert across(locate_by_disparity(cam, view, u, v, disparity, NO_NOISE).position_m) > 0.3
