"""Contract of gcs: keys in/out, calls, ports and parameters."""
from aeroperception.schemas import (
    ArmReply, ArmRequest, BatteryState, Empty, EstimatorStatus, GcsLink, GetMissionReply, GpsPosition, HomePosition,
    Joystick, LoadMissionReply,
    LoadMissionRequest, MissionCommand, MissionStatus, ObjectEvent, ParamList, ParamSet, ParamSetReply, Reply,
    SafetyStatus, SetModeReply, SetModeRequest, TrackedObjectArray, VehicleState, VehicleStatus, WaypointReached,
)
from aeroperception.services.runtime import Param, Queries, Query, Topic, Topics
from aeroperception.services.runtime.params import start_only_but

NAME = "gcs"
INPUTS = Topics(
    Topic("state/vehicle", VehicleState, note="pose (ENU), mode, armed, landed, battery"),
    Topic("fmu/out/battery_status", BatteryState, note="real battery for SYS_STATUS / BATTERY_STATUS"),
    Topic("fmu/out/home_position", HomePosition, note="the FC's home: geodetic <-> local (else the home_* params)"),
    Topic("fmu/out/vehicle_gps_position", GpsPosition, note="GPS_RAW_INT: the FC's fix (NO_GPS without one)"),
    Topic("fmu/out/estimator_status", EstimatorStatus,
          note="ESTIMATOR_STATUS (vision-only position: REL without ABS)"),
    Topic("mission/status", MissionStatus, note="MISSION_CURRENT"),
    Topic("mission/waypoint_reached", WaypointReached, note="MISSION_ITEM_REACHED"),
    Topic("safety/status", SafetyStatus, note="SYS_STATUS geofence bits; warnings/errors -> STATUSTEXT"),
    Topic("fmu/out/vehicle_status", VehicleStatus,
          note="only with identity=companion (GcsService.bind_selection): the flight controller's system id"),
    Topic("perception/objects/events", ObjectEvent, note="new / lost object -> STATUSTEXT"),
    Topic("perception/objects", TrackedObjectArray, note="confirmed objects -> ADSB_VEHICLE at 1 Hz (map labels)"),
)
OUTPUTS = Topics(
    Topic("gcs/link", GcsLink, 1.0, note="ground station heartbeat up/down; also at once on a change"),
    Topic("gcs/joystick", Joystick, note="MANUAL_CONTROL, as received"),
)
CALLS = Queries(
    Query("mission/srv/load", LoadMissionRequest, LoadMissionReply),
    Query("mission/srv/get", Empty, GetMissionReply, note="a mission loaded without us, for downloads"),
    Query("mission/srv/command", MissionCommand, Reply),
    Query("fmu/srv/arm", ArmRequest, ArmReply),
    Query("fmu/srv/set_mode", SetModeRequest, SetModeReply),
    Query("config/<service>/@params", None, ParamList),
    Query("config/<service>/@set", ParamSet, ParamSetReply),
)
ACTION_CALLS = ("mission/action/takeoff", "mission/action/goto")   # goals only (landing: mission/srv/command)

# Requirement GCS-1: bind 14551, send to the ground station at 14550 until one talks; then to every
# ground station heard (link.py).
DEFAULT_LOCAL_PORT = 14551
# Who gcs is on the ground-station link. In the sim profile the stack is the vehicle
# (the built-in sim has no ground-station link of its own). In the vehicle profile the flight
# controller (PX4 SITL or real, its own GCS link on 14550) is the vehicle and gcs is its onboard
# computer: MAV_COMP_ID_ONBOARD_COMPUTER of the FC's system, MAV_TYPE_ONBOARD_CONTROLLER heartbeats,
# no vehicle telemetry, and only messages addressed to that component (parameters also to 0).
IDENTITY_AUTOPILOT = "autopilot"
IDENTITY_COMPANION = "companion"
COMPANION_COMPONENT_ID = 191        # MAV_COMP_ID_ONBOARD_COMPUTER
DEFAULT_REMOTE_PORT = 14550
# Requirement GCS-4: default home (Tanashi, Tokyo), altitude 10 m AMSL. Only a fallback: once fmu publishes
# the flight controller's home (fmu/out/home_position), that is the home.
DEFAULT_HOME_LAT_DEG = 35.736805
DEFAULT_HOME_LON_DEG = 139.539676
DEFAULT_HOME_ALT_M = 10.0

_DECLARED = [
    Param("gcs_ip", "127.0.0.1", description="ground station address while none is heard"),
    Param("remote_port", DEFAULT_REMOTE_PORT, "", 1, 65535, description="ground station UDP port (initial)"),
    Param("local_port", DEFAULT_LOCAL_PORT, "", 0, 65535, description="UDP port we bind (0 = any)"),
    Param("bind_ip", "0.0.0.0", description="address we bind"),
    Param("identity", IDENTITY_AUTOPILOT, choices=(IDENTITY_AUTOPILOT, IDENTITY_COMPANION),
          description="autopilot: present the stack as the vehicle (sim profile); companion: as the flight "
                      "controller's onboard computer, component 191 of its system (vehicle profile)"),
    Param("system_id", 1, "", 1, 255, description="our MAVLink system id (companion: until fmu reports the FC's)"),
    Param("component_id", 1, "", 1, 255, description="our MAVLink component id (1 = autopilot; companion: 191)"),
    Param("telemetry_period_s", 0.9, "s", 0.05, 10.0, description="telemetry set period (GCS-2: 900 ms)"),
    Param("home_lat_deg", DEFAULT_HOME_LAT_DEG, "deg", -90.0, 90.0,
          description="home latitude (local ENU origin) until the flight controller's home is known"),
    Param("home_lon_deg", DEFAULT_HOME_LON_DEG, "deg", -180.0, 180.0, description="home longitude (fallback)"),
    Param("home_alt_m", DEFAULT_HOME_ALT_M, "m", -500.0, 9000.0, description="home altitude AMSL (fallback)"),
    Param("gcs_timeout_s", 3.5, "s", 0.5, 60.0, description="a ground station without a heartbeat this long (time "
          "gcs was running) gets no telemetry; none left -> gcs/link down; no verdict before this long after start"),
    Param("gcs_system_ids", "", description="system ids that count as ground stations besides MAV_TYPE_GCS "
          "heartbeats (comma-separated, e.g. '255,254')"),
    Param("mission_item_timeout_s", 0.25, "s", 0.05, 5.0, description="re-request a mission item after this"),
    Param("mission_retries", 5, "", 1, 50, description="re-requests of one item before giving up"),
    Param("max_mission_items", 500, "", 1, 10000, description="MISSION_COUNT above this is refused"),
    Param("param_services", "planner,mission,fmu,gcs,safety",
          description="services whose parameters are exposed under gcs's names (PX4-named aliases: params.py)"),
    Param("param_refresh_s", 5.0, "s", 0.5, 120.0, description="re-read config/<service>/@params this often"),
    Param("call_timeout_s", 3.0, "s", 0.2, 20.0, description="timeout of calls into the stack"),
    # MAVLink 2 signing (link.py). The key itself is never a parameter (parameters are readable on
    # config/gcs/@params and logged when set): a file, or the environment variable below. Read at start.
    Param("signing_key_file", "", description="MAVLink 2 signing key file (64 hex digits or 32 raw bytes); "
          "empty = env AERO_GCS_SIGNING_KEY (hex), else no signing. When set, unsigned packets are refused"),
    Param("signing_link_id", 0, "", 0, 255, description="MAVLink 2 signing link id of our packets"),
]
# gcs builds its link, schedulers and tables from its parameters at start: all but call_timeout_s
# are read there only, so a live set (aero param, a ground station's PARAM_SET) is refused, saying so.
PARAMS = start_only_but(_DECLARED, live=("call_timeout_s",))
SIGNING_KEY_ENV = "AERO_GCS_SIGNING_KEY"
