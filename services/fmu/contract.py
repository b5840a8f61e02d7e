"""Contract of fmu: keys in/out (ENU/FLU) and parameters."""
from aeroperception.schemas import (
    ArmReply, ArmRequest, Attitude, BatteryState, EmergencyStopReply, EmergencyStopRequest, EstimatorStatus,
    GpsPosition, HomePosition, Image, Imu, LocalPosition, Odometry, SetModeReply, SetModeRequest, TrajectorySetpoint,
    TrajectoryStatus, VehicleState, VehicleStatus,
)
from aeroperception.services.runtime import SMALL, Param, Queries, Query, Topic, Topics

NAME = "fmu"
# The FC's HEARTBEAT comes at 1 Hz; the status is republished from the latest telemetry at this
# rate (while the link is fresh) so a landed-state change or a late subscriber waits <= 0.2 s.
STATUS_RATE_HZ = 5.0
INPUTS = Topics(
    Topic("fmu/in/trajectory_setpoint", TrajectorySetpoint, note="from planner, ENU", strict=True),
    Topic("state/visual_odometry", Odometry, note="from vio, injected as ODOMETRY (VISION)"),
    Topic("planner/status", TrajectoryStatus, note="ERROR -> stop following the planner, hold"),
    Topic("sensors/camera/left/image", Image, note="only with publish_imu: camera / IMU stamp alignment"),
)
LIVELINESS = ("planner",)   # gone -> brake and hold at once
OUTPUTS = Topics(
    Topic("fmu/out/vehicle_local_position", LocalPosition, 50.0),
    Topic("fmu/out/vehicle_attitude", Attitude, 50.0),
    Topic("fmu/out/vehicle_status", VehicleStatus, STATUS_RATE_HZ, note="and at once on a heartbeat that changes it"),
    Topic("fmu/out/battery_status", BatteryState, 1.0),
    Topic("fmu/out/home_position", HomePosition, 1.0, note="FC's home (HOME_POSITION), also at once on a change"),
    Topic("fmu/out/sensor_combined", Imu, note="FC IMU (HIGHRES_IMU), FLU, at the FC's stream rate"),
    Topic("fmu/out/vehicle_gps_position", GpsPosition, 1.0,
          note="the FC's GPS receiver (GPS_RAW_INT), NO_GPS/NO_FIX too"),
    Topic("fmu/out/estimator_status", EstimatorStatus, 1.0, note="the FC's estimator flags (ESTIMATOR_STATUS)"),
    Topic("fmu/out/vehicle_ground_truth", VehicleState, note="a simulated FC's ground truth (HIL_STATE_QUATERNION at "
          "ground_truth_rate_hz) about its local origin, on sensors/imu's clock: the simulator's follow mode renders from it"),
    Topic("sensors/imu", Imu, note="only with publish_imu (real hardware): HIGHRES_IMU as received"),
    # SMALL (DATA_HIGH, express): on a slow link to a ground host, state must not wait behind images
    # and scans or bulk telemetry: the ground mission calls 0.5 s without it an fmu outage.
    Topic("state/vehicle", VehicleState, 50.0, qos=SMALL,
          note="pose (ENU), velocity, mode, armed, landed, battery, FC link"),
)
SERVICES = Queries(    # locked=False: each waits for the FC's ACK and heartbeat
    Query("fmu/srv/arm", ArmRequest, ArmReply, locked=False),
    Query("fmu/srv/set_mode", SetModeRequest, SetModeReply, locked=False),
    Query("fmu/srv/emergency_stop", EmergencyStopRequest, EmergencyStopReply, locked=False),
)
# Keys only some runs bind (FmuService.bind_selection): with publish_imu, the FC's IMU republished
# and the camera stamps it is checked against.
PUBLISH_IMU_ONLY = ("sensors/imu", "sensors/camera/left/image")
DEFAULT_FCU_URL = "udpin:127.0.0.1:14540"   # PX4 SITL / the built-in sim send here
PARAMS = [
    Param("offboard_rate_hz", 50.0, "Hz", 20.0, 100.0, description="SET_POSITION_TARGET_LOCAL_NED stream rate"),
    Param("setpoint_timeout_s", 0.3, "s", 0.02, 2.0,
          description="planner silent this long -> brake and hold (liveliness loss / ERROR: at once)"),
    Param("resume_setpoints", 5, "", 1, 100,
          description="consecutive fresh valid setpoints before following the planner again after a hold"),
    Param("setpoint_max_age_s", 0.5, "s", 0.05, 5.0,
          description="setpoint stamp older than fmu's newest state by this -> stale, not forwarded"),
    Param("brake_speed_mps", 0.15, "m/s", 0.02, 2.0,
          description="brake (zero velocity) until slower than this, then hold where the vehicle is"),
    Param("brake_timeout_s", 5.0, "s", 0.5, 30.0, description="hold wherever the vehicle is after braking this long"),
    Param("max_velocity_mps", 15.0, "m/s", 0.5, 50.0, description="envelope: faster setpoints are refused"),
    Param("max_acceleration_mps2", 10.0, "m/s^2", 0.5, 50.0, description="envelope: acceleration setpoint limit"),
    Param("max_distance_m", 1000.0, "m", 1.0, 100000.0,
          description="envelope: position setpoint horizontal distance from the local origin"),
    Param("max_altitude_m", 500.0, "m", 1.0, 10000.0, description="envelope: position setpoint z (up) above the origin"),
    Param("min_altitude_m", -10.0, "m", -1000.0, 0.0, description="envelope: position setpoint z (up) lower limit"),
    Param("max_yaw_rate_radps", 6.0, "rad/s", 0.1, 20.0, description="envelope: yaw rate setpoint limit"),
    Param("fcu_peer", "", description="udpin: only this HOST:PORT is the flight controller ('' = lock onto the "
                                      "first autopilot HEARTBEAT)", start_only=True),
    Param("fcu_relock_s", 3.0, "s", 0.0, 600.0, start_only=True,
          description="udpin: locked FC silent this long -> lock onto the next autopilot HEARTBEAT (0: never)"),
    Param("reboot_gap_s", 2.0, "s", 0.5, 60.0,
          description="FC heartbeat missing this long (or time_boot_ms going back) -> redo the link set-up"),
    Param("link_timeout_s", 0.4, "s", 0.1, 5.0, description="no MAVLink this long -> link stale, ERROR (reported within 0.5 s)"),
    Param("vio_timeout_s", 1.0, "s", 0.1, 5.0, description="older VIO is not injected"),
    Param("home_request_period_s", 10.0, "s", 1.0, 120.0,
          description="ask the FC for HOME_POSITION this often until it sends one"),
    Param("command_timeout_s", 3.0, "s", 0.5, 20.0, description="wait for ACK + heartbeat confirmation"),
    Param("offboard_warmup_s", 1.5, "s", 0.0, 10.0,
          description="an OFFBOARD request waits (within command_timeout_s) until fmu has streamed setpoints "
                      "this long, and is re-sent while the FC answers TEMPORARILY_REJECTED (PX4 needs a stream "
                      "before it accepts OFFBOARD)"),
    Param("ground_truth_rate_hz", 100.0, "Hz", 0.0, 250.0, start_only=True,
          description="ask a simulated FC for its ground truth (HIL_STATE_QUATERNION) at this rate "
                      "(0: never; a real FC has none and sends nothing)"),
    Param("global_origin", "", start_only=True,
          description="'LAT,LON,ALT_M' (WGS-84 deg, m): sent to the FC as its local origin (SET_GPS_GLOBAL_ORIGIN) "
                      "once it has a local position, until it reports a home; GPS-denied, PX4 has no global "
                      "position without it (Hold, Return, arming in Hold and the geofence need one). PX4's EKF2 "
                      "moves its local height by a change of the origin's altitude: give the altitude it already "
                      "takes as its origin's (0 on a fresh boot). '' = never"),
    Param("publish_imu", False, start_only=True,
          description="republish HIGHRES_IMU as sensors/imu (real hardware, no sim)"),
    Param("source_system", 1, "", 1, 255, start_only=True, description="our MAVLink system id"),
    Param("source_component", 191, "", 1, 255, start_only=True,
          description="our component id (191 = onboard computer)"),
]
