"""Contract of fmu: keys in/out (ENU/FLU) and parameters."""
from aeroperception.schemas import (
    ArmReply, ArmRequest, Attitude, BatteryState, EmergencyStopReply, EmergencyStopRequest, HomePosition, Imu,
    LocalPosition, Odometry, SetModeReply, SetModeRequest, TrajectorySetpoint, TrajectoryStatus, VehicleState, VehicleStatus,
)
from aeroperception.services.runtime import Param

NAME = "fmu"
INPUTS = {
    "fmu/in/trajectory_setpoint": TrajectorySetpoint,   # from planner, ENU
    "state/visual_odometry": Odometry,                  # from vio, injected as ODOMETRY (VISION)
    "planner/status": TrajectoryStatus,                 # ERROR -> stop following the planner, hold
    "aero/alive/<vehicle>/planner": None,               # liveliness: gone -> hold at once
}
OUTPUTS = {
    "fmu/out/vehicle_local_position": LocalPosition,    # 50 Hz
    "fmu/out/vehicle_attitude": Attitude,               # 50 Hz
    "fmu/out/vehicle_status": VehicleStatus,            # 5 Hz
    "fmu/out/battery_status": BatteryState,             # 1 Hz
    "fmu/out/home_position": HomePosition,              # FC's home (HOME_POSITION): on change + 1 Hz (latched)
    "fmu/out/sensor_combined": Imu,                     # FC IMU (HIGHRES_IMU), FLU
    "sensors/imu": Imu,                                 # only with publish_imu (real hardware)
    "state/vehicle": VehicleState,                      # 50 Hz
}
SERVICES = {
    "fmu/srv/arm": (ArmRequest, ArmReply),
    "fmu/srv/set_mode": (SetModeRequest, SetModeReply),
    "fmu/srv/emergency_stop": (EmergencyStopRequest, EmergencyStopReply),
}
DEFAULT_FCU_URL = "udpin:127.0.0.1:14540"   # PX4 SITL / the built-in sim send here
PARAMS = [
    Param("offboard_rate_hz", 50.0, "Hz", 20.0, 100.0, description="SET_POSITION_TARGET_LOCAL_NED stream rate"),
    Param("setpoint_timeout_s", 0.1, "s", 0.02, 1.0, description="planner silent this long -> hold position"),
    Param("link_timeout_s", 0.5, "s", 0.1, 5.0, description="no MAVLink this long -> link stale, ERROR"),
    Param("vio_timeout_s", 1.0, "s", 0.1, 5.0, description="older VIO is not injected"),
    Param("home_request_period_s", 10.0, "s", 1.0, 120.0,
          description="ask the FC for HOME_POSITION this often until it sends one"),
    Param("command_timeout_s", 3.0, "s", 0.5, 20.0, description="wait for ACK + heartbeat confirmation"),
    Param("publish_imu", False, description="republish HIGHRES_IMU as sensors/imu (real hardware, no sim)"),
    Param("source_system", 1, "", 1, 255, description="our MAVLink system id"),
    Param("source_component", 191, "", 1, 255, description="our component id (191 = onboard computer)"),
]
