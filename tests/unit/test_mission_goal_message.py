"""mission/active_goal as the mission builds it from a GoalOut (services/mission/goals.py)."""
from __future__ import annotations

import numpy as np
import pytest

from aeroperception.schemas import Header, MissionGoal
from aeroperception.services.mission.goals import GoalOut, goal_message


def test_a_goal_becomes_the_planners_message_hold_or_a_pose_with_its_yaw_or_the_vehicles():
    hold = goal_message(GoalOut(None), 1.0, Header(stamp_ns=5))
    assert hold.header == Header(stamp_ns=5, frame_id=MissionGoal.HOLD_FRAME)
    g = goal_message(GoalOut(np.array([1.0, 2.0, 3.0]), None, max_speed_mps=2.0), 0.5, Header(stamp_ns=6))
    assert g.header.frame_id == "map" and g.pose.position.to_array().tolist() == [1.0, 2.0, 3.0]
    assert g.pose.orientation.to_yaw() == pytest.approx(0.5) and g.max_speed_mps == 2.0
    assert goal_message(GoalOut(np.zeros(3), 1.2), 0.5, Header()).pose.orientation.to_yaw() == pytest.approx(1.2)
    assert goal_message(GoalOut(np.zeros(3)), None, Header()).pose.orientation.to_yaw() == pytest.approx(0.0)
