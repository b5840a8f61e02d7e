"""Vehicle state, flight-controller telemetry and setpoints.

VehicleState is the one state message (state/vehicle): the vehicle state of requirement FC-4 and
IF-2's State merged. The fmu/out/* types mirror the PX4 topics FC-4 names, already converted
to ENU/FLU by the fmu service: nothing in here is ever NED/FRD (only fmu and gcs see NED, through
one conversion module).
"""
from __future__ import annotations

import msgspec

from ._base import Header, Message, NDArray, schema
from ._checks import check_choice, check_dtype, enum_names
from .geometry import Pose, Quaternion, Vector3
from .safety import SafetyStatus

__all__ = [
    "LandedState", "VehicleState", "TrajectorySetpoint", "ControlOutput", "UAVMode", "UAVStatus",
    "VehicleStatus", "LocalPosition", "Attitude", "HomePosition", "GpsPosition", "EstimatorStatus",
]


class LandedState:
    """MAVLink MAV_LANDED_STATE values, shared by VehicleState and VehicleStatus."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4

    @classmethod
    def name(cls, value: int) -> str:
        return enum_names(cls).get(value, str(value))


class _LandedStateConstants:
    # Mixed into the Structs below so `VehicleState.LANDED_STATE_IN_AIR` reads naturally.
    __slots__ = ()
    LANDED_STATE_UNDEFINED = LandedState.UNDEFINED
    LANDED_STATE_ON_GROUND = LandedState.ON_GROUND
    LANDED_STATE_IN_AIR = LandedState.IN_AIR
    LANDED_STATE_TAKEOFF = LandedState.TAKEOFF
    LANDED_STATE_LANDING = LandedState.LANDING


@schema("VehicleState", 1)
class VehicleState(Message, _LandedStateConstants, kw_only=True):
    """Everything the autonomy needs about the vehicle, at 50 Hz (state/vehicle).

    Position, velocity, acceleration in the world ENU frame (`header.frame_id`, e.g. "map");
    `orientation` rotates body FLU into world ENU; `angular_velocity_radps` is body FLU.
    roll/pitch/yaw are derived from `orientation` for convenience (yaw 0 = East, CCW positive).
    Covariances are 6x6 (x, y, z, roll, pitch, yaw / vx, vy, vz, wx, wy, wz), None when unknown.
    `connected` is False when the flight-controller link is stale: then treat the rest as old.
    Battery quantities are None when unknown.
    """

    header: Header = msgspec.field(default_factory=Header)
    position_m: Vector3 = msgspec.field(default_factory=Vector3)
    velocity_mps: Vector3 = msgspec.field(default_factory=Vector3)
    acceleration_mps2: Vector3 = msgspec.field(default_factory=Vector3)
    orientation: Quaternion = msgspec.field(default_factory=Quaternion)
    angular_velocity_radps: Vector3 = msgspec.field(default_factory=Vector3)
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    pose_covariance: NDArray | None = None
    twist_covariance: NDArray | None = None
    estimator_name: str = ""
    confidence: float = 0.0
    flight_mode: str = ""
    armed: bool = False
    landed_state: int = LandedState.UNDEFINED
    battery_remaining: float | None = None
    battery_voltage_v: float | None = None
    connected: bool = False

    __shapes__ = {"pose_covariance": (6, 6), "twist_covariance": (6, 6)}

    def __post_init__(self) -> None:
        super().__post_init__()
        check_dtype("pose_covariance", self.pose_covariance, ("float64", "float32"))
        check_dtype("twist_covariance", self.twist_covariance, ("float64", "float32"))

    @property
    def pose(self) -> Pose:
        return Pose(position=self.position_m, orientation=self.orientation)

    @property
    def landed(self) -> bool:
        return self.landed_state == LandedState.ON_GROUND


@schema("TrajectorySetpoint", 1)
class TrajectorySetpoint(Message, kw_only=True):
    """Reference for the flight controller (fmu/in/trajectory_setpoint, 50 Hz), ENU.

    IF-2's TrajectorySetpoint; replaces px4 TrajectorySetpoint (fmu converts to NED). Only the
    parts whose `*_valid` flag is set are used; unused values may be anything, NaN included.
    """

    header: Header = msgspec.field(default_factory=Header)
    position_valid: bool = False
    velocity_valid: bool = False
    acceleration_valid: bool = False
    jerk_valid: bool = False
    yaw_valid: bool = False
    yaw_rate_valid: bool = False
    position_m: Vector3 = msgspec.field(default_factory=Vector3)
    velocity_mps: Vector3 = msgspec.field(default_factory=Vector3)
    acceleration_mps2: Vector3 = msgspec.field(default_factory=Vector3)
    jerk_mps3: Vector3 = msgspec.field(default_factory=Vector3)
    yaw_rad: float = 0.0
    yaw_rate_radps: float = 0.0

    @classmethod
    def hold(cls, position_m, yaw_rad: float) -> "TrajectorySetpoint":
        """Hold here: position target with zero velocity (the planner's and fmu's hold)."""
        return cls(position_valid=True, velocity_valid=True, yaw_valid=True,
                   position_m=Vector3.from_array(position_m), velocity_mps=Vector3(), yaw_rad=yaw_rad)


@schema("ControlOutput", 1)
class ControlOutput(Message, kw_only=True):
    """A controller's command to the flight controller; `control_mode` says which fields apply.

    IF-2's ControlOutput (the source's two `thrust_normalized` lines are one field here). Position and
    velocity are ENU; orientation is ENU <- FLU; body rates are FLU.
    """

    header: Header = msgspec.field(default_factory=Header)
    control_mode: int = 0
    CONTROL_MODE_POSITION = 0
    CONTROL_MODE_VELOCITY = 1
    CONTROL_MODE_ATTITUDE = 2
    CONTROL_MODE_BODY_RATE = 3

    position_m: Vector3 = msgspec.field(default_factory=Vector3)
    yaw_rad: float = 0.0
    velocity_mps: Vector3 = msgspec.field(default_factory=Vector3)
    yaw_rate_radps: float = 0.0
    orientation: Quaternion = msgspec.field(default_factory=Quaternion)
    body_rates_radps: Vector3 = msgspec.field(default_factory=Vector3)
    thrust_normalized: float = 0.0  # 0..1
    controller_name: str = ""


@schema("UAVMode", 1)
class UAVMode(Message, kw_only=True):
    """High-level operational state and control mode, with what transitions are allowed now."""

    header: Header = msgspec.field(default_factory=Header)
    state: int = 0
    STATE_IDLE = 0
    STATE_ARMED = 1
    STATE_TAKING_OFF = 2
    STATE_HOVERING = 3
    STATE_FLYING = 4
    STATE_LANDING = 5
    STATE_LANDED = 6
    STATE_EMERGENCY = 7

    control_mode: int = 0
    MODE_MANUAL = 0
    MODE_POSITION = 1
    MODE_VELOCITY = 2
    MODE_TRAJECTORY = 3
    MODE_OFFBOARD = 4

    submode: str = ""  # e.g. "formation", "inspection", "rth"
    armed: bool = False
    can_arm: bool = False
    can_takeoff: bool = False
    can_land: bool = False


@schema("UAVStatus", 1)
class UAVStatus(Message, kw_only=True):
    """Everything about one UAV for monitoring (a GCS dashboard). IF-2's UAVStatus; battery is a
    0..1 fraction and the latency is seconds (SI), unlike the source's percent and ms.

    px4_latency_s: the flight controller's state, its sample to the mission (None before one).
    The source's gcs latency is left out: nothing here times the ground link (the ground station
    times it with TIMESYNC, which gcs only answers); gcs/link's last_heartbeat_age_s says how
    recently the ground station was heard."""

    header: Header = msgspec.field(default_factory=Header)
    uav_id: str = ""
    uav_name: str = ""
    current_state: VehicleState = msgspec.field(default_factory=VehicleState)
    current_mode: UAVMode = msgspec.field(default_factory=UAVMode)
    active_estimator: str = ""
    active_controller: str = ""
    active_trajectory_generator: str = ""
    safety_status: SafetyStatus = msgspec.field(default_factory=SafetyStatus)
    battery_remaining: float | None = None
    cpu_percent: float = 0.0
    memory_percent: float = 0.0
    px4_connected: bool = False
    gcs_connected: bool = False
    px4_latency_s: float | None = None
    current_mission_id: str = ""
    mission_progress_percent: float = 0.0


@schema("VehicleStatus", 1)
class VehicleStatus(Message, _LandedStateConstants, kw_only=True):
    """Flight-controller status (fmu/out/vehicle_status, 5 Hz): mode, arming, landed, failsafe.

    Replaces px4 VehicleStatus. `nav_state` is the autopilot-neutral mode name ("OFFBOARD",
    "HOLD", "POSCTL", "LAND", "RTL", "TAKEOFF", "MISSION", "MANUAL", ...); `custom_mode` is the
    raw MAVLink HEARTBEAT value, and for PX4 `px4_main_mode`/`px4_sub_mode` are its decoded parts
    (custom_mode = main << 16 | sub << 24), 0 otherwise.
    """

    header: Header = msgspec.field(default_factory=Header)
    nav_state: str = ""
    custom_mode: int = 0
    px4_main_mode: int = 0
    px4_sub_mode: int = 0
    armed: bool = False
    landed_state: int = LandedState.UNDEFINED
    failsafe: bool = False
    system_id: int = 1
    autopilot: str = ""  # "px4", "ardupilot"

    @property
    def landed(self) -> bool:
        return self.landed_state == LandedState.ON_GROUND


@schema("LocalPosition", 1)
class LocalPosition(Message, kw_only=True):
    """Flight controller's local position estimate in ENU (fmu/out/vehicle_local_position, 50 Hz).

    Replaces px4 VehicleLocalPosition. `yaw_rad` is the ENU yaw (0 = East, CCW positive), i.e. PX4's
    `heading` converted. `distance_bottom_m` is height above ground when a range sensor knows it.
    """

    header: Header = msgspec.field(default_factory=Header)
    position_m: Vector3 = msgspec.field(default_factory=Vector3)
    velocity_mps: Vector3 = msgspec.field(default_factory=Vector3)
    acceleration_mps2: Vector3 = msgspec.field(default_factory=Vector3)
    yaw_rad: float = 0.0
    position_valid: bool = False
    velocity_valid: bool = False
    distance_bottom_m: float | None = None


@schema("Attitude", 1)
class Attitude(Message, kw_only=True):
    """Flight controller's attitude (fmu/out/vehicle_attitude, 50 Hz): `orientation` rotates body
    FLU into world ENU; `angular_velocity_radps` is body FLU. Replaces px4 VehicleAttitude."""

    header: Header = msgspec.field(default_factory=Header)
    orientation: Quaternion = msgspec.field(default_factory=Quaternion)
    angular_velocity_radps: Vector3 = msgspec.field(default_factory=Vector3)


@schema("HomePosition", 1)
class HomePosition(Message, kw_only=True):
    """The flight controller's home (fmu/out/home_position, on change and 1 Hz, latched): where the
    local ENU frame sits on the Earth. Replaces px4 HomePosition / MAVLink HOME_POSITION.

    `latitude_deg`/`longitude_deg` are WGS84, `altitude_amsl_m` above mean sea level; `position_m`
    is the same point in the local ENU frame (`header.frame_id`, e.g. "map"). The local origin is
    not necessarily home (PX4: the EKF origin), so geodetic <-> local conversions about home must
    add/subtract `position_m`. Altitudes "relative to home" (MAVLink relative_alt, global-relative
    mission frames) are above `altitude_amsl_m`, i.e. local z minus `position_m.z`.
    """

    header: Header = msgspec.field(default_factory=Header)
    latitude_deg: float = 0.0
    longitude_deg: float = 0.0
    altitude_amsl_m: float = 0.0
    position_m: Vector3 = msgspec.field(default_factory=Vector3)


@schema("GpsPosition", 1)
class GpsPosition(Message, kw_only=True):
    """The flight controller's GPS receiver as it reports it (fmu/out/vehicle_gps_position, MAVLink
    GPS_RAW_INT, ~1-10 Hz). Replaces px4 SensorGps. Not the fused position (that is state/vehicle):
    a ground station shows this to say whether there is a GPS and what fix it has.

    `fix_type` is MAVLink's GPS_FIX_TYPE (NO_GPS 0: no receiver, NO_FIX 1: receiver without a fix,
    FIX_2D 2, FIX_3D 3, DGPS 4, RTK_FLOAT 5, RTK_FIXED 6, ...). Position fields are None without a
    fix; unknown accuracies / satellite count are None. `course_rad` is the ENU course over ground
    (0 = East, CCW positive, like yaw_rad), None when the receiver does not know it.
    """

    FIX_NO_GPS = 0
    FIX_NO_FIX = 1
    FIX_2D = 2
    FIX_3D = 3
    FIX_DGPS = 4
    FIX_RTK_FLOAT = 5
    FIX_RTK_FIXED = 6

    header: Header = msgspec.field(default_factory=Header)
    fix_type: int = FIX_NO_GPS
    latitude_deg: float | None = None
    longitude_deg: float | None = None
    altitude_amsl_m: float | None = None
    hdop: float | None = None              # horizontal dilution of precision (unitless)
    vdop: float | None = None              # vertical dilution of precision (unitless)
    horizontal_accuracy_m: float | None = None  # the receiver's 1-sigma position uncertainty
    vertical_accuracy_m: float | None = None
    ground_speed_mps: float | None = None
    course_rad: float | None = None
    satellites_visible: int | None = None

    def __post_init__(self) -> None:
        check_choice("fix_type", self.fix_type, range(9))   # GPS_FIX_TYPE 0..8

    @property
    def has_fix(self) -> bool:
        return self.fix_type >= self.FIX_2D


@schema("EstimatorStatus", 1)
class EstimatorStatus(Message, kw_only=True):
    """The flight controller's estimator health (fmu/out/estimator_status, MAVLink ESTIMATOR_STATUS,
    ~1 Hz). Replaces px4 EstimatorStatusFlags. `flags` is MAVLink's ESTIMATOR_STATUS_FLAGS bitmask
    (the constants below): position from vision alone shows as POS_HORIZ_REL without POS_HORIZ_ABS.
    Test ratios (innovation / gate, < 1 passes) and accuracies are None when unknown.
    """

    ATTITUDE = 1
    VELOCITY_HORIZ = 2
    VELOCITY_VERT = 4
    POS_HORIZ_REL = 8
    POS_HORIZ_ABS = 16
    POS_VERT_ABS = 32
    POS_VERT_AGL = 64
    CONST_POS_MODE = 128
    PRED_POS_HORIZ_REL = 256
    PRED_POS_HORIZ_ABS = 512
    GPS_GLITCH = 1024
    ACCEL_ERROR = 2048

    header: Header = msgspec.field(default_factory=Header)
    flags: int = 0
    velocity_test_ratio: float | None = None
    position_horizontal_test_ratio: float | None = None
    position_vertical_test_ratio: float | None = None
    magnetometer_test_ratio: float | None = None
    height_above_ground_test_ratio: float | None = None
    airspeed_test_ratio: float | None = None
    position_horizontal_accuracy_m: float | None = None
    position_vertical_accuracy_m: float | None = None
