"""safety/status recommendations: a rising HOLD / RTH / LAND acts once, airborne only; the
operator may command afterwards.
"""
from __future__ import annotations

import pytest

from aeroperception.schemas import SafetyStatus
from aeroperception.services.mission.fsm import SAFETY_REACTIONS, State
from mission_rig import Rig


REACTIONS = [  # (recommended_action, from state, expected state, FC mode asked)
    (SafetyStatus.ACTION_HOLD, State.EXECUTING, State.HOLDING, None),
    (SafetyStatus.ACTION_HOLD, State.TAKEOFF, State.HOLDING, None),
    (SafetyStatus.ACTION_HOLD, State.LAND, State.LAND, None),          # a landing is never turned into a hold
    (SafetyStatus.ACTION_RTH, State.EXECUTING, State.LAND, "RTL"),
    (SafetyStatus.ACTION_RTH, State.HOLDING, State.LAND, "RTL"),
    (SafetyStatus.ACTION_RTH, State.TAKEOFF, State.LAND, "RTL"),
    (SafetyStatus.ACTION_LAND, State.EXECUTING, State.LAND, "LAND"),
    (SafetyStatus.ACTION_LAND, State.HOLDING, State.LAND, "LAND"),
    (SafetyStatus.ACTION_LAND, State.TAKEOFF, State.LAND, "LAND"),
    (SafetyStatus.ACTION_LAND, State.IDLE, State.IDLE, None),          # only when airborne
    (SafetyStatus.ACTION_RTH, State.IDLE, State.IDLE, None),
    (SafetyStatus.ACTION_WARN, State.EXECUTING, State.EXECUTING, None),
    (SafetyStatus.ACTION_EMERGENCY_STOP, State.EXECUTING, State.EXECUTING, None),  # the safety service acts
]


@pytest.mark.parametrize(("action", "src", "dst", "mode"), REACTIONS,
                         ids=[f"{a}-{s.value}" for a, s, _, _ in REACTIONS])
def test_safety_reaction_table(action, src, dst, mode):
    rig = Rig()
    rig.to(src)
    rig.clear()
    rig.mgr.on_safety(action, "battery critical")
    assert rig.mgr.state == dst
    assert rig.bridge.modes() == ([mode] if mode else [])
    if src != State.IDLE and action != SafetyStatus.ACTION_WARN:
        assert "safety" in rig.mgr.message and "battery critical" in rig.mgr.message
    if action == SafetyStatus.ACTION_EMERGENCY_STOP:
        assert "executed by the safety service" in rig.mgr.message


def test_safety_reactions_cover_hold_rth_land():
    assert set(SAFETY_REACTIONS) == {SafetyStatus.ACTION_HOLD, SafetyStatus.ACTION_RTH, SafetyStatus.ACTION_LAND}


def test_safety_acts_once_per_rising_recommendation_so_the_operator_can_command():
    rig = Rig()
    rig.to_executing()
    rig.mgr.on_safety(SafetyStatus.ACTION_HOLD, "geofence warning")
    assert rig.mgr.state == State.HOLDING
    assert rig.mgr.command("START")[0]                # the operator acknowledges and resumes
    for _ in range(5):                                # the same recommendation repeated at 1 Hz
        rig.mgr.on_safety(SafetyStatus.ACTION_HOLD, "geofence warning")
    assert rig.mgr.state == State.EXECUTING
    rig.mgr.on_safety(SafetyStatus.ACTION_RTH, "battery low")   # rising: acts
    assert rig.mgr.state == State.LAND and rig.mgr.land_mode == "RTL"
    rig.mgr.on_safety(SafetyStatus.ACTION_HOLD, "")   # falling: nothing
    assert rig.mgr.state == State.LAND
    rig.mgr.on_safety(SafetyStatus.ACTION_NONE, "")
    rig.mgr.command("HOLD")
    rig.mgr.on_safety(SafetyStatus.ACTION_HOLD, "again")  # cleared, then raised again: acts (already holding)
    assert rig.mgr.state == State.HOLDING and "again" in rig.mgr.message
