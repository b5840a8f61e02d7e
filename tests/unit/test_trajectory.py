"""The planner's trajectory math: the smooth generator's continuity, limits and corner bounds, and
the evaluation of each Trajectory type against hand-computed values."""
from __future__ import annotations

import math

import numpy as np
import pytest

from aeroperception.schemas import Header, Pose, PoseStamped, Quaternion, Trajectory, Vector3
from aeroperception.services.lib.trajectory import KinematicLimits, TrajectoryRefused, evaluate, peaks, smooth
from aeroperception.services.lib.trajectory.blend import CORNER_SHARE

SURVEY = np.array([[0, 0, 5], [10, 0, 5], [10, 10, 5], [0, 0, 5]], float)


def dense(path, n: int = 20001):
    ts = np.linspace(0.0, path.duration_s, n)
    samples = [path.sample(float(t)) for t in ts]
    return ts, {k: np.array([getattr(s, k) for s in samples])
                for k in ("position_m", "velocity_mps", "acceleration_mps2", "jerk_mps3")}


def assert_consistent(path, n: int = 20001, tol: float = 1e-3, with_jerk: bool = True):
    """Each derivative is the slope of the one before it everywhere, so position, velocity and
    acceleration (and jerk, when asked) have no jump at any joint. Jerk's own slope (snap) may
    jump where a blend begins, which costs the finite difference one step: a looser bound there."""
    ts, s = dense(path, n)
    dt = ts[1] - ts[0]
    pairs = [("position_m", "velocity_mps", tol), ("velocity_mps", "acceleration_mps2", tol)]
    if with_jerk:
        pairs.append(("acceleration_mps2", "jerk_mps3", 20 * tol))
    for lower, upper, bound in pairs:
        slope = np.diff(s[lower], axis=0) / dt
        mid = (s[upper][1:] + s[upper][:-1]) / 2
        scale = max(1.0, float(np.abs(s[upper]).max()))
        assert np.abs(slope - mid).max() < bound * scale, (lower, upper, np.abs(slope - mid).max())


def distance_to_polyline(p: np.ndarray, pts: np.ndarray) -> float:
    best = math.inf
    for a, b in zip(pts, pts[1:]):
        ab = b - a
        if not ab.any():
            continue
        u = np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0, 1)
        best = min(best, float(np.linalg.norm(a + u * ab - p)))
    return best


# ---------------------------------------------------------------- the smooth generator


def test_smooth_survey_is_continuous_within_limits_and_rounds_corners_inside_the_acceptance_radius():
    limits = KinematicLimits(xy_vel_max_mps=2.0)
    path = smooth(SURVEY, limits, acceptance_radius_m=0.5, yaws_rad=[0.0] * 4)
    assert_consistent(path)
    assert peaks(path).excess(limits) == []
    assert np.allclose(path.sample(0).position_m, SURVEY[0]) and np.allclose(path.sample(0).velocity_mps, 0)
    end = path.sample(path.duration_s)
    assert np.allclose(end.position_m, SURVEY[-1]) and np.allclose(end.velocity_mps, 0, atol=1e-9)
    # each corner is passed within the share of the acceptance radius, at the time given for it
    for k, t in enumerate(path.waypoint_times_s):
        assert np.linalg.norm(path.sample(t).position_m - SURVEY[k]) <= CORNER_SHARE * 0.5 + 1e-6
    # never farther from the straight legs than a corner is cut
    _, s = dense(path, 4001)
    assert max(distance_to_polyline(p, SURVEY) for p in s["position_m"]) <= CORNER_SHARE * 0.5 + 1e-6
    # the P-controller takes ~36 s for this survey at 2 m/s; 34.1 m at 2 m/s is 17 s of cruise
    assert 17.0 < path.duration_s < 22.0


def test_smooth_respects_vertical_caps_and_each_legs_own_cap():
    limits = KinematicLimits(xy_vel_max_mps=5.0, z_vel_max_up_mps=1.0, z_vel_max_dn_mps=0.5)
    pts = np.array([[0, 0, 0], [0, 0, 6], [20, 0, 6], [20, 0, 2]], float)
    path = smooth(pts, limits, 0.5, speed_caps_mps=[0, 3.0, 0])
    pk = peaks(path)
    assert pk.excess(limits) == []
    assert pk.z_up_mps == pytest.approx(1.0, abs=1e-6) and pk.z_down_mps == pytest.approx(0.5, abs=1e-6)
    assert pk.xy_speed_mps == pytest.approx(3.0, abs=1e-6)
    assert_consistent(path)


def test_smooth_slows_short_legs_instead_of_overlapping_blends_and_merges_repeated_points():
    limits = KinematicLimits(xy_vel_max_mps=8.0)
    pts = np.array([[0, 0, 2], [0.5, 0, 2], [0.5, 0, 2], [0.5, 0.4, 2], [3, 0.4, 2]], float)
    path = smooth(pts, limits, 0.3)
    assert len(path.waypoint_times_s) == 4          # the repeated point is merged
    assert peaks(path).excess(limits) == []
    assert_consistent(path)
    _, s = dense(path, 4001)
    assert max(distance_to_polyline(p, pts) for p in s["position_m"]) <= CORNER_SHARE * 0.3 + 1e-6


@pytest.mark.parametrize("seed", range(6))
def test_smooth_random_polylines_stay_within_limits_and_on_their_legs(seed):
    rng = np.random.default_rng(seed)
    pts = np.cumsum(rng.uniform(-6, 6, size=(6, 3)), axis=0)
    limits = KinematicLimits(xy_vel_max_mps=float(rng.uniform(1, 6)), jerk_mps3=float(rng.uniform(2, 8)))
    path = smooth(pts, limits, float(rng.uniform(0.2, 1.0)))
    assert peaks(path, 0.005).excess(limits, tolerance=1e-3) == []
    assert_consistent(path)
    assert np.allclose(path.sample(path.duration_s).position_m, pts[-1])


@pytest.mark.parametrize("v0", [(0, 0, 0.27), (1.5, 0.5, 0.0), (-1.0, 1.0, -0.3)],
                         ids=["climbing", "flying_on", "flying_away"])
def test_smooth_starts_at_the_velocity_given_and_still_passes_every_waypoint(v0):
    """A path handed to a moving vehicle starts at its velocity (no step in the reference) and
    still passes each waypoint within the corner bound and ends at rest at the last one."""
    limits, radius = KinematicLimits(xy_vel_max_mps=3.0), 0.5
    v0 = np.array(v0, float)
    pts = np.array([[0, 0, 4.7], [8, 0, 5], [8, 8, 5], [0, 8, 5]], float)
    path = smooth(pts, limits, radius, start_velocity_mps=v0)
    start = path.sample(0.0)
    assert np.allclose(start.position_m, pts[0]) and np.allclose(start.velocity_mps, v0)
    assert np.allclose(start.acceleration_mps2, 0)
    assert_consistent(path)
    assert peaks(path, 0.005).excess(limits, tolerance=1e-3) == []
    for k, t in enumerate(path.waypoint_times_s[1:], 1):
        assert np.linalg.norm(path.sample(t).position_m - pts[k]) <= CORNER_SHARE * radius + 1e-6, k
    end = path.sample(path.duration_s)
    assert np.allclose(end.position_m, pts[-1]) and np.allclose(end.velocity_mps, 0, atol=1e-9)


def test_take_off_hand_over_climbing_into_the_path_has_no_velocity_step():
    """The mission counts a take-off done 0.3 m under its altitude while the vehicle still climbs at
    ~0.27 m/s: a path from rest there stepped the velocity setpoint 0.27 -> 0 m/s, and the flight
    controller's answer to the step was the flight's peak jerk (built-in sim: 4.0-4.9 m/s^3
    vertical by truth, over MPC_JERK_AUTO 4). Carried on, the climb fades within the first blend."""
    limits = KinematicLimits(xy_vel_max_mps=3.0)
    pts = np.array([[0, 0, 4.7], [8, 0, 5], [8, 8, 5]], float)
    climbing = np.array([0, 0, 0.27])
    assert np.linalg.norm(smooth(pts, limits, 0.5).sample(0).velocity_mps - climbing) == pytest.approx(0.27)
    path = smooth(pts, limits, 0.5, start_velocity_mps=climbing)
    assert np.allclose(path.sample(0).velocity_mps, climbing)
    _, s = dense(path, 8001)
    assert np.abs(s["jerk_mps3"][:, 2]).max() < 0.5 and s["velocity_mps"][:, 2].min() > -0.05   # never sinks back


def test_smooth_turns_to_each_waypoints_heading_within_the_yaw_rate_limit():
    limits = KinematicLimits(yaw_rate_max_radps=math.radians(30))
    pts = np.array([[0, 0, 3], [2, 0, 3], [4, 0, 3]], float)
    path = smooth(pts, limits, 0.5, yaws_rad=[0.0, math.pi / 2, -math.pi])     # the last turn is the short way
    assert peaks(path).yaw_rate_radps <= limits.yaw_rate_max_radps + 1e-9
    assert path.sample(0).yaw_rad == 0.0
    final = path.sample(1e6).yaw_rad
    assert abs(math.remainder(final - math.pi, 2 * math.pi)) < 1e-6
    # 0 -> 90 deg -> 180 deg, the turns counter-clockwise the short way: never a negative heading
    yaws = [path.sample(t).yaw_rad for t in np.linspace(0, path.duration_s, 2000)]
    assert all(y >= -1e-6 or y <= -math.pi + 1e-6 for y in yaws)
    assert path.duration_s > path.motion_s      # 270 deg at 30 deg/s outlasts 4 m of legs: it turns after the stop


def test_smooth_refuses_bad_inputs_saying_what():
    with pytest.raises(ValueError, match="speed caps"):
        smooth(SURVEY, KinematicLimits(), 0.5, speed_caps_mps=[1.0])
    with pytest.raises(ValueError, match="acceptance_radius_m"):
        smooth(SURVEY, KinematicLimits(), 0.0)
    with pytest.raises(ValueError, match="jerk_mps3"):
        KinematicLimits(jerk_mps3=0.0)


# ---------------------------------------------------------------- Trajectory messages


def pose(x, y, z, yaw=0.0) -> PoseStamped:
    return PoseStamped(header=Header(frame_id="map"),
                       pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion.from_yaw(yaw)))


def test_polynomial_segments_evaluate_in_their_own_time():
    # segment 1: x = 1 + 2t + 3t^2 ; segment 2: x = 2 - t ; over 4 s (2 s each); y = 0.5 t ; z = 3
    msg = Trajectory(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=4.0, poly_order=2,
                     poly_coeffs_x=[1, 2, 3, 2, -1, 0], poly_coeffs_y=[0, 0.5, 0, 0, 0.5, 0],
                     poly_coeffs_z=[3, 0, 0, 3, 0, 0])
    path = evaluate(msg)
    s = path.sample(1.0)
    assert s.position_m == pytest.approx([6.0, 0.5, 3.0]) and s.velocity_mps == pytest.approx([8.0, 0.5, 0.0])
    assert s.acceleration_mps2 == pytest.approx([6.0, 0.0, 0.0]) and s.yaw_rad is None
    s = path.sample(3.0)                         # one second into segment 2
    assert s.position_m == pytest.approx([1.0, 0.5, 3.0]) and s.velocity_mps == pytest.approx([-1.0, 0.5, 0.0])
    assert path.waypoint_times_s == [0.0, 2.0, 4.0]


def test_polynomial_yaw_and_refusals_name_the_field():
    base = dict(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=2.0, poly_order=1,
                poly_coeffs_x=[0, 1], poly_coeffs_y=[0, 0], poly_coeffs_z=[2, 0])
    assert evaluate(Trajectory(**base, poly_coeffs_yaw=[0, 0.5])).sample(1.0).yaw_rate_radps == pytest.approx(0.5)
    for change, field in [({"poly_coeffs_y": [0]}, "poly_coeffs_y"), ({"poly_coeffs_x": [0, 1, 2]}, "poly_coeffs_x"),
                          ({"total_duration_s": 0.0}, "total_duration_s"), ({"poly_order": 12}, "poly_order"),
                          ({"waypoints": [pose(0, 0, 0)]}, "waypoints"),
                          ({"poly_coeffs_z": [2, float("nan")]}, "poly_coeffs_z")]:
        with pytest.raises(TrajectoryRefused, match=field):
            evaluate(Trajectory(**{**base, **change}))


def test_bezier_matches_bernstein_by_hand():
    # quadratic, control points (0,0), (1,2), (2,0) over 2 s: at u = 0.5 -> (1, 1); dP/du = (2, 0)
    msg = Trajectory(trajectory_type=Trajectory.TRAJECTORY_BEZIER, total_duration_s=2.0, poly_order=2,
                     waypoints=[pose(0, 0, 1), pose(1, 2, 1), pose(2, 0, 1)])
    s = evaluate(msg).sample(1.0)
    assert s.position_m == pytest.approx([1.0, 1.0, 1.0]) and s.velocity_mps == pytest.approx([1.0, 0.0, 0.0])
    assert s.acceleration_mps2 == pytest.approx([0.0, -2.0, 0.0])   # d2P/du2 = 2(P0 - 2P1 + P2) = (0, -8) / T^2
    with pytest.raises(TrajectoryRefused, match="waypoints"):     # 4 points are not m x 2 + 1
        evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_BEZIER, total_duration_s=2.0, poly_order=2,
                            waypoints=[pose(0, 0, 1)] * 4))


def test_bspline_is_clamped_and_degree_three_on_four_points_is_the_cubic_bezier():
    pts = [pose(0, 0, 2), pose(1, 3, 2), pose(4, 3, 2), pose(5, 0, 2, yaw=1.0)]
    kw = dict(total_duration_s=5.0, poly_order=3, waypoints=pts)
    spline = evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_BSPLINE, **kw))
    curve = evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_BEZIER, **kw))
    for t in (0.0, 1.3, 2.5, 4.9, 5.0):
        a, b = spline.sample(t), curve.sample(t)
        assert a.position_m == pytest.approx(b.position_m) and a.velocity_mps == pytest.approx(b.velocity_mps)
    assert spline.sample(0).position_m == pytest.approx([0, 0, 2]) and spline.sample(5).position_m == pytest.approx([5, 0, 2])
    assert spline.sample(5).yaw_rad == pytest.approx(1.0)
    linear = evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_BSPLINE, total_duration_s=4.0, poly_order=1,
                                 waypoints=pts[:3]))
    assert linear.sample(2.0).position_m == pytest.approx([1, 3, 2])   # degree 1: through the middle point at T/2
    with pytest.raises(TrajectoryRefused, match="waypoint_times_s"):
        evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_BSPLINE, waypoint_times_s=[0, 1, 2, 3], **kw))
    with pytest.raises(TrajectoryRefused, match="poly_order"):
        evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_BSPLINE, total_duration_s=5.0, waypoints=pts))


def test_timed_waypoints_pass_each_waypoint_at_its_time_from_rest_to_rest():
    pts = [pose(0, 0, 2), pose(4, 0, 2), pose(4, 4, 3), pose(0, 4, 3)]
    path = evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_WAYPOINT, waypoints=pts,
                               waypoint_times_s=[0.0, 3.0, 6.0, 10.0]))
    for w, t in zip(pts, [0.0, 3.0, 6.0, 10.0]):
        assert path.sample(t).position_m == pytest.approx([w.pose.position.x, w.pose.position.y, w.pose.position.z])
    assert path.sample(0).velocity_mps == pytest.approx([0, 0, 0]) and path.sample(10).velocity_mps == pytest.approx([0, 0, 0])
    assert_consistent(path, tol=2e-3, with_jerk=False)     # a cubic spline's jerk steps at its knots
    for bad, field in [({"waypoint_times_s": [0.0, 3.0, 3.0, 10.0]}, "waypoint_times_s"),
                       ({"waypoint_times_s": [1.0, 3.0, 6.0, 10.0]}, "waypoint_times_s"),
                       ({"total_duration_s": 12.0}, "total_duration_s"), ({"poly_order": 3}, "poly_order")]:
        with pytest.raises(TrajectoryRefused, match=field):
            evaluate(Trajectory(trajectory_type=Trajectory.TRAJECTORY_WAYPOINT, waypoints=pts,
                                **{"waypoint_times_s": [0.0, 3.0, 6.0, 10.0], **bad}))
    with pytest.raises(TrajectoryRefused, match="trajectory_type"):
        evaluate(Trajectory(trajectory_type=7, total_duration_s=1.0))
