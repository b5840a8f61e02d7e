"""Schemas: every registered type round-trips, is plain msgpack, and rejects bad data by name.

The generic tests run over REGISTRY, so a new schema without an entry in SAMPLES fails
`test_every_registered_schema_has_a_sample` until someone writes one.
"""
from __future__ import annotations

import argparse
import json
import math

import msgpack
import msgspec
import numpy as np
import pytest

from aeroperception.schemas import (
    ACTIONS, REGISTRY, ActionFeedback, ActionResult, ArmReply, ArmRequest, Attitude, BatteryState,
    CameraInfo, CancelReply, CancelRequest, CollisionConstraint, ControlOutput, Detection2D,
    Detection2DArray, DiagnosticArray, DiagnosticStatus, EmergencyStopReply, EmergencyStopRequest,
    Empty, EstimatorStatus, GetMissionReply, GoalReply, GoalStatus, GoToPositionFeedback, GoToPositionGoal,
    GoToPositionResult, GpsPosition, Header,
    HomePosition, Image, Imu, LandedState, LandFeedback, LandGoal, LandResult, LoadMissionReply,
    LoadMissionRequest, LocalPosition, Message, Mission, MissionCommand, MissionGoal, MissionStatus, MissionTrajectory,
    NDArray,
    OccupancyGrid, Odometry, PerceptionHealth, PointCloud, Pose, PoseStamped, Quaternion, Reply,
    ResultRequest, SafetyStatus, SchemaError, SelectPluginReply, SelectPluginRequest, SetModeReply,
    SetModeRequest, SetTrajectoryFeedback, SetTrajectoryGoal, SetTrajectoryResult, TakeoffFeedback,
    TakeoffGoal, TakeoffResult, Trajectory, TrajectoryLimits, TrajectorySetpoint, TrajectoryStatus, Twist, UAVMode,
    UAVStatus, Vector3, VehicleState, VehicleStatus, VioHealth, VioResetRequest, Waypoint, WaypointReached, decode,
    encode, from_builtins, load_mission_file, parse_mission, to_builtins,
    ObjectEvent, TrackedObject, TrackedObjectArray,
)

# ---------------------------------------------------------------- representative samples

H = Header(stamp_ns=1_700_000_000_123_456_789, frame_id="map")
V = Vector3(x=1.5, y=-2.25, z=3.0)
Q = Quaternion.from_euler(0.1, -0.2, 0.3)
P = Pose(position=V, orientation=Q)


def arr(shape, dtype="float64", start=1):
    n = int(np.prod(shape))
    return NDArray.from_numpy(np.arange(start, start + n).reshape(shape).astype(dtype))


def _state():
    return VehicleState(
        header=H, position_m=V, velocity_mps=Vector3(x=0.5, y=0.1, z=-0.2),
        acceleration_mps2=Vector3(x=0.01, y=0.02, z=0.03), orientation=Q,
        angular_velocity_radps=Vector3(x=0.1, y=0.2, z=0.3), roll_rad=0.1, pitch_rad=-0.2, yaw_rad=0.3,
        pose_covariance=arr((6, 6)), twist_covariance=arr((6, 6), start=100), estimator_name="vio",
        confidence=0.9, flight_mode="OFFBOARD", armed=True, landed_state=LandedState.IN_AIR,
        battery_remaining=0.76, battery_voltage_v=15.9, connected=True,
    )


def _setpoint():
    return TrajectorySetpoint(
        header=H, position_valid=True, velocity_valid=True, yaw_valid=True, position_m=V,
        velocity_mps=Vector3(x=1.0), acceleration_mps2=Vector3(z=0.5), jerk_mps3=Vector3(y=0.1),
        yaw_rad=1.2, yaw_rate_radps=0.3,
    )


def _traj_status():
    return TrajectoryStatus(
        header=H, trajectory_id="t1", progress_percent=42.0, elapsed_time_s=3.5, remaining_time_s=4.0,
        current_setpoint=_setpoint(), position_error_m=0.2, velocity_error_mps=0.1,
        status=TrajectoryStatus.STATUS_EXECUTING,
    )


def _trajectory():
    return Trajectory(
        header=H, trajectory_id="t1", generator_name="minsnap",
        trajectory_type=Trajectory.TRAJECTORY_POLYNOMIAL, start_time_ns=5, total_duration_s=12.5,
        waypoints=[PoseStamped(header=H, pose=P), PoseStamped(pose=Pose(position=Vector3(x=9.0)))],
        waypoint_times_s=[0.0, 12.5], poly_coeffs_x=[0.0, 1.0, 0.5], poly_coeffs_y=[1.0],
        poly_coeffs_z=[2.0, 0.0], poly_coeffs_yaw=[0.1], poly_order=3,
        setpoint_type=Trajectory.SETPOINT_FULL_STATE, limits=TrajectoryLimits(max_velocity_mps=1.5, jerk_mps3=2.0),
    )


def _safety():
    return SafetyStatus(
        header=H, safety_level=SafetyStatus.LEVEL_CAUTION, estimator_healthy=True, controller_healthy=True,
        trajectory_healthy=False, px4_connected=True, gcs_connected=True,
        geofence_status=SafetyStatus.GEOFENCE_WARNING, distance_to_geofence_m=4.5, heartbeats_alive=5,
        heartbeats_total=6, dead_heartbeats=["detector"], battery_remaining=0.3, battery_voltage_v=14.1,
        battery_status=SafetyStatus.BATTERY_WARNING, active_warnings=["battery low"],
        active_errors=["detector dead"], recommended_action=SafetyStatus.ACTION_HOLD,
    )


def _mode():
    return UAVMode(header=H, state=UAVMode.STATE_FLYING, control_mode=UAVMode.MODE_OFFBOARD,
                   submode="inspection", armed=True, can_arm=False, can_takeoff=False, can_land=True)


def _mission():
    return Mission(header=H, mission_id="survey_01", takeoff_altitude_m=5.0, require_vio=True,
                   waypoints=[Waypoint(x=0.0, y=0.0, z=5.0), Waypoint(x=10.0, y=-1.0, z=6.0, yaw_deg=90.0)],
                   waypoint_acceptance_radius_m=0.75,
                   trajectory=MissionTrajectory(generator="smooth", acc_hor_mps2=2.0))


def _gcs_samples():
    from aeroperception.schemas import GcsLink, Joystick

    return {
        "GcsLink": lambda: GcsLink(header=H, connected=True, address="127.0.0.1:14550", system_id=255,
                                   last_heartbeat_age_s=0.4, packets_received=12, packets_invalid=1),
        "Joystick": lambda: Joystick(header=H, x=0.5, y=-0.25, z=0.6, r=0.1, buttons=3, source_system=255),
    }


def _system_samples():
    # schemas/system.py (sim clock, live parameters) is owned by the runtime; sampled here so the
    # generic guarantees cover it too.
    from aeroperception.schemas.system import Clock, ParamDescriptor, ParamList, ParamSet, ParamSetReply

    return {
        "Clock": lambda: Clock(header=H, speed_factor=2.0),
        "ParamSet": lambda: ParamSet(name="max_velocity_mps", value=2.5),
        "ParamSetReply": lambda: ParamSetReply(success=True, message="ok", name="rate_hz", value=10),
        "ParamList": lambda: ParamList(service="planner", params=[
            ParamDescriptor(name="max_velocity_mps", value=2.0, default=2.0, unit="m/s", min=0.0, max=10.0,
                            description="speed cap"),
            ParamDescriptor(name="mode", value="a", default="a", type="str", choices=["a", "b"]),
        ]),
    }


def _tracked() -> TrackedObject:
    return TrackedObject(track_id=7, class_name="person", class_id=0, confirmed=True,
                         position_m=Vector3(x=18.0, y=1.0, z=0.9), position_covariance_m2=[0.1, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.2],
                         velocity_mps=Vector3(x=0.5), first_seen_ns=1, last_seen_ns=2, hits=5, best_score=0.91,
                         range_m=18.2, latitude_deg=47.39, longitude_deg=8.54, altitude_amsl_m=489.0)


SAMPLES = {
    "PoseStamped": lambda: PoseStamped(header=H, pose=P),
    "Imu": lambda: Imu(
        header=Header(stamp_ns=7, frame_id="base_link"), orientation=Q, has_orientation=True,
        angular_velocity_radps=Vector3(x=0.01, y=0.02, z=-0.03), linear_acceleration_mps2=Vector3(z=9.81),
        orientation_covariance=arr((3, 3)), angular_velocity_covariance=arr((3, 3), start=10),
        linear_acceleration_covariance=arr((3, 3), start=20)),
    "Image": lambda: Image.from_numpy(np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3), "bgr8",
                                      Header(stamp_ns=9, frame_id="camera_left")),
    "CameraInfo": lambda: CameraInfo(
        header=Header(stamp_ns=9, frame_id="camera_left"), width=640, height=480,
        distortion_model="equidistant", K=arr((3, 3)), D=arr((4,)), R=arr((3, 3), start=3), P=arr((3, 4)),
        T_body_camera=P),
    "PointCloud": lambda: PointCloud.from_numpy(
        np.arange(12, dtype=np.float32).reshape(4, 3), intensity=[0.1, 0.2, 0.3, 0.4], labels=[0, 1, 1, 2],
        header=Header(stamp_ns=3, frame_id="lidar")),
    "OccupancyGrid": lambda: OccupancyGrid(
        header=H, resolution_m=0.25, width=4, height=3, origin=P,
        data=NDArray.from_numpy(np.array([[-1, 0, 100, 50]] * 3, dtype=np.int8))),
    "Detection2DArray": lambda: Detection2DArray(header=H, image_width=640, image_height=480, detections=[
        Detection2D(center_x_px=100.5, center_y_px=50.0, size_x_px=20.0, size_y_px=40.0, class_id=0,
                    class_name="person", score=0.87),
        Detection2D(center_x_px=1.0, center_y_px=2.0, size_x_px=3.0, size_y_px=4.0, class_id=2,
                    class_name="car", score=0.5)]),
    "TrackedObjectArray": lambda: TrackedObjectArray(header=H, objects=[_tracked()]),
    "ObjectEvent": lambda: ObjectEvent(header=H, event=ObjectEvent.CONFIRMED, object=_tracked()),
    "BatteryState": lambda: BatteryState(
        header=H, voltage_v=15.2, current_a=12.5, remaining_fraction=0.64, temperature_c=31.0, cell_count=4,
        cell_voltages_v=[3.8, 3.8, 3.81, 3.79], time_remaining_s=600.0, warning=BatteryState.WARNING_LOW),
    "DiagnosticStatus": lambda: DiagnosticStatus(
        header=H, level=DiagnosticStatus.WARN, name="vio", message="slow", hardware_id="cam0",
        values={"rate_hz": 28.5, "dropped": 3, "backend": "klt", "ok": False}),
    "DiagnosticArray": lambda: DiagnosticArray(header=H, status=[
        DiagnosticStatus(name="fmu", level=DiagnosticStatus.OK, values={"link": "up"}),
        DiagnosticStatus(name="vio", level=DiagnosticStatus.STALE)]),
    "Odometry": lambda: Odometry(
        header=Header(stamp_ns=11, frame_id="odom"), child_frame_id="base_link", pose=P,
        twist=Twist(linear=Vector3(x=1.0), angular=Vector3(z=0.1)), pose_covariance=arr((6, 6)),
        twist_covariance=arr((6, 6), start=50)),
    "VioHealth": lambda: VioHealth(
        header=H, state=VioHealth.DEGRADED, message="low parallax", strategy="klt_ransac",
        tracked_features=87, lost_features=12, consecutive_lost=2, mean_parallax_px=0.8,
        mean_reprojection_error_px=1.7, accel_bias_mps2=Vector3(x=0.01), gyro_bias_radps=Vector3(z=0.001),
        bias_norm=0.02),
    "VehicleState": _state,
    "TrajectorySetpoint": _setpoint,
    "ControlOutput": lambda: ControlOutput(
        header=H, control_mode=ControlOutput.CONTROL_MODE_BODY_RATE, position_m=V, yaw_rad=0.5,
        velocity_mps=Vector3(y=1.0), yaw_rate_radps=0.2, orientation=Q, body_rates_radps=Vector3(x=0.3),
        thrust_normalized=0.55, controller_name="pid"),
    "UAVMode": _mode,
    "UAVStatus": lambda: UAVStatus(
        header=H, uav_id="uav1", uav_name="alpha", current_state=_state(), current_mode=_mode(),
        active_estimator="vio", active_controller="pid", active_trajectory_generator="minsnap",
        safety_status=_safety(), battery_remaining=0.5, cpu_percent=37.5, memory_percent=51.0,
        px4_connected=True, gcs_connected=True, px4_latency_s=0.004,
        current_mission_id="survey_01", mission_progress_percent=25.0),
    "VehicleStatus": lambda: VehicleStatus(
        header=H, nav_state="OFFBOARD", custom_mode=6 << 16, px4_main_mode=6, px4_sub_mode=0, armed=True,
        landed_state=LandedState.IN_AIR, failsafe=True, system_id=3, autopilot="px4"),
    "LocalPosition": lambda: LocalPosition(
        header=H, position_m=V, velocity_mps=Vector3(x=0.2), acceleration_mps2=Vector3(z=-0.1), yaw_rad=1.0,
        position_valid=True, velocity_valid=True, distance_bottom_m=2.5),
    "Attitude": lambda: Attitude(header=H, orientation=Q, angular_velocity_radps=Vector3(y=0.4)),
    "HomePosition": lambda: HomePosition(
        header=H, latitude_deg=47.397742, longitude_deg=8.545594, altitude_amsl_m=488.0,
        position_m=Vector3(x=1.0, y=-2.0, z=0.3)),
    "GpsPosition": lambda: GpsPosition(
        header=H, fix_type=GpsPosition.FIX_3D, latitude_deg=47.397742, longitude_deg=8.545594, altitude_amsl_m=490.5,
        hdop=0.9, vdop=1.4, horizontal_accuracy_m=1.1,
        vertical_accuracy_m=1.7, ground_speed_mps=2.5, course_rad=1.2, satellites_visible=11),
    "EstimatorStatus": lambda: EstimatorStatus(
        header=H, flags=EstimatorStatus.ATTITUDE | EstimatorStatus.POS_HORIZ_REL, velocity_test_ratio=0.1,
        position_horizontal_test_ratio=0.2, position_vertical_test_ratio=0.3, magnetometer_test_ratio=0.4,
        height_above_ground_test_ratio=0.5, airspeed_test_ratio=0.6, position_horizontal_accuracy_m=0.7,
        position_vertical_accuracy_m=0.8),
    "SafetyStatus": _safety,
    "Trajectory": _trajectory,
    "TrajectoryStatus": _traj_status,
    "CollisionConstraint": lambda: CollisionConstraint(
        header=H, constraint_type=CollisionConstraint.CONSTRAINT_POLYGON, normal=Vector3(x=1.0), offset_m=2.0,
        center_m=V, radius_m=1.5, polygon_m=[Vector3(x=0.0), Vector3(x=1.0), Vector3(y=1.0)],
        source_uav_id="uav2", confidence=0.8, expires_at_ns=123),
    "Mission": _mission,
    "MissionStatus": lambda: MissionStatus(
        header=H, mission_id="survey_01", state=MissionStatus.STATE_EXECUTING, active_waypoint=2,
        total_waypoints=4, elapsed_time_s=33.5, perception_healthy=True, distance_to_goal_m=3.2,
        message="flying to wp 2"),
    "MissionCommand": lambda: MissionCommand(header=H, command="LOAD", mission_json=_mission().to_json()),
    "MissionGoal": lambda: MissionGoal(header=H, pose=P, max_speed_mps=1.5, max_vertical_speed_mps=0.5),
    "PerceptionHealth": lambda: PerceptionHealth(
        header=H, vio_status=PerceptionHealth.HEALTHY, detector_status=PerceptionHealth.DEGRADED,
        overall_healthy=True, message="detector slow"),
    "WaypointReached": lambda: WaypointReached(header=H, mission_id="survey_01", index=3, position_m=V),
    "Empty": lambda: Empty(header=H),
    "Reply": lambda: Reply(header=H, success=True, message="done"),
    "ArmRequest": lambda: ArmRequest(header=H, arm=True, force=True),
    "ArmReply": lambda: ArmReply(header=H, success=True, message="armed", armed=True),
    "SetModeRequest": lambda: SetModeRequest(header=H, mode="OFFBOARD"),
    "SetModeReply": lambda: SetModeReply(header=H, success=False, message="no setpoints", current_mode="HOLD"),
    "LoadMissionRequest": lambda: LoadMissionRequest(header=H, mission_json=_mission().to_json()),
    "LoadMissionReply": lambda: LoadMissionReply(header=H, success=True, message="", num_waypoints=2,
                                                 mission_id="survey_01"),
    "GetMissionReply": lambda: GetMissionReply(header=H, success=True, message="", mission_id="survey_01",
                                               num_waypoints=2, mission_json=_mission().to_json()),
    "EmergencyStopRequest": lambda: EmergencyStopRequest(header=H, confirm=True, reason="fire"),
    "EmergencyStopReply": lambda: EmergencyStopReply(header=H, success=True, message="motors stopped"),
    "SelectPluginRequest": lambda: SelectPluginRequest(header=H, role="estimator", name="vio"),
    "SelectPluginReply": lambda: SelectPluginReply(header=H, success=True, message="switched", active="vio"),
    "VioResetRequest": lambda: VioResetRequest(header=H, pose=Pose(position=Vector3(x=10.0, y=-2.0, z=3.0)),
                                               velocity_mps=Vector3(x=0.5)),
    "TakeoffGoal": lambda: TakeoffGoal(header=H, target_altitude_m=5.0, climb_rate_mps=1.0),
    "TakeoffResult": lambda: TakeoffResult(header=H, success=True, message="at altitude", final_altitude_m=4.95),
    "TakeoffFeedback": lambda: TakeoffFeedback(header=H, current_altitude_m=2.5, progress_percent=50.0),
    "LandGoal": lambda: LandGoal(header=H, land_at_current_position=False, target_position_m=V,
                                 descent_rate_mps=0.5),
    "LandResult": lambda: LandResult(header=H, success=True, message="landed", final_position_m=V),
    "LandFeedback": lambda: LandFeedback(header=H, altitude_agl_m=1.2, progress_percent=80.0),
    "SetTrajectoryGoal": lambda: SetTrajectoryGoal(header=H, trajectory=_trajectory(), replace_current=False),
    "SetTrajectoryResult": lambda: SetTrajectoryResult(
        header=H, success=False, message="aborted", completion_status=TrajectoryStatus.STATUS_ABORTED),
    "SetTrajectoryFeedback": lambda: SetTrajectoryFeedback(header=H, status=_traj_status()),
    "GoToPositionGoal": lambda: GoToPositionGoal(header=H, position_m=V, yaw_rad=1.57, velocity_mps=2.0,
                                                 acceptance_radius_m=0.3),
    "GoToPositionResult": lambda: GoToPositionResult(header=H, success=True, message="arrived",
                                                     final_position_m=V),
    "GoToPositionFeedback": lambda: GoToPositionFeedback(header=H, distance_remaining_m=7.5, eta_s=3.2),
    "GoalReply": lambda: GoalReply(header=H, success=True, message="accepted", goal_id="abc123",
                                   status=GoalStatus.ACCEPTED),
    "CancelRequest": lambda: CancelRequest(header=H, goal_id="abc123"),
    "CancelReply": lambda: CancelReply(header=H, success=True, message="cancelling", goal_id="abc123",
                                       status=GoalStatus.CANCELING),
    "ResultRequest": lambda: ResultRequest(header=H, goal_id="abc123"),
    "ActionFeedback": lambda: ActionFeedback.wrap(
        "abc123", TakeoffFeedback(current_altitude_m=1.0, progress_percent=20.0), action="takeoff", header=H),
    "ActionResult": lambda: ActionResult.wrap(
        "abc123", TakeoffResult(success=True, message="ok", final_altitude_m=5.0), GoalStatus.SUCCEEDED,
        action="takeoff", header=H),
    **_system_samples(),
    **_gcs_samples(),
}

# Registered schemas that do not (yet) carry a header; everything else must. (schemas/system.py's
# parameter messages are addressed by key, not time — reported to their owner.)
HEADERLESS: set[str] = set()

NAMES = sorted(REGISTRY)

# Required values that must change when optional fields are dropped (cross-field rules).
MINIMAL_OVERRIDES = {"MissionCommand": {"command": "HOLD"}}  # LOAD needs mission_json


def sample(name: str) -> Message:
    return SAMPLES[name]()


def fields_of(cls):
    return msgspec.structs.fields(cls)


def ndarray_shapes(cls):
    return dict(getattr(cls, "__shapes__", {}))


def _bad_value_for(value):
    """A value of the wrong type for whatever `value` is (maps become strings, the rest maps)."""
    return "not-a-map" if isinstance(value, dict) else {"bogus": 1}


# ---------------------------------------------------------------- registry-wide guarantees


def test_every_registered_schema_has_a_sample():
    assert set(REGISTRY) - set(SAMPLES) == set()
    assert set(SAMPLES) - set(REGISTRY) == set()


@pytest.mark.parametrize("name", NAMES)
def test_sample_differs_from_defaults_and_round_trips(name):
    cls = REGISTRY[name]
    msg = sample(name)
    assert type(msg) is cls
    payload = encode(msg)
    assert isinstance(payload, bytes)
    back = decode(payload, cls)
    assert back == msg
    assert encode(back) == payload


@pytest.mark.parametrize("name", NAMES)
def test_payload_is_a_plain_msgpack_map_with_every_field(name):
    cls = REGISTRY[name]
    msg = sample(name)
    plain = msgpack.unpackb(encode(msg))
    assert isinstance(plain, dict)
    assert set(plain) == {f.encode_name for f in fields_of(cls)}
    # and what another language writes back decodes to the same message
    assert decode(msgpack.packb(plain), cls) == msg


@pytest.mark.parametrize("name", sorted(set(NAMES) - HEADERLESS))
def test_every_top_level_message_has_a_defaulted_header(name):
    cls = REGISTRY[name]
    f = {f.name: f for f in fields_of(cls)}.get("header")
    assert f is not None and f.type is Header and f.default_factory is Header


@pytest.mark.parametrize("name", NAMES)
def test_unknown_fields_are_ignored(name):
    cls = REGISTRY[name]
    msg = sample(name)
    plain = msgpack.unpackb(encode(msg))
    plain["zz_added_in_v2"] = [1, {"nested": b"\x00"}]
    if isinstance(plain.get("header"), dict):
        plain["header"]["zz_clock_source"] = "gps"
    assert decode(msgpack.packb(plain), cls) == msg


@pytest.mark.parametrize("name", NAMES)
def test_missing_optional_fields_take_defaults(name):
    cls = REGISTRY[name]
    full = msgpack.unpackb(encode(sample(name)))
    required = {f.encode_name for f in fields_of(cls) if f.required}
    only_required = {k: v for k, v in full.items() if k in required}
    only_required.update(MINIMAL_OVERRIDES.get(name, {}))
    got = decode(msgpack.packb(only_required), cls)
    for f in fields_of(cls):
        if f.required:
            continue
        want = f.default if f.default is not msgspec.NODEFAULT else f.default_factory()
        assert getattr(got, f.name) == want, f.name


@pytest.mark.parametrize("name", NAMES)
def test_wrong_type_is_rejected_naming_the_field(name):
    cls = REGISTRY[name]
    full = msgpack.unpackb(encode(sample(name)))
    for key, value in full.items():
        bad = dict(full)
        bad[key] = _bad_value_for(value)
        with pytest.raises(SchemaError) as e:
            decode(msgpack.packb(bad), cls)
        assert key in str(e.value), str(e.value)
        assert name in str(e.value)


@pytest.mark.parametrize("name", [n for n in NAMES if ndarray_shapes(REGISTRY[n])])
def test_wrong_array_shape_is_rejected_naming_the_field(name):
    cls = REGISTRY[name]
    full = msgpack.unpackb(encode(sample(name)))
    checked = 0
    for field, shape in ndarray_shapes(cls).items():
        if len(shape) == 1 and shape[0] == -1:
            continue  # any length is valid
        n = int(np.prod([d if d > 0 else 2 for d in shape]))
        flat = NDArray.from_numpy(np.zeros(n))  # e.g. 36 values instead of a 6x6 covariance
        bad = dict(full)
        bad[field] = to_builtins(flat)
        with pytest.raises(SchemaError) as e:
            decode(msgpack.packb(bad), cls)
        assert field in str(e.value), str(e.value)
        checked += 1
    assert checked


def _top_level_arrays(name):
    return [f.name for f in fields_of(REGISTRY[name]) if isinstance(getattr(sample(name), f.name), NDArray)]


@pytest.mark.parametrize("name", [n for n in NAMES if _top_level_arrays(n)])
def test_array_with_wrong_byte_count_is_rejected_naming_the_field(name):
    cls = REGISTRY[name]
    full = msgpack.unpackb(encode(sample(name)))
    for field in _top_level_arrays(name):
        bad = dict(full)
        bad[field] = dict(full[field], data=full[field]["data"] + b"\x00")
        with pytest.raises(SchemaError) as e:
            decode(msgpack.packb(bad), cls)
        assert field in str(e.value) and "bytes" in str(e.value), str(e.value)


@pytest.mark.parametrize("name", NAMES)
def test_builtins_view_converts_back(name):
    cls = REGISTRY[name]
    msg = sample(name)
    assert from_builtins(to_builtins(msg), cls) == msg


def test_garbage_and_wrong_container_raise_schema_error():
    with pytest.raises(SchemaError):
        decode(b"\xc1\xff", VehicleState)
    with pytest.raises(SchemaError, match="VehicleState"):
        decode(msgpack.packb([1, 2, 3]), VehicleState)


def test_plain_msgpack_reader_can_rebuild_a_covariance():
    plain = msgpack.unpackb(encode(sample("Odometry")))
    cov = plain["pose_covariance"]
    m = np.frombuffer(cov["data"], dtype="<" + np.dtype(cov["dtype"]).str[1:]).reshape(cov["shape"])
    assert m.shape == (6, 6) and m[0, 0] == 1.0 and m[5, 5] == 36.0


def test_flat_36_covariance_is_rejected():
    plain = msgpack.unpackb(encode(sample("VehicleState")))
    plain["pose_covariance"] = to_builtins(NDArray.from_numpy(np.eye(6).reshape(36)))
    with pytest.raises(SchemaError, match="pose_covariance.*6, 6"):
        decode(msgpack.packb(plain), VehicleState)


def test_covariance_dtype_must_be_float():
    with pytest.raises(SchemaError, match="pose_covariance"):
        from_builtins({"pose_covariance": to_builtins(NDArray.from_numpy(np.zeros((6, 6), np.int32)))}, Odometry)


def test_nested_array_errors_carry_the_path():
    plain = msgpack.unpackb(encode(sample("UAVStatus")))
    cov = plain["current_state"]["twist_covariance"]
    cov["data"] = cov["data"][:-8]
    with pytest.raises(SchemaError, match=r"current_state\.twist_covariance"):
        decode(msgpack.packb(plain), UAVStatus)


# ---------------------------------------------------------------- geometry


def test_vector_and_quaternion_numpy_helpers():
    v = Vector3.from_array(np.array([1, 2, 3]))
    assert v == Vector3(x=1.0, y=2.0, z=3.0)
    assert np.array_equal(v.to_array(), [1.0, 2.0, 3.0])
    assert Quaternion() == Quaternion(w=1.0, x=0.0, y=0.0, z=0.0)
    q = Quaternion.from_array([0.0, 1.0, 0.0, 0.0])
    assert np.array_equal(q.to_array(), [0.0, 1.0, 0.0, 0.0])
    r, p, y = Quaternion.from_euler(0.1, -0.2, 2.5).to_euler()
    assert (r, p, y) == pytest.approx((0.1, -0.2, 2.5))
    assert Quaternion.from_yaw(0.7).to_euler()[2] == pytest.approx(0.7)


# ---------------------------------------------------------------- sensors


def test_image_round_trip_is_a_zero_copy_view_of_the_pixels():
    pixels = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    img = decode(encode(Image.from_numpy(pixels, "rgb8")), Image)
    assert (img.height, img.width, img.step) == (48, 64, 64 * 3)
    assert np.array_equal(img.to_numpy(), pixels)


def test_mono_image_may_be_two_dimensional():
    img = Image.from_numpy(np.zeros((4, 6), np.uint8), "mono8")
    assert decode(encode(img), Image).to_numpy().shape == (4, 6)


@pytest.mark.parametrize("change, field", [
    ({"height": 5}, "data"),
    ({"encoding": "mono8"}, "data"),
    ({"encoding": "yuv422_weird"}, "encoding"),
    ({"step": 7}, "step"),
])
def test_image_inconsistent_with_its_size_or_encoding_is_rejected(change, field):
    plain = msgpack.unpackb(encode(sample("Image")))
    plain.update(change)
    with pytest.raises(SchemaError, match=field):
        decode(msgpack.packb(plain), Image)


def test_image_dtype_must_match_encoding():
    plain = msgpack.unpackb(encode(sample("Image")))
    plain["data"] = to_builtins(NDArray.from_numpy(np.zeros((4, 5, 3), np.float32)))
    with pytest.raises(SchemaError, match="data.*uint8"):
        decode(msgpack.packb(plain), Image)


def test_point_cloud_per_point_arrays_must_match_the_point_count():
    with pytest.raises(ValueError, match="labels"):
        PointCloud.from_numpy(np.zeros((4, 3)), labels=[1, 2])
    plain = msgpack.unpackb(encode(sample("PointCloud")))
    plain["points"] = to_builtins(NDArray.from_numpy(np.zeros((4, 3), np.float64)))
    with pytest.raises(SchemaError, match="points.*float32"):
        decode(msgpack.packb(plain), PointCloud)


def test_empty_point_cloud_and_grid_are_valid():
    empty = decode(encode(PointCloud()), PointCloud)
    assert len(empty) == 0 and empty.points.to_numpy().shape == (0, 3)
    assert decode(encode(OccupancyGrid()), OccupancyGrid).data.to_numpy().shape == (0, 0)


def test_occupancy_grid_data_must_be_height_by_width():
    plain = msgpack.unpackb(encode(sample("OccupancyGrid")))
    plain["width"] = 5
    with pytest.raises(SchemaError, match="data"):
        decode(msgpack.packb(plain), OccupancyGrid)


def test_camera_info_pinhole_helper():
    info = CameraInfo.pinhole(640, 480, 500.0, 501.0, 320.0, 240.0)
    K = decode(encode(info), CameraInfo).K.to_numpy()
    assert K[0, 0] == 500.0 and K[1, 1] == 501.0 and K[0, 2] == 320.0 and K[2, 2] == 1.0
    assert info.P.to_numpy().shape == (3, 4)


def test_enum_names():
    assert DiagnosticStatus(level=DiagnosticStatus.STALE).level_name == "STALE"
    assert VioHealth(state=VioHealth.LOST).state_name == "LOST"
    assert PerceptionHealth.status_name(PerceptionHealth.INITIALIZING) == "INITIALIZING"
    assert LandedState.name(LandedState.ON_GROUND) == "ON_GROUND"
    assert VehicleState.LANDED_STATE_IN_AIR == VehicleStatus.LANDED_STATE_IN_AIR == LandedState.IN_AIR
    assert VehicleStatus(landed_state=LandedState.ON_GROUND).landed


# ---------------------------------------------------------------- vehicle


def test_setpoint_allows_nan_for_unused_parts():
    sp = TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=1.0),
                            position_m=Vector3(x=math.nan, y=math.nan, z=math.nan), yaw_rad=math.nan)
    back = decode(encode(sp), TrajectorySetpoint)
    assert math.isnan(back.position_m.x) and math.isnan(back.yaw_rad) and back.velocity_mps.x == 1.0


def test_vehicle_state_pose_view():
    s = sample("VehicleState")
    assert s.pose == Pose(position=s.position_m, orientation=s.orientation)
    assert not s.landed


# ---------------------------------------------------------------- missions

SURVEY_01 = """
{
  "mission_id": "survey_01",
  "takeoff_altitude_m": 5.0,
  "waypoints": [
    {"x": 0.0, "y": 0.0, "z": 5.0, "yaw_deg": 0.0},
    {"x": 10.0, "y": 0.0, "z": 5.0, "yaw_deg": 0.0},
    {"x": 10.0, "y": 10.0, "z": 5.0, "yaw_deg": 0.0},
    {"x": 0.0, "y": 0.0, "z": 5.0, "yaw_deg": 0.0}
  ],
  "waypoint_acceptance_radius_m": 0.5
}
"""


def test_seed_example_mission_is_accepted():
    m = parse_mission(SURVEY_01)
    assert m.mission_id == "survey_01" and m.takeoff_altitude_m == 5.0
    assert [(w.x, w.y, w.z) for w in m.waypoints] == [(0, 0, 5), (10, 0, 5), (10, 10, 5), (0, 0, 5)]
    assert m.waypoint_acceptance_radius_m == 0.5 and m.require_vio is None
    assert parse_mission(m.to_json()) == m


def test_mission_defaults():
    m = parse_mission('{"mission_id": "m", "waypoints": [{"x": 1, "y": 2, "z": 3}]}')
    assert m.takeoff_altitude_m == 3.0 and m.waypoint_acceptance_radius_m == 0.5
    assert m.waypoints[0] == Waypoint(x=1.0, y=2.0, z=3.0, yaw_deg=0.0)


def _mission_with(**changes):
    d = json.loads(SURVEY_01)
    d.update(changes)
    return json.dumps(d)


@pytest.mark.parametrize("text, field", [
    (json.dumps({"mission_id": "x", "takeoff_altitude_m": 5.0}), "waypoints"),
    (_mission_with(waypoints=[]), "waypoints"),
    (_mission_with(waypoint_acceptance_radius_m=-0.5), "waypoint_acceptance_radius_m"),
    (_mission_with(waypoint_acceptance_radius_m=0), "waypoint_acceptance_radius_m"),
    (_mission_with(takeoff_altitude_m=0.0), "takeoff_altitude_m"),
    (_mission_with(waypoints=[{"x": "ten", "y": 0.0, "z": 5.0}]), "waypoints[0].x"),
    (_mission_with(waypoints=[{"x": 1.0, "z": 5.0}]), "y"),
    (_mission_with(mission_id=7), "mission_id"),
])
def test_bad_mission_is_rejected_naming_the_field(text, field):
    with pytest.raises(SchemaError) as e:
        parse_mission(text)
    assert field in str(e.value) and str(e.value).startswith("Mission")


def test_mission_text_is_json_or_yaml_and_anything_else_a_schema_error():
    yaml_text = "mission_id: y1\nwaypoints:\n  - {x: 1.0, y: 2.0, z: 3.0}\n"
    assert parse_mission(yaml_text) == parse_mission('{"mission_id": "y1", "waypoints": [{"x": 1, "y": 2, "z": 3}]}')
    with pytest.raises(SchemaError, match="at least one waypoint"):
        parse_mission("waypoints: []")
    with pytest.raises(SchemaError, match="malformed"):
        parse_mission('{"waypoints": [}')
    with pytest.raises(SchemaError, match="neither JSON nor valid YAML"):
        parse_mission("waypoints: [x: {")
    with pytest.raises(SchemaError, match="YAML mapping"):
        parse_mission("just words")
    with pytest.raises(SchemaError, match="missing required field `waypoints`"):
        parse_mission("mission_id: no_waypoints\n")


def test_mission_files_json_and_yaml(tmp_path):
    (tmp_path / "m.json").write_text(SURVEY_01)
    (tmp_path / "m.yaml").write_text(
        "mission_id: y1\nwaypoints:\n  - {x: 1.0, y: 2.0, z: 3.0, yaw_deg: 90}\n")
    (tmp_path / "nan.yaml").write_text("waypoints:\n  - {x: .nan, y: 2.0, z: 3.0}\n")
    assert load_mission_file(tmp_path / "m.json").mission_id == "survey_01"
    assert load_mission_file(tmp_path / "m.yaml").waypoints[0].yaw_deg == 90.0
    with pytest.raises(SchemaError, match="x"):
        load_mission_file(tmp_path / "nan.yaml")
    with pytest.raises(SchemaError, match="cannot read"):
        load_mission_file(tmp_path / "missing.json")


# ---------------------------------------------------------------- mission messages and services


def test_mission_command_is_normalized_and_validated():
    assert MissionCommand(command=" hold ").command == "HOLD"
    assert decode(msgpack.packb({"command": "rtl"}), MissionCommand).command == "RTL"
    with pytest.raises(SchemaError, match="command.*ARM"):
        decode(msgpack.packb({"command": "FLY_AWAY"}), MissionCommand)
    with pytest.raises(SchemaError, match="mission_json"):
        decode(msgpack.packb({"command": "LOAD"}), MissionCommand)
    assert set(MissionCommand.COMMANDS) == {"ARM", "TAKEOFF", "START", "HOLD", "LAND", "RTL", "LOAD", "DISARM", "SET_CURRENT"}


def test_select_plugin_role_is_validated():
    with pytest.raises(SchemaError, match="role"):
        decode(msgpack.packb({"role": "planner", "name": "x"}), SelectPluginRequest)


def test_arm_request_must_say_arm_or_disarm():
    with pytest.raises(SchemaError, match="arm"):
        decode(msgpack.packb({}), ArmRequest)


def test_every_reply_type_is_a_reply():
    for name, cls in REGISTRY.items():
        if name.endswith(("Reply", "Result")) and name not in HEADERLESS:
            assert issubclass(cls, Reply), name


def test_empty_request_decodes_from_an_empty_map():
    assert decode(msgpack.packb({}), Empty) == Empty()


# ---------------------------------------------------------------- actions


def test_actions_table_is_complete_and_typed():
    assert set(ACTIONS) == {"takeoff", "land", "goto", "set_trajectory"}
    for spec in ACTIONS.values():
        goal, result, feedback = spec
        assert {goal, result, feedback} <= set(REGISTRY.values())
        assert issubclass(result, Reply)


def test_feedback_envelope_is_a_nested_plain_map_and_unwraps():
    fb = TakeoffFeedback(current_altitude_m=2.0, progress_percent=40.0)
    env = ActionFeedback.wrap("g1", fb, action="takeoff")
    plain = msgpack.unpackb(encode(env))
    assert plain["feedback"]["current_altitude_m"] == 2.0
    assert plain["feedback_type"] == "TakeoffFeedback@1" and plain["goal_id"] == "g1"
    back = decode(encode(env), ActionFeedback)
    assert back.unwrap() == fb and back.unwrap(TakeoffFeedback) == fb


def test_result_envelope_carries_success_and_unwraps():
    res = SetTrajectoryResult(success=False, message="obstacle", completion_status=TrajectoryStatus.STATUS_ABORTED)
    env = decode(encode(ActionResult.wrap("g2", res, GoalStatus.ABORTED, action="set_trajectory")), ActionResult)
    assert (env.success, env.message, env.status) == (False, "obstacle", GoalStatus.ABORTED)
    assert env.unwrap() == res
    assert GoalStatus.ABORTED in GoalStatus.TERMINAL and GoalStatus.name(GoalStatus.ABORTED) == "ABORTED"


def test_nested_trajectory_feedback_unwraps():
    fb = sample("SetTrajectoryFeedback")
    env = decode(encode(ActionFeedback.wrap("g", fb)), ActionFeedback)
    assert env.unwrap() == fb


def test_unwrap_with_mismatching_payload_is_a_schema_error():
    env = ActionFeedback(goal_id="g", feedback_type="TakeoffFeedback@1", feedback={"current_altitude_m": "high"})
    with pytest.raises(SchemaError, match="current_altitude_m"):
        env.unwrap()
    with pytest.raises(SchemaError):
        ActionFeedback(goal_id="g").unwrap()


def test_goal_reply_accepted_is_success():
    assert GoalReply(success=True, goal_id="x").accepted
    assert not GoalReply(success=False, message="busy").accepted


def test_goal_validation():
    with pytest.raises(SchemaError, match="target_altitude_m"):
        decode(msgpack.packb({"target_altitude_m": -1.0}), TakeoffGoal)
    with pytest.raises(SchemaError, match="position_m"):
        decode(msgpack.packb({"position_m": {"x": float("nan")}}), GoToPositionGoal)
    assert decode(msgpack.packb({"position_m": {"x": 1.0}}), GoToPositionGoal).yaw_rad is None


# ---------------------------------------------------------------- CLI


@pytest.fixture
def aero():
    from aeroperception.tools.cli import schema as cmd_schema

    parser = argparse.ArgumentParser(prog="aero")
    cmd_schema.register(parser.add_subparsers())

    def run(*argv):
        args = parser.parse_args(list(argv))
        return args.func(args)

    return run


def test_cli_schema_list(aero, capsys):
    assert aero("schema", "list") == 0
    out = capsys.readouterr().out
    for name, cls in REGISTRY.items():
        assert f"{name}@{cls.__schema_version__}" in out


def test_cli_schema_show(aero, capsys):
    assert aero("schema", "show", "SafetyStatus") == 0
    out = capsys.readouterr().out
    assert "battery_remaining" in out and "float | None" in out and "LEVEL_NOMINAL = 0" in out
    assert aero("schema", "show", "odometry@1") == 0  # case-insensitive fallback
    out = capsys.readouterr().out
    assert "pose_covariance: [6, 6]" in out and "NDArray | None" in out


def test_cli_schema_show_unknown_is_one_line_and_exit_2(aero, capsys):
    assert aero("schema", "show", "NoSuchThing") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "NoSuchThing" in err and "Traceback" not in err


def test_cli_schema_without_subcommand_exits_2(aero, capsys):
    assert aero("schema") == 2
    assert "list" in capsys.readouterr().err


def test_cli_schema_export_writes_valid_json_schemas(aero, tmp_path, capsys):
    out = tmp_path / "export"
    assert aero("schema", "export", "--out", str(out)) == 0
    files = sorted(out.glob("*.json"))
    assert [f.stem for f in files] == sorted(REGISTRY)
    for f in files:
        doc = json.loads(f.read_text())
        assert doc["$id"].startswith(f.stem + "@")
        assert doc["$ref"] == f"#/$defs/{REGISTRY[f.stem].__name__}" and doc["$defs"]
    vs = json.loads((out / "VehicleState.json").read_text())["$defs"]["VehicleState"]
    assert "position_m" in vs["properties"]


def test_cli_schema_export_to_unwritable_place_exits_2(aero, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert aero("schema", "export", "--out", str(blocker / "sub")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write" in err


# ---------------------------------------------------------------- codec thread safety, strictness

_CONCURRENT_FIRST_DECODE = r"""
import threading
from aeroperception.schemas import REGISTRY, decode, encode, SchemaError
payloads = []
for cls in REGISTRY.values():
    try:
        payloads.append((cls, encode(cls())))
    except Exception:
        payloads.append((cls, b"\x80"))
start = threading.Barrier(8)
def work():
    start.wait()
    for cls, data in payloads:
        try:
            decode(data, cls)
        except SchemaError:
            pass
ts = [threading.Thread(target=work) for _ in range(8)]
[t.start() for t in ts]
[t.join() for t in ts]
print("ok", len(payloads))
"""


def test_first_decode_from_many_threads_at_once_does_not_crash():
    """Issue 8 #1: msgspec 0.22 segfaulted when threads raced on a lazily created Decoder
    (4 of 40 fresh processes). Decoders are now built at registration; each run is a fresh
    interpreter so every decode is the first one."""
    import subprocess
    import sys

    for run in range(8):
        p = subprocess.run([sys.executable, "-c", _CONCURRENT_FIRST_DECODE], capture_output=True,
                           text=True, timeout=60)
        assert p.returncode == 0, f"run {run}: exit {p.returncode} (negative = signal): {p.stderr[-500:]}"
        assert p.stdout.startswith("ok ")


def test_every_registered_schema_has_its_codec_built_up_front():
    from aeroperception.schemas import REGISTRY
    from aeroperception.schemas._base import _codecs

    assert set(REGISTRY.values()) <= set(_codecs)


def test_strict_decode_refuses_unknown_fields_naming_them_and_lenient_ignores_them():
    import msgpack

    from aeroperception.schemas import LandGoal, SchemaError, TrajectorySetpoint, decode

    raw = msgpack.packb({"a": 1})
    assert decode(raw, TrajectorySetpoint) == TrajectorySetpoint()     # telemetry: forward compatible
    with pytest.raises(SchemaError, match="unknown field `a`"):
        decode(raw, TrajectorySetpoint, strict=True)
    with pytest.raises(SchemaError, match="unknown field `bogus`"):
        decode(msgpack.packb({"bogus": True, "junk": 2}), LandGoal, strict=True)
    nested = msgpack.packb({"position_m": {"x": 1.0, "w": 2.0}})
    with pytest.raises(SchemaError, match=r"unknown field `position_m.w`"):
        decode(nested, TrajectorySetpoint, strict=True)
    ok = decode(msgpack.packb({"position_m": {"x": 1.0}, "position_valid": True}), TrajectorySetpoint, strict=True)
    assert ok.position_m.x == 1.0


def test_mission_file_with_a_misspelt_field_is_refused(tmp_path):
    from aeroperception.schemas import SchemaError, load_mission_file, parse_mission

    good = '{"takeoff_altitude_m": 4, "waypoints": [{"x": 0, "y": 0, "z": 4}]}'
    assert parse_mission(good).takeoff_altitude_m == 4
    with pytest.raises(SchemaError, match="unknown field `takeoff_altitude`"):
        parse_mission('{"takeoff_altitude": 4, "waypoints": [{"x": 0, "y": 0, "z": 4}]}')
    with pytest.raises(SchemaError, match=r"unknown field `waypoints\[0\].zz`"):
        parse_mission('{"waypoints": [{"x": 0, "y": 0, "z": 4, "zz": 1}]}')
    f = tmp_path / "m.yaml"
    f.write_text("takeoff_altitud_m: 4\nwaypoints: [{x: 0, y: 0, z: 4}]\n")
    with pytest.raises(SchemaError, match="unknown field `takeoff_altitud_m`"):
        load_mission_file(f)
