"""What the mission hands the planner as mission/active_trajectory."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from aeroperception.schemas import SchemaError, Trajectory, load_mission_file, parse_mission
from aeroperception.services.mission.trajectory import NONE, TrajectoryHandover

SURVEY = load_mission_file(Path(__file__).resolve().parents[2] / "examples/missions/survey_01.json")


def test_the_waypoint_generator_hands_over_nothing():
    assert TrajectoryHandover("waypoint").message(True, SURVEY, 0) == NONE


def test_one_message_for_a_stretch_of_flying_from_the_waypoint_it_began_at():
    h = TrajectoryHandover("smooth")
    first = h.message(True, SURVEY, 1)
    assert first.trajectory_id == "survey_01@1" and first.generator_name == "smooth"
    assert first.setpoint_type == Trajectory.SETPOINT_FULL_STATE
    assert [(w.pose.position.x, w.pose.position.y) for w in first.waypoints] == [(10, 0), (10, 10), (0, 0)]
    assert h.message(True, SURVEY, 2) is first          # advancing waypoints: the same message
    assert h.message(False, SURVEY, 2) == NONE           # a hold, goto or landing ends the stretch
    again = h.message(True, SURVEY, 2)
    assert again.trajectory_id == "survey_01@2" and len(again.waypoints) == 2


def test_the_mission_files_own_choice_wins_over_the_parameter():
    h = TrajectoryHandover("waypoint")
    mission = SimpleNamespace(mission_id="m", waypoints=SURVEY.waypoints, trajectory=SimpleNamespace(generator="smooth"))
    msg = h.message(True, mission, 0)
    assert msg.generator_name == "smooth" and msg.waypoints[0].pose.orientation.to_yaw() == 0.0
    assert len(msg.waypoints) == 4
    assert h.message(True, SURVEY, 4) == NONE            # past the last waypoint: nothing left to fly


def test_a_mission_files_trajectory_section_is_read_strictly():
    base = '{"mission_id": "m", "waypoints": [{"x": 0, "y": 0, "z": 2}], "trajectory": %s}'
    assert parse_mission(base % '{"generator": "smooth"}').trajectory.generator == "smooth"
    assert parse_mission("mission_id: m\nwaypoints: [{x: 0, y: 0, z: 2}]\ntrajectory: {generator: waypoint}\n"
                         ).trajectory.generator == "waypoint"
    for bad, why in [('{"generator": "fast"}', "generator"), ('{"generator": "smooth", "speed": 3}', "trajectory.speed"),
                     ("{}", "generator")]:
        with pytest.raises(SchemaError, match=why):
            parse_mission(base % bad)
