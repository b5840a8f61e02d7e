"""A goal the planner reports blocked or unreachable for blocked_timeout_s: hold with the reason
(START retries), skip to the next waypoint, or return home, per blocked_action.
"""
from __future__ import annotations

from aeroperception.services.mission.fsm import Config, State
from mission_rig import SURVEY_WPS, Rig, assert_goal, assert_hold, flying


def blocked_rig(action: str) -> Rig:
    rig = Rig(Config.from_params(blocked_timeout_s=5.0, blocked_action=action))
    rig.to_executing()
    rig.feed(flying(*SURVEY_WPS[0]))                  # flying to waypoint index 1 (10, 0, 5)
    return rig


def report_blocked(rig: Rig, seconds: float, state: str = "unreachable") -> None:
    """planner/status at 10 Hz saying the goal cannot be reached."""
    for _ in range(round(seconds * 10)):
        rig.t += 0.1
        rig.mgr.on_planner(state, "goal (10.0, 0.0) is 0.40 m from an obstacle", rig.t)


def test_unreachable_goal_holds_with_the_reason_and_start_retries():
    rig = blocked_rig("hold")
    report_blocked(rig, 4.5)
    rig.mgr.on_planner("avoiding", "", rig.t)         # a moment of hope restarts the clock
    report_blocked(rig, 4.5)
    assert rig.mgr.state == State.EXECUTING
    report_blocked(rig, 1.0)
    assert rig.mgr.state == State.HOLDING and rig.mgr.hold_reason == "blocked"
    msg = rig.mgr.status().message
    assert "waypoint 2/4 (10.0, 0.0, 5.0) unreachable for 5 s (planner unreachable: goal (10.0, 0.0) is 0.40 m" in msg
    assert_hold(rig.goals[-1])
    assert rig.mgr.command("START")[0]                # the operator retries the same waypoint
    assert_goal(rig.goals[-1], SURVEY_WPS[1])
    assert rig.mgr.command("SET_CURRENT", waypoint_index=2)[0]   # ... or skips it
    assert_goal(rig.goals[-1], SURVEY_WPS[2])


def test_unreachable_waypoint_is_skipped_with_blocked_action_skip():
    rig = blocked_rig("skip")
    report_blocked(rig, 5.3, "blocked")
    assert rig.mgr.state == State.EXECUTING and rig.mgr.wp_index == 2
    assert rig.mgr.message.startswith("skipped waypoint 2/4 (10.0, 0.0, 5.0) unreachable")
    assert_goal(rig.goals[-1], SURVEY_WPS[2])
    rig.mgr.wp_index = 3                              # the last waypoint unreachable too: complete
    report_blocked(rig, 5.3)
    assert rig.mgr.state == State.LAND


def test_unreachable_goal_returns_home_with_blocked_action_rtl():
    rig = blocked_rig("rtl")
    report_blocked(rig, 5.3)
    assert rig.mgr.state == State.LAND and rig.bridge.modes()[-1] == "RTL"
    assert "returning home (blocked_action rtl)" in rig.mgr.message


def test_a_trajectory_the_planner_refuses_for_what_it_asks_holds_at_once_saying_why():
    rig = blocked_rig("skip")                         # not a blocked goal: never skipped, never flown goal by goal
    rig.mgr.on_trajectory_refused("trajectory refused: `limits.max_velocity_mps` 5 is above the planner's 2")
    assert rig.mgr.state == State.HOLDING and "limits.max_velocity_mps" in rig.mgr.status().message
    assert_hold(rig.goals[-1])
    rig.mgr.on_trajectory_refused("again")            # holding already: nothing more
    assert rig.mgr.state == State.HOLDING
