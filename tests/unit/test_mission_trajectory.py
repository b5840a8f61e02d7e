"""What the mission hands the planner as mission/active_trajectory."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from aeroperception.schemas import (
    Header, MissionTrajectory, PoseStamped, SchemaError, SetTrajectoryGoal, Trajectory, TrajectoryLimits, Waypoint,
    TrajectoryStatus, load_mission_file, parse_mission,
)
from aeroperception.services.mission.trajectory import NONE, TrajectoryHandover, check_given, waypoint_pose

SURVEY = load_mission_file(Path(__file__).resolve().parents[2] / "examples/missions/survey_01.json")


def test_without_a_choice_in_the_file_the_planners_generator_flies_the_waypoints():
    msg = TrajectoryHandover().message(True, SURVEY, 0)
    assert msg.generator_name == "" and len(msg.waypoints) == 4 and msg.limits is None
    assert all(w.header.frame_id == "map" for w in msg.waypoints)


def test_one_message_for_a_stretch_of_flying_from_the_waypoint_it_began_at():
    h = TrajectoryHandover()
    first = h.message(True, SURVEY, 1)
    assert first.trajectory_id == "survey_01@1" and h.current is first
    assert first.setpoint_type == Trajectory.SETPOINT_FULL_STATE
    assert [(w.pose.position.x, w.pose.position.y) for w in first.waypoints] == [(10, 0), (10, 10), (0, 0)]
    assert h.message(True, SURVEY, 2) is first          # advancing waypoints: the same message
    assert h.message(False, SURVEY, 2) == NONE           # a hold, goto or landing ends the stretch
    again = h.message(True, SURVEY, 2)
    assert again.trajectory_id == "survey_01@2" and len(again.waypoints) == 2


def test_the_mission_files_own_generator_and_limits_travel_with_its_waypoints():
    h = TrajectoryHandover()
    mission = SimpleNamespace(mission_id="m", waypoints=SURVEY.waypoints,
                              trajectory=MissionTrajectory(generator="smooth", max_velocity_mps=1.5))
    msg = h.message(True, mission, 0)
    assert msg.generator_name == "smooth" and msg.waypoints[0].pose.orientation.to_yaw() == 0.0
    assert msg.limits == TrajectoryLimits(max_velocity_mps=1.5) and len(msg.waypoints) == 4
    assert h.message(True, SURVEY, 4) == NONE            # past the last waypoint: nothing left to fly


def test_a_mission_files_trajectory_section_is_read_strictly():
    base = '{"mission_id": "m", "waypoints": [{"x": 0, "y": 0, "z": 2}], "trajectory": %s}'
    assert parse_mission(base % '{"generator": "smooth"}').trajectory.generator == "smooth"
    assert parse_mission("mission_id: m\nwaypoints: [{x: 0, y: 0, z: 2}]\ntrajectory: {generator: waypoint}\n"
                         ).trajectory.generator == "waypoint"
    limited = parse_mission(base % '{"jerk_mps3": 2, "z_vel_max_dn_mps": 0.5}').trajectory
    assert limited.generator == "" and limited.given() == {"jerk_mps3": 2.0, "z_vel_max_dn_mps": 0.5}
    for bad, why in [('{"generator": "fast"}', "generator"), ('{"generator": "smooth", "speed": 3}', "trajectory.speed"),
                     ('{"max_velocity_mps": 0}', "max_velocity_mps"), ('{"acc_hor_mps2": "fast"}', "acc_hor_mps2")]:
        with pytest.raises(SchemaError, match=why):
            parse_mission(base % bad)


def line(x0=0.0, distance=6.0, duration=8.0, poly_order=3, **kw) -> Trajectory:
    d, t = distance, duration
    return Trajectory(trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, total_duration_s=t, poly_order=poly_order,
                      poly_coeffs_x=[x0, 0.0, 3 * d / t ** 2, -2 * d / t ** 3], poly_coeffs_y=[0, 0, 0, 0],
                      poly_coeffs_z=[3, 0, 0, 0], **kw)


def test_a_given_trajectory_is_checked_from_where_the_vehicle_is_and_handed_over_while_flown():
    here = np.array([0.0, 0.0, 3.0])
    why, end = check_given(SetTrajectoryGoal(trajectory=line()), here, 0.0, 0.5)
    assert why == "" and end == pytest.approx([6.0, 0.0, 3.0])
    for goal, field in [(SetTrajectoryGoal(trajectory=line(), replace_current=False), "replace_current"),
                        (SetTrajectoryGoal(trajectory=line(start_time_ns=7)), "start_time_ns"),
                        (SetTrajectoryGoal(trajectory=line(x0=20.0)), "starts 20.0 m"),
                        (SetTrajectoryGoal(trajectory=line(distance=0.2)), "loop"),
                        (SetTrajectoryGoal(trajectory=line(poly_order=4)), "poly_coeffs_x"),
                        (SetTrajectoryGoal(trajectory=line(limits=TrajectoryLimits(max_velocity_mps=9.0))),
                         "limits.max_velocity_mps"),
                        (SetTrajectoryGoal(trajectory=Trajectory(waypoints=[waypoint_pose(Waypoint(x=5, y=0, z=3))])),
                         "generator_name"),
                        (SetTrajectoryGoal(trajectory=Trajectory(generator_name="smooth", waypoints=[
                            PoseStamped(header=Header(frame_id="odom"))])), "waypoints[0].header.frame_id")]:
        assert field in check_given(goal, here, 0.0, 0.5)[0], field
    h = TrajectoryHandover()
    h.give(line(), end)
    assert h.message(False, SURVEY, 0, goto_m=end) == line()          # the goto to its end: handed over
    assert h.message(True, SURVEY, 0).trajectory_id == "survey_01@0"  # the goto ended: back to the mission's
    assert h.given is None


def test_only_an_abort_of_the_trajectory_handed_over_now_is_a_refusal():
    h = TrajectoryHandover()
    aborted = lambda tid: TrajectoryStatus(status=TrajectoryStatus.STATUS_ABORTED, trajectory_id=tid)  # noqa: E731
    assert not h.refused(aborted(""))                        # nothing handed over
    msg = h.message(True, SURVEY, 1)
    assert h.refused(aborted(msg.trajectory_id))
    assert not h.refused(aborted("other@0"))
    assert not h.refused(TrajectoryStatus(status=TrajectoryStatus.STATUS_EXECUTING, trajectory_id=msg.trajectory_id))
