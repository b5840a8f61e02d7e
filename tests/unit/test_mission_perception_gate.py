"""What the mission does when perception (VIO) is lost: hold while EXECUTING, resume at the same
waypoint when it is back, RTL after the recovery time; the same gate before a takeoff starts the
mission; a silent perception/health counts as unhealthy.
"""
from __future__ import annotations

import pytest

from aeroperception.services.mission.fsm import Config, Event, State
from mission_rig import SURVEY_WPS, Rig, assert_goal, assert_hold, flying, survey


# ---------------------------------------------------------------- perception lost while flying

def test_perception_loss_while_executing_holds_and_recovery_resumes_the_same_waypoint():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(healthy=True)
    rig.feed(flying(0.0, 0.0, 5.0))                   # waypoint 0 reached, flying to 1
    assert rig.mgr.wp_index == 1 and rig.mgr.state == State.EXECUTING
    rig.clear()

    rig.tick(healthy=False)
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.hold_reason == "perception"
    assert "perception" in rig.mgr.status().message
    assert_hold(rig.goals[-1])
    rig.feed(flying(3.0, 0.0, 5.0))                   # positions while holding change nothing
    assert rig.mgr.reached_events == [0]

    for _ in range(8):                                # 4 s still unhealthy
        rig.tick(0.5, healthy=False)
        assert rig.mgr.state == State.HOLDING
    rig.tick(0.5, healthy=True)                       # back well within 10 s
    assert rig.mgr.state == State.EXECUTING
    assert rig.mgr.wp_index == 1
    assert_goal(rig.goals[-1], SURVEY_WPS[1])
    assert rig.bridge.calls == []


def test_perception_not_back_within_recovery_time_lands_with_rtl():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(healthy=True)
    rig.tick(healthy=False)
    assert rig.mgr.state == State.HOLDING
    t_hold = rig.t
    while rig.t - t_hold < 9.9:
        rig.tick(0.5, healthy=False)
        assert rig.mgr.state == State.HOLDING, rig.t - t_hold
    rig.tick(0.6, healthy=False)                      # > perception_recovery_s (10 s)

    assert rig.mgr.state == State.LAND
    assert rig.mgr.transitions[-1] == (State.HOLDING, Event.PERCEPTION_TIMEOUT, State.LAND)
    assert rig.mgr.land_mode == "RTL"
    assert rig.bridge.calls[-1] == ("set_mode", "RTL")


def test_silent_perception_counts_as_unhealthy():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(0.5, healthy=True)
    rig.tick(2.0)
    assert rig.mgr.state == State.EXECUTING
    rig.tick(1.5)                                     # 3.5 s without perception/health
    assert rig.mgr.state == State.HOLDING and rig.mgr.hold_reason == "perception"


def test_unhealthy_perception_is_ignored_when_not_required():
    rig = Rig()
    rig.to_executing(survey(require_vio=False))
    for _ in range(30):
        rig.tick(0.5, healthy=False)
    assert rig.mgr.state == State.EXECUTING


def test_config_require_perception_applies_when_the_mission_does_not_say():
    rig = Rig(Config.from_params(require_perception=True))
    rig.to_executing(survey())
    rig.tick(healthy=False)
    assert rig.mgr.state == State.HOLDING


def test_operator_hold_is_not_resumed_by_healthy_perception():
    rig = Rig()
    rig.to_executing(survey(require_vio=True))
    rig.tick(healthy=True)
    rig.mgr.command("HOLD")
    for _ in range(30):
        rig.tick(0.5, healthy=True)
    assert rig.mgr.state == State.HOLDING


# ---------------------------------------------------------------- perception gate after takeoff

def test_takeoff_does_not_start_the_mission_until_perception_is_healthy():
    rig = Rig()
    rig.to_takeoff(survey(require_vio=True))
    assert rig.mgr.command("START", rig.outcome())[0]       # start requested during the takeoff
    rig.tick(0.5, healthy=False)
    rig.feed(flying(z=5.0))                                  # altitude reached, VIO not TRACKING
    assert rig.mgr.state == State.HOLDING and rig.mgr.hold_reason == "perception"
    assert "VIO TRACKING" in rig.mgr.status().message
    for _ in range(6):
        rig.tick(0.5, healthy=False)
        assert rig.mgr.state == State.HOLDING
    assert all(g.position_m is None or g.position_m[2] == pytest.approx(5.0) for g in rig.goals)
    rig.tick(0.5, healthy=True)
    assert rig.mgr.state == State.EXECUTING and rig.mgr.wp_index == 0
    assert "starting mission" in rig.mgr.message
    assert_goal(rig.goals[-1], SURVEY_WPS[0])


def test_takeoff_waiting_for_perception_returns_home_after_the_recovery_time():
    rig = Rig()
    rig.to_takeoff(survey(require_vio=True))
    rig.mgr.command("START", rig.outcome())
    rig.feed(flying(z=5.0))
    assert rig.mgr.state == State.HOLDING
    for _ in range(21):
        rig.tick(0.5, healthy=False)
    assert rig.mgr.state == State.LAND and rig.mgr.land_mode == "RTL"


def test_takeoff_with_healthy_perception_starts_at_once():
    rig = Rig()
    rig.to_takeoff(survey(require_vio=True))
    rig.mgr.command("START", rig.outcome())
    rig.tick(0.1, healthy=True)
    rig.feed(flying(z=5.0))
    assert rig.mgr.state == State.EXECUTING
