"""`aero mission fly` (tools/cli/mission.py) without a stack: the progress lines (1-based
waypoints, "landing", never 0/4 or 5/4) and the end of the flight judged from the vehicle
(state/vehicle on the ground and disarmed), never from the mission FSM's IDLE label.
"""
from __future__ import annotations

import argparse
import threading
import time

import pytest

from aeroperception.schemas import (
    LandedState, MissionStatus, ParamDescriptor, ParamList, TrajectoryStatus, Vector3, VehicleState, WaypointReached,
)
from aeroperception.tools.cli.mission import Progress, _follow, check_limits, progress_line, reached_line
from aeroperception.tools.common import CliError


def status(state: str, active: int = -1, total: int = 4, message: str = "") -> MissionStatus:
    return MissionStatus(state=state, active_waypoint=active, total_waypoints=total,
                         distance_to_goal_m=3.0 if state == "EXECUTING" else None, message=message)


def vehicle(armed: bool, landed: int, z: float = 0.0) -> VehicleState:
    return VehicleState(position_m=Vector3(z=z), armed=armed, landed_state=landed, connected=True)


@pytest.mark.parametrize(("active", "shown"), [(0, "waypoint 1/4"), (1, "waypoint 2/4"), (3, "waypoint 4/4")])
def test_progress_is_one_based(active, shown):
    assert progress_line(status("EXECUTING", active)).startswith(shown)


def test_after_the_last_waypoint_it_says_landing_never_5_of_4():
    assert progress_line(status("LAND", 4), vehicle(True, LandedState.IN_AIR, 2.5)).startswith("landing")
    assert "5/4" not in (progress_line(status("EXECUTING", 4)) or "")
    assert progress_line(status("IDLE", -1)) is None          # not "waypoint 0/4"
    assert "0/4" not in progress_line(status("TAKEOFF", -1), vehicle(True, LandedState.IN_AIR, 1.0))


def test_progress_along_the_trajectory_or_the_leg_comes_from_planner_status():
    along = TrajectoryStatus(status=TrajectoryStatus.STATUS_EXECUTING, trajectory_id="survey_01@0",
                             progress_percent=42.4, remaining_time_s=12.25)
    assert progress_line(status("EXECUTING", 1), None, along).endswith("trajectory  42 % ( 12.2 s left)")
    leg = TrajectoryStatus(status=TrajectoryStatus.STATUS_EXECUTING, trajectory_id="goal-3", progress_percent=80.0,
                           remaining_time_s=1.5)
    assert "leg  80 % (  1.5 s left)" in progress_line(status("EXECUTING", 1), None, leg)
    assert "left" not in progress_line(status("EXECUTING", 1), None, TrajectoryStatus())   # idle planner: nothing


def test_a_files_limits_above_the_planners_are_refused_before_loading(monkeypatch):
    class Session:
        def get(self, *a, **kw):
            raise AssertionError("not called")
    plain = '{"waypoints": [{"x": 0, "y": 0, "z": 2}]}'
    check_limits(Session(), argparse.Namespace(vehicle=""), plain)      # no limits: nothing to ask the planner
    fast = '{"waypoints": [{"x": 0, "y": 0, "z": 2}], "trajectory": {"max_velocity_mps": 9}}'
    own = ParamList(params=[ParamDescriptor(name="max_velocity_mps", value=2.0)])
    monkeypatch.setattr("aeroperception.tools.cli.mission.call_or_fail", lambda *a, **kw: own)
    with pytest.raises(CliError, match="trajectory.max_velocity_mps 9 is above the planner's max_velocity_mps 2"):
        check_limits(Session(), argparse.Namespace(vehicle=""), fast)
    check_limits(Session(), argparse.Namespace(vehicle=""), fast.replace("9", "1.5"))


def test_every_reached_waypoint_is_shown_even_between_status_samples():
    lines = [reached_line(WaypointReached(index=i), 4) for i in range(4)]
    assert lines == ["reached waypoint 1/4", "reached waypoint 2/4", "reached waypoint 3/4", "reached waypoint 4/4"]


def args(timeout_s: float) -> argparse.Namespace:
    return argparse.Namespace(timeout=timeout_s, quiet=True)


def test_idle_mission_over_a_flying_vehicle_is_not_landed():
    """A restarted mission service reports IDLE (or HOLDING): fly must keep waiting for the vehicle."""
    prog = Progress()
    prog.status = status("IDLE", message="ready")
    prog.vehicle = vehicle(True, LandedState.IN_AIR, 5.0)
    with pytest.raises(CliError, match="did not finish.*armed"):
        _follow(args(1.0), prog, 4)


def test_armed_then_disarmed_while_the_mission_stayed_idle_is_not_done(capsys):
    """Seen across a router link: TAKEOFF never acted on, the FC auto-disarmed on the ground, and
    fly said "4/4 done: landed" with the vehicle never off the ground."""
    prog = Progress()
    prog.status = status("IDLE", message="mission lean loaded, 2 waypoints")
    prog.vehicle = vehicle(True, LandedState.ON_GROUND)

    def disarm_later():
        time.sleep(0.6)
        with prog.lock:
            prog.vehicle = vehicle(False, LandedState.ON_GROUND)
        prog.changed.set()

    t = threading.Thread(target=disarm_later)
    t.start()
    try:
        with pytest.raises(CliError, match="never left IDLE"):
            _follow(args(5.0), prog, 4)
    finally:
        t.join()
    assert "4/4 done" not in capsys.readouterr().out


def test_done_when_the_vehicle_is_down_and_disarmed(capsys):
    prog = Progress()
    prog.status = status("EXECUTING", 2)
    prog.vehicle = vehicle(True, LandedState.IN_AIR, 5.0)
    prog.reached = [WaypointReached(index=i) for i in (0, 1, 1, 2, 3)]   # a repeated event counts once

    def land_later():
        time.sleep(0.6)
        with prog.lock:
            prog.status = status("IDLE", message="mission restarted on the ground")
            prog.vehicle = vehicle(False, LandedState.ON_GROUND)
        prog.changed.set()

    t = threading.Thread(target=land_later)
    t.start()
    try:
        assert _follow(args(5.0), prog, 4) == 0
    finally:
        t.join()
    assert "4/4 done: landed and disarmed (vehicle on the ground)" in capsys.readouterr().out
