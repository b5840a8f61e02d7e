"""The planner's swappable parts: registries keyed by name, when a switch is safe, what each
controller sends, the VIO estimate in the map frame, and the trajectories refused for what they ask."""
from __future__ import annotations

import math

import numpy as np
import pytest

from aeroperception.schemas import (
    Header, LandedState, Odometry, Pose, PoseStamped, Quaternion, Trajectory, TrajectoryLimits, TrajectorySetpoint,
    Twist, Vector3, VehicleState,
)
from aeroperception.schemas.mission import TRAJECTORY_GENERATORS
from aeroperception.services.planner import contract
from aeroperception.services.planner.controllers import CONTROLLERS, Gains
from aeroperception.services.planner.estimators import ESTIMATORS, VioEstimate, fc_offset_m
from aeroperception.services.runtime.state_store import StateStore
from aeroperception.services.planner.plugins import (
    PARTS_FILE, REGISTRIES, is_hovering, restore_parts, selected_parts, switch_refusal,
)
from aeroperception.services.runtime.params import ParamSet
from aeroperception.services.planner.tracking import TrackerConfig, TrajectoryTracker
from aeroperception.services.runtime.config import build
from aeroperception.services.lib.trajectory import KinematicLimits
from aeroperception.services.lib.trajectory.generators import GENERATORS, path_for

HOVER = 0.3


def state(speed=0.0, armed=True, landed=LandedState.IN_AIR, **kw) -> VehicleState:
    return VehicleState(velocity_mps=Vector3(x=speed), armed=armed, landed_state=landed, **kw)


def test_each_slot_is_a_registry_keyed_by_name_with_its_parameter_choices():
    assert set(REGISTRIES) == {"trajectory_generator", "controller", "estimator"}
    assert tuple(GENERATORS) == TRAJECTORY_GENERATORS == ("waypoint", "smooth")
    assert set(CONTROLLERS) == {"feedforward", "velocity"} and set(ESTIMATORS) == {"fc", "vio"}
    params = {p.name: p for p in contract.PARAMS}
    for role, registry in REGISTRIES.items():
        assert params[role].choices == tuple(registry) and params[role].default in registry
        with pytest.raises(ValueError, match="is not one of"):
            params[role].validate("nope")      # what SelectPlugin answers for an unknown name


def test_a_switch_is_refused_moving_and_allowed_on_the_ground_or_hovering():
    assert switch_refusal("controller", "velocity", state(0.1), HOVER) == ""                    # hovering
    assert switch_refusal("controller", "velocity", state(2.0, armed=False, landed=LandedState.ON_GROUND), HOVER) == ""
    assert switch_refusal("trajectory_generator", "smooth", None, HOVER) == ""                  # no state: no setpoints
    why = switch_refusal("trajectory_generator", "smooth", state(1.2), HOVER)
    assert "moving at 1.20 m/s" in why and "hover_speed_mps 0.3" in why
    assert "not registered: fc, vio" in switch_refusal("estimator", "gps", state(), HOVER)
    assert "visual_odometry" in switch_refusal("estimator", "vio", state(), HOVER, vio_fresh=False)
    assert switch_refusal("estimator", "vio", state(), HOVER, vio_fresh=True) == ""
    assert is_hovering(state(0.29), HOVER) and not is_hovering(state(0.31), HOVER)
    assert not is_hovering(state(0.0, landed=LandedState.ON_GROUND), HOVER)


def test_feedforward_sends_the_reference_as_is_velocity_closes_the_position_loop():
    sp = TrajectorySetpoint(position_valid=True, velocity_valid=True, acceleration_valid=True, yaw_valid=True,
                            position_m=Vector3(x=10.0), velocity_mps=Vector3(x=1.0),
                            acceleration_mps2=Vector3(x=0.5), yaw_rad=0.3)
    gains = Gains(kp=0.8, max_velocity_mps=2.0)
    assert CONTROLLERS["feedforward"].apply(sp, np.array([9.0, 0, 0]), gains) is sp
    v = CONTROLLERS["velocity"].apply(sp, np.array([9.5, 0.5, 0]), gains)
    assert not (v.position_valid or v.acceleration_valid) and v.velocity_valid and v.yaw_valid and v.yaw_rad == 0.3
    assert v.velocity_mps.to_array() == pytest.approx([1.0 + 0.4, -0.4, 0.0])
    far = CONTROLLERS["velocity"].apply(sp, np.array([0.0, 0, 0]), gains)          # capped at the speed limit
    assert np.linalg.norm(far.velocity_mps.to_array()) == pytest.approx(2.0)
    hold = CONTROLLERS["velocity"].apply(TrajectorySetpoint.hold([1.0, 2.0, 3.0], 0.0), np.array([1.0, 2.0, 3.0]), gains)
    assert hold.velocity_mps.to_array() == pytest.approx([0, 0, 0])


def odom(x, y, z, yaw, vx_body=0.0, reset=0) -> Odometry:
    return Odometry(header=Header(stamp_ns=5, frame_id="odom"),
                    pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion.from_yaw(yaw)),
                    twist=Twist(linear=Vector3(x=vx_body)), reset_counter=reset)


def test_vio_is_aligned_to_the_map_with_the_fcs_estimate_when_taken_up_and_at_each_reset():
    fc = state(position_m=Vector3(x=5.0, y=1.0, z=3.0), yaw_rad=math.pi / 2, flight_mode="OFFBOARD")
    vio = VioEstimate()
    first = vio.estimate(odom(0, 0, 0, 0.0), fc)           # VIO started at its own origin facing its x
    assert first.position_m.to_array() == pytest.approx([5.0, 1.0, 3.0]) and first.yaw_rad == pytest.approx(math.pi / 2)
    moved = vio.estimate(odom(2.0, 0, 0.5, 0.0, vx_body=1.0), fc)       # 2 m along VIO's x = the map's north
    assert moved.position_m.to_array() == pytest.approx([5.0, 3.0, 3.5])
    assert moved.velocity_mps.to_array() == pytest.approx([0.0, 1.0, 0.0], abs=1e-9)
    assert moved.estimator_name == "vio" and moved.flight_mode == "OFFBOARD" and moved.header.stamp_ns == 5
    assert fc_offset_m(fc, moved) == pytest.approx([0.0, -2.0, -0.5]) and not fc_offset_m(fc, fc).any()
    vio.estimate(odom(7.0, 7.0, 0, 1.0, reset=1), fc)       # VIO restarted: aligned anew
    assert vio.realigned == 2 and vio.estimate(odom(7.0, 7.0, 0, 1.0, reset=1), fc).position_m.to_array() \
        == pytest.approx([5.0, 1.0, 3.0])
    assert vio.estimate(odom(0, 0, 0, 0.0), None) is None   # nothing to align with yet


def wp(x, y, z, frame="map") -> PoseStamped:
    return PoseStamped(header=Header(frame_id=frame), pose=Pose(position=Vector3(x=x, y=y, z=z)))


def waypoints(generator="", frame="map", limits=None) -> Trajectory:
    return Trajectory(trajectory_id="m@0", generator_name=generator, limits=limits,
                      waypoints=[wp(10, 0, 5, frame), wp(10, 10, 5)])


def test_the_generator_is_the_messages_own_else_the_planners_and_waypoint_makes_no_path():
    here = np.array([0.0, 0.0, 5.0])
    assert path_for(waypoints(), here, 0.0, KinematicLimits(), 0.5, "waypoint") is None
    assert path_for(waypoints("smooth"), here, 0.0, KinematicLimits(), 0.5, "waypoint").duration_s > 10
    tr = TrajectoryTracker(build(TrackerConfig, contract.PARAMS, generator="waypoint"))
    tr.offer(waypoints())
    assert tr.generator() == "waypoint" and tr.step(here, 0.0, 0.0, np.array([10.0, 0, 5])) is None
    tr.set_generator("smooth")                               # switched while hovering: the next step makes a path
    assert tr.step(here, 0.0, 0.0, np.array([10.0, 0, 5])) is not None and tr.built == 1


def test_a_trajectory_refused_for_what_it_asks_is_held_at_never_flown_goal_by_goal():
    goal = np.array([10.0, 0, 5])
    for msg, field in [(waypoints("smooth", frame="odom"), "`waypoints[0].header.frame_id` 'odom'"),
                       (waypoints(limits=TrajectoryLimits(max_velocity_mps=5.0)),
                        "`limits.max_velocity_mps` 5 is above the planner's max_velocity_mps 2"),
                       (waypoints("fast"), "`generator_name` 'fast'")]:
        tr = TrajectoryTracker(build(TrackerConfig, contract.PARAMS, generator="smooth"))
        tr.offer(msg)
        assert field in tr.refused and tr.holds_for(goal), tr.refused
        assert not tr.holds_for(np.array([3.0, 3, 3]))     # a goto elsewhere flies
    tighter = waypoints("smooth", limits=TrajectoryLimits(max_velocity_mps=1.0))
    slow = path_for(tighter, np.zeros(3) + [0, 0, 5], 0.0, KinematicLimits(), 0.5)
    fast = path_for(waypoints("smooth"), np.zeros(3) + [0, 0, 5], 0.0, KinematicLimits(), 0.5)
    assert slow.duration_s > 1.6 * fast.duration_s


def test_a_restarted_planner_starts_with_the_parts_selected_last(tmp_path):
    """A switch persists (the mission's store, PARTS_FILE); a restart restores it over the start-up
    value, saying so, so a restart in flight never silently changes what flies."""
    before = ParamSet.from_declarations(contract.PARAMS)
    before.set("controller", "velocity")
    before.set("estimator", "vio")
    store = StateStore(tmp_path, PARTS_FILE)
    store.save(selected_parts(before))
    after = ParamSet.from_declarations(contract.PARAMS)         # a new process: the defaults
    notes = restore_parts(store.load(), after)
    assert selected_parts(after) == {"trajectory_generator": "waypoint", "controller": "velocity", "estimator": "vio"}
    assert notes == ["controller 'velocity' restored (selected before the restart) over 'feedforward'",
                     "estimator 'vio' restored (selected before the restart) over 'fc'"]
    assert restore_parts(None, after) == [] and restore_parts(store.load(), after) == []   # none / nothing differs
    odd = ParamSet.from_declarations(contract.PARAMS)
    assert restore_parts({"controller": "mpc"}, odd) == ["controller 'mpc' persisted but not registered: 'feedforward' runs"]
    assert odd["controller"] == "feedforward"
