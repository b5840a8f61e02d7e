"""Flying a path in time (Follower) and turning a Trajectory message into a path (path_for)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from aeroperception.schemas import Header, Pose, PoseStamped, Quaternion, Trajectory, Vector3
from aeroperception.services.lib.trajectory import KinematicLimits, TrajectoryRefused, smooth
from aeroperception.services.lib.trajectory.core import PlanningMargin, peaks
from aeroperception.services.planner.follow import FeedForward, Follower, SpeedGovernor, setpoint_of
from aeroperception.services.lib.trajectory.generators import path_for

LINE = np.array([[0, 0, 3], [10, 0, 3]], float)


def waypoint(x, y, z, yaw=0.0) -> PoseStamped:
    return PoseStamped(header=Header(frame_id="map"),
                       pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion.from_yaw(yaw)))


def test_reference_runs_in_time_while_the_vehicle_keeps_up_and_waits_when_it_lags():
    path = smooth(LINE, KinematicLimits(), 0.5)
    f = Follower(path, start_s=100.0, lag_m=1.5)
    for k in range(101):                              # a vehicle exactly on the reference
        now = 100.0 + 0.02 * k
        step = f.step(path.sample(f.t_s).position_m, now)
    assert f.t_s == pytest.approx(2.0, abs=1e-9) and step.tracking_error_m < 0.05
    stuck = step.reference.position_m.copy() - np.array([2.0, 0, 0])    # 2 m behind: beyond lag_m
    t = f.t_s
    for k in range(50):
        step = f.step(stuck, 102.0 + 0.02 * (k + 1))
    assert f.t_s == pytest.approx(t) and not step.finished      # time stood still: no run-away reference
    for k in range(2000):                             # caught up again: flies on and finishes
        step = f.step(path.sample(f.t_s).position_m, 103.0 + 0.02 * (k + 1))
        if step.finished:
            break
    assert step.finished and np.allclose(step.reference.position_m, LINE[-1])
    percent, elapsed, remaining = f.progress(103.0 + 0.02 * (k + 1))
    assert percent == pytest.approx(100.0) and remaining == 0.0 and elapsed > path.duration_s


def test_a_later_start_waits_at_the_beginning():
    path = smooth(LINE, KinematicLimits(), 0.5)
    f = Follower(path, start_s=10.0)
    for now in (5.0, 7.0, 9.99):
        assert np.allclose(f.step(LINE[0], now).reference.position_m, LINE[0]) and f.t_s == 0.0
    f.step(LINE[0], 10.0)
    f.step(LINE[0], 10.1)
    assert f.t_s == pytest.approx(0.1)


def test_setpoint_type_says_which_fields_are_valid():
    ref = smooth(LINE, KinematicLimits(), 0.5, yaws_rad=[0.0, 0.0]).sample(1.0)
    only = setpoint_of(ref, Trajectory.SETPOINT_POSITION_ONLY)
    assert only.position_valid and not (only.velocity_valid or only.acceleration_valid or only.yaw_valid)
    yaw = setpoint_of(ref, Trajectory.SETPOINT_POSITION_YAW)
    assert yaw.position_valid and yaw.yaw_valid and not yaw.velocity_valid
    full = setpoint_of(ref, Trajectory.SETPOINT_FULL_STATE)
    assert full.velocity_valid and full.acceleration_valid and full.yaw_rate_valid and not full.jerk_valid
    assert full.acceleration_mps2.x == pytest.approx(ref.acceleration_mps2[0])


def test_smooth_message_starts_where_the_vehicle_is_and_passes_every_waypoint():
    msg = Trajectory(generator_name="smooth", setpoint_type=Trajectory.SETPOINT_FULL_STATE,
                     waypoints=[waypoint(5, 0, 3), waypoint(5, 5, 3, math.pi / 2)])
    here = np.array([0.0, 0.0, 3.0])
    path = path_for(msg, here, 0.3, KinematicLimits(), 0.5)
    assert np.allclose(path.sample(0).position_m, here) and path.sample(0).yaw_rad == pytest.approx(0.3)
    assert np.allclose(path.sample(path.duration_s).position_m, [5, 5, 3])
    assert path.sample(path.duration_s).yaw_rad == pytest.approx(math.pi / 2)


def test_messages_the_planner_cannot_fly_as_given_are_refused_naming_why():
    here = np.array([0.0, 0.0, 3.0])
    cases = [
        (Trajectory(generator_name="min_snap", waypoints=[waypoint(5, 0, 3)]), "generator_name"),
        (Trajectory(generator_name="smooth", total_duration_s=9.0, waypoints=[waypoint(5, 0, 3)]), "total_duration_s"),
        (Trajectory(generator_name="smooth"), "waypoints"),
        # 10 m in 1 s: 10 m/s against a 2 m/s cap
        (Trajectory(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=1.0, poly_order=1,
                    poly_coeffs_x=[0, 10], poly_coeffs_y=[0, 0], poly_coeffs_z=[3, 0]), "MPC_XY_VEL_MAX"),
        # starts 20 m away from the vehicle
        (Trajectory(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=20.0, poly_order=1,
                    poly_coeffs_x=[20, 0.1], poly_coeffs_y=[0, 0], poly_coeffs_z=[3, 0]), "starts 20.0 m"),
    ]
    for msg, why in cases:
        with pytest.raises(TrajectoryRefused, match=why):
            path_for(msg, here, 0.0, KinematicLimits(), 0.5)
    ok = Trajectory(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=10.0, poly_order=1,
                    poly_coeffs_x=[0, 1.0], poly_coeffs_y=[0, 0], poly_coeffs_z=[3, 0])
    assert path_for(ok, here, 0.0, KinematicLimits(), 0.5).duration_s == 10.0


def test_the_acceleration_fed_forward_leads_the_reference_and_pays_for_drag():
    """What the flight controller must command now: the reference's acceleration `lead_s` ahead
    (its attitude lag) plus drag x the velocity it will then have; never past a waypoint the
    mission has not counted, and zero while waiting there."""
    path = smooth(LINE, KinematicLimits(), 0.5)
    ff = FeedForward(lead_s=0.2, drag_per_s=1.0)
    f = Follower(path, start_s=0.0, feedforward=ff)
    f.step(LINE[0], 0.0)
    step = f.step(LINE[0], 0.5)                             # accelerating
    ahead = path.sample(0.7)
    assert f.t_s == pytest.approx(0.5)
    assert np.allclose(step.setpoint.acceleration_mps2.to_array(), ahead.acceleration_mps2 + ahead.velocity_mps)
    assert np.allclose(step.setpoint.velocity_mps.to_array(), path.sample(0.5).velocity_mps)   # velocity: now
    cruise = path.sample(path.duration_s / 2)
    assert np.allclose(ff.acceleration(path, path.duration_s / 2), cruise.velocity_mps, atol=1e-6)  # drag only
    end = path.duration_s
    assert np.allclose(ff.acceleration(path, end - 0.05), path.sample(end).acceleration_mps2)   # no lead past the end
    assert np.allclose(ff.acceleration(path, 1.0, until_s=1.1), path.sample(1.1).acceleration_mps2
                       + path.sample(1.1).velocity_mps)    # nor past a waypoint waited at
    waiting = Follower(path, start_s=0.0, feedforward=ff)
    waiting.step(LINE[0], 0.0)
    held = waiting.step(LINE[0], 0.5, wait_at=(0.3, LINE[0]))
    assert np.allclose(held.setpoint.acceleration_mps2.to_array(), 0.0)
    plain = Follower(path, start_s=0.0)                      # no lead, no drag: the reference's own
    plain.step(LINE[0], 0.0)
    assert np.allclose(plain.step(LINE[0], 0.5).setpoint.acceleration_mps2.to_array(), path.sample(0.5).acceleration_mps2)


def test_the_feed_forward_pays_back_the_fcs_d_term_on_its_own_acceleration():
    """PX4 subtracts MPC_XY_VEL_D_ACC x the vehicle's acceleration from its acceleration setpoint:
    a vehicle on the reference accelerates as the reference does now (not `lead_s` ahead), so that
    much of the reference's current horizontal acceleration is added; vertically nothing (PX4's
    MPC_Z_VEL_D_ACC is 0)."""
    pts = np.array([[0, 0, 3], [10, 0, 3], [10, 8, 6]], float)
    path = smooth(pts, KinematicLimits(), 0.5)
    t = 1.0                                                  # accelerating along x
    now, ahead = path.sample(t), path.sample(t + 0.25)
    ff = FeedForward(lead_s=0.25, drag_per_s=1.0, xy_vel_d=0.2)
    want = ahead.acceleration_mps2 + ahead.velocity_mps
    want[:2] += 0.2 * now.acceleration_mps2[:2]
    assert abs(now.acceleration_mps2[0]) > 0.5
    assert np.allclose(ff.acceleration(path, t), want)
    corner = path.waypoint_times_s[2] - 1.0                 # climbing into the last leg: z untouched
    got = ff.acceleration(path, corner) - FeedForward(lead_s=0.25, drag_per_s=1.0).acceleration(path, corner)
    assert np.allclose(got, [*(0.2 * path.sample(corner).acceleration_mps2[:2]), 0.0])


def test_the_speed_governor_holds_the_clock_so_the_fcs_catch_up_stays_within_the_limit():
    """PX4 commands feed-forward + gain x (setpoint - vehicle): a vehicle 0.5 m behind at cruise
    would be flown at 2 + 0.95 x 0.5 = 2.48 m/s. The governor lets the reference run only as far
    as keeps that within the limit + 5 %, never backwards, and does nothing when off."""
    path = smooth(np.array([[0, 0, 3], [40, 0, 3]], float), KinematicLimits(xy_vel_max_mps=2.0), 0.5)
    gov = SpeedGovernor(gain_per_s=0.95, xy_speed_mps=2.0)
    cruise_s = path.duration_s / 2
    ref = path.sample(cruise_s)
    assert gov.command_xy_mps(ref, ref.position_m - [0.5, 0, 0]) == pytest.approx(2.0 + 0.95 * 0.5)
    f = Follower(path, start_s=0.0, governor=gov)
    f.t_s, f.last_s = cruise_s, 0.0
    behind = ref.position_m - [0.5, 0, 0]
    step = f.step(behind, 0.02)
    assert f.t_s == pytest.approx(cruise_s)                                # stands: already over the cap
    closer = ref.position_m - [0.05, 0, 0]          # 0.05 m behind; 0.1 s at full rate would lead by 0.25 m
    step = f.step(closer, 0.12)
    assert f.t_s - cruise_s == pytest.approx((2.1 - 2.0) / 0.95 / 2.0 - 0.05 / 2.0, abs=1e-3)  # leads by 0.105 m
    assert gov.command_xy_mps(step.reference, closer) == pytest.approx(2.1, abs=1e-3)
    off = Follower(path, start_s=0.0)                                       # gain 0: the clock runs on
    off.t_s, off.last_s = cruise_s, 0.0
    off.step(behind, 0.02)
    assert off.t_s == pytest.approx(cruise_s + 0.02)
    # a reference faster than the limit (a typed trajectory up to 10 % over) is not stalled by it
    fast = SpeedGovernor(gain_per_s=0.95, xy_speed_mps=1.8)
    assert fast.latest_s(path, cruise_s, cruise_s + 0.02, path.sample(cruise_s + 0.02).position_m) == cruise_s + 0.02


def test_the_governor_keeps_a_lagging_vehicle_within_the_limit_over_a_whole_path():
    """A vehicle that realises its commanded velocity 0.3 s late (PX4-like) flown through an
    L-shaped path with the FC's law ff + gain x error: the commanded speed stays within the
    limit + 5 % with the governor and exceeds it without."""
    pts = np.array([[0, 0, 3], [12, 0, 3], [12, 8, 3]], float)
    path = smooth(pts, KinematicLimits(xy_vel_max_mps=2.0), 0.5)

    def fly(gov: SpeedGovernor) -> tuple[float, bool]:
        f = Follower(path, start_s=0.0, governor=gov)
        p, v, peak, dt = pts[0].copy(), np.zeros(3), 0.0, 0.02
        for k in range(3000):
            step = f.step(p, k * dt)
            cmd = step.setpoint.velocity_mps.to_array() + 0.95 * (step.reference.position_m - p)
            cmd[2] = 0.0
            peak = max(peak, float(np.hypot(*cmd[:2])))
            v += (cmd - v) * dt / 0.3
            p = p + v * dt
            if step.finished:
                return peak, True
        return peak, False

    governed, done = fly(SpeedGovernor(0.95, 2.0))
    ungoverned, _ = fly(SpeedGovernor())
    assert done and governed <= 2.1 + 1e-6 < ungoverned


def test_a_reference_that_waits_streams_no_velocity():
    """A reference stopped by the lag rule feeds no velocity forward: with it, PX4 flew on past the
    stopped reference and sat 2.8 m ahead, its position loop balancing the feed-forward (figure8)."""
    path = smooth(LINE, KinematicLimits(), 0.5)
    f = Follower(path, start_s=0.0, feedforward=FeedForward(lead_s=0.2, drag_per_s=1.0))
    f.t_s, f.last_s = path.duration_s / 2, 0.0
    ref = path.sample(f.t_s)
    ahead = f.step(ref.position_m + [2.0, 0, 0], 0.02)                 # 2 m past it: beyond lag_m
    assert f.rate == 0.0 and np.allclose(ahead.setpoint.velocity_mps.to_array(), 0.0)
    assert np.allclose(ahead.setpoint.acceleration_mps2.to_array(), 0.0)
    half = f.step(ref.position_m + [1.125, 0, 0], 0.04)                 # between lag_m / 2 and lag_m: half rate
    assert f.rate == pytest.approx(0.5) and np.allclose(half.setpoint.velocity_mps.to_array(),
                                                         0.5 * path.sample(f.t_s).velocity_mps)


def test_a_planning_margin_shapes_generated_paths_only():
    here = np.array([0.0, 0.0, 3.0])
    msg = Trajectory(generator_name="smooth", waypoints=[waypoint(20, 0, 3)])
    slow = path_for(msg, here, 0.0, KinematicLimits(), 0.5, margin=PlanningMargin(0.2, 1.0))
    assert float(np.hypot(*slow.sample(slow.duration_s / 2).velocity_mps[:2])) == pytest.approx(1.8)
    assert peaks(slow, 0.005).jerk_mps3 == pytest.approx(3.0, abs=0.02)
    typed = Trajectory(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=10.0, poly_order=1,
                       poly_coeffs_x=[0, 2.0], poly_coeffs_y=[0, 0], poly_coeffs_z=[3, 0])
    assert path_for(typed, here, 0.0, KinematicLimits(), 0.5, margin=PlanningMargin(0.2, 1.0)).duration_s == 10.0   # flown as given


@pytest.mark.parametrize("off_m", [0.001, 0.02, 0.05])
def test_a_vehicle_already_at_the_first_waypoint_flies_on_from_it(off_m):
    """A vehicle a few centimetres from the first waypoint (hovering there, a mission resumed)
    gives a first leg too short for any blend: the path starts at that waypoint instead of being
    refused (which made the planner fly goal by goal)."""
    msg = Trajectory(generator_name="smooth", waypoints=[waypoint(0, 0, 5), waypoint(8, 0, 5), waypoint(8, 8, 5)])
    here = np.array([0.0, off_m, 5.0])
    path = path_for(msg, here, 0.3, KinematicLimits(), 0.5)
    start = path.sample(0)
    assert np.linalg.norm(start.position_m - [0, 0, 5]) <= off_m + 1e-9 and start.yaw_rad == pytest.approx(0.3)
    assert np.allclose(path.sample(path.duration_s).position_m, [8, 8, 5])
    assert len(path.waypoint_times_s) == 4   # the vehicle's point, then each waypoint (the planner waits by index)
    far = Trajectory(generator_name="smooth", waypoints=[waypoint(0, 0, 5), waypoint(0.03, 0, 5)])
    with pytest.raises(TrajectoryRefused, match="waypoints"):   # two waypoints too close stay refused
        path_for(far, np.array([-5.0, 0, 5]), 0.0, KinematicLimits(), 0.5)
