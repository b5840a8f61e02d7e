"""What the mission accepts to fly (services/mission/limits.py): missions, takeoff altitudes and
goto targets outside the shared geofence or the radius limits are refused naming the reason.
"""
from __future__ import annotations

import msgspec
import numpy as np
import pytest

from aeroperception.schemas import Mission
from aeroperception.services.mission.fsm import State
from aeroperception.services.mission import contract
from aeroperception.services.mission.config import MissionConfig
from aeroperception.services.mission.limits import Limits, obstacle_warning
from aeroperception.services.runtime.config import check_covers
from aeroperception.services.lib.geofence import Geofence
from mission_rig import Rig, survey, vehicle


def mission_with(**changes) -> Mission:
    data = msgspec.to_builtins(survey())
    data.update(changes)
    return msgspec.convert(data, Mission)


@pytest.mark.parametrize(("changes", "words"), [
    ({"waypoints": [{"x": 0, "y": 0, "z": 5}, {"x": 5, "y": 0, "z": -50}]}, ["waypoint 1", "floor"]),
    ({"waypoints": [{"x": 0, "y": 0, "z": 5}, {"x": 10_000, "y": 0, "z": 5}]}, ["waypoint 1", "radius"]),
    ({"waypoints": [{"x": 0, "y": 0, "z": 5000}]}, ["waypoint 0", "ceiling"]),
    ({"takeoff_altitude_m": 1e12}, ["takeoff altitude"]),
    ({"waypoint_acceptance_radius_m": 1e9}, ["acceptance radius"]),
    ({"waypoint_acceptance_radius_m": 0.01}, ["acceptance radius"]),
])
def test_unsafe_missions_are_refused_naming_the_reason(changes, words):
    rig = Rig()
    rig.feed(vehicle())
    ok, msg = rig.mgr.load(mission_with(**changes))
    assert not ok and "refused" in msg
    for w in words:
        assert w in msg, msg
    assert rig.mgr.mission is None


def test_takeoff_altitude_above_the_limits_is_refused():
    rig = Rig(limits=Limits.from_params(max_takeoff_altitude_m=30.0))
    rig.to_idle()
    ok, msg = rig.mgr.takeoff(1e12, rig.outcome())
    assert not ok and "takeoff" in msg and rig.bridge.calls == []
    ok, msg = rig.mgr.takeoff(40.0, rig.outcome())
    assert not ok and "30" in msg
    assert rig.mgr.takeoff(10.0, rig.outcome())[0]


def test_goto_outside_the_geofence_or_with_a_silly_radius_is_refused():
    rig = Rig(limits=Limits.from_params(geofence=Geofence.from_params(radius_m=100.0)))
    rig.to_holding()
    rig.clear()
    ok, msg = rig.mgr.goto(np.array([500.0, 0.0, 5.0]), None)
    assert not ok and "geofence radius" in msg
    ok, msg = rig.mgr.goto(np.array([5.0, 0.0, 5.0]), None, acceptance_radius_m=1e9)
    assert not ok and "acceptance radius" in msg
    assert rig.mgr.state == State.HOLDING and rig.goals == []
    assert rig.mgr.goto(np.array([5.0, 0.0, 5.0]), None)[0]


def test_limits_take_the_geofence_from_the_shared_parameters():
    from aeroperception.services.mission import contract
    from aeroperception.services.runtime.params import ParamSet
    params = ParamSet.from_declarations(contract.PARAMS)
    params.set("geofence_radius_m", 50.0)
    limits = Limits.from_params(params)
    assert limits.geofence.radius_m == 50.0
    assert "waypoint 1" in limits.check_mission(mission_with(waypoints=[{"x": 0, "y": 0, "z": 5},
                                                                         {"x": 60, "y": 0, "z": 5}]))


def test_the_service_config_references_every_parameter_and_the_load_warning_names_the_waypoints():
    check_covers(MissionConfig, contract.PARAMS, "mission")
    assert obstacle_warning([]) == ""
    assert obstacle_warning(["waypoint 2 (1, 2, 3)"]) == \
        "; warning: the costmap shows waypoint 2 (1, 2, 3) inside an obstacle: unreachable"
