"""fmu: the only place that knows the flight controller (requirements FC-1 - FC-6).

MAVLink client (pymavlink) of PX4, ArduPilot or the built-in simulated vehicle, through one
code path. Telemetry becomes fmu/out/** and state/vehicle in ENU/FLU; setpoints from the
planner go out as SET_POSITION_TARGET_LOCAL_NED at 50 Hz, with a hold-position setpoint when
the planner is silent; arm / mode / e-stop are queryables that wait for the FC's ACK and the
heartbeat that confirms it. NED/FRD never leave this folder (conversions: services/mavlink/frames).
"""
