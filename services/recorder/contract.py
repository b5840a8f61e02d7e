"""Contract of the recorder: which keys the presets record, and parameters.

It publishes nothing but its diagnostics; its inputs are whatever the preset selects.
"""
from dataclasses import replace

from aeroperception.services.runtime import Param, Topics

NAME = "recorder"
INPUTS = Topics()      # any key (Node.subscribe_raw): raw samples, recorded with their own encoding (see PRESETS)
OUTPUTS = Topics()

# The `essentials` preset of requirement LOG-1, its ROS topic names mapped to our keys:
#   /aeroperception/vehicle_state, /flight_mode -> state/vehicle (flight_mode is a field of it)
#   /aeroperception/battery -> fmu/out/battery_status; /diagnostics_agg -> diagnostics/agg;
#   the rest keep their names.
ESSENTIALS = (
    "state/vehicle",
    "fmu/out/battery_status",
    "state/visual_odometry",
    "state/vio_health",
    "perception/detections",
    "perception/objects",               # every live track with each detection frame (events derive from it)
    "perception/health",
    "mission/status",
    "mission/active_goal",
    "fmu/in/trajectory_setpoint",
    "fmu/out/vehicle_local_position",
    "fmu/out/vehicle_status",
    "diagnostics/agg",
)
# Raw images (~2 GB/min at full rate, LOG-1): only with record_images.
IMAGE_KEYS = ("sensors/camera/*/image",)
PRESETS = {"essentials": ESSENTIALS, "all": ("**",), "none": ()}

_PARAMS = [
    Param("preset", "essentials", choices=tuple(PRESETS), description="key set: essentials, all, or none (keys only)"),
    Param("keys", "", description="extra key expressions, comma-separated (e.g. sensors/imu,planner/**)"),
    Param("record_images", False, description="also record camera images (sensors/camera/*/image)"),
    Param("output_dir", "", description="where files go; '' = $AERO_RECORD_DIR or ~/.aero/recordings"),
    Param("prefix", "aero", description="file names: <prefix>_<UTC start>_<split>.mcap"),
    Param("max_bag_size", 1 << 30, "B", 1 << 16, 1 << 40, description="start a new file past this size"),
    Param("max_total_size", 0, "B", 0, 1 << 50,
          description="disk budget of the <prefix>_*.mcap files in output_dir (0 = none): before each new file "
                      "the oldest are deleted so they and a full new file fit; >= 2 x max_bag_size + chunk_size"),
    Param("flush_interval_s", 0.5, "s", 0.05, 1.0, description="chunks written at least this often (kill -9 loses <= this)"),
    Param("chunk_size", 1 << 20, "B", 1 << 12, 1 << 26, description="chunk written early when it reaches this size"),
    Param("compression", "zstd", choices=("zstd", "lz4", "none"), description="chunk compression"),
    Param("max_buffer_mb", 64.0, "MiB", 1.0, 4096.0, description="samples waiting for the disk; beyond it new ones are dropped and counted"),
    Param("params_timeout_s", 1.0, "s", 0.1, 10.0, description="wait for every service's parameters at start (metadata)"),
]
# Every parameter is read once, when the recording starts: a live set is refused, saying so.
PARAMS = [replace(p, start_only=True) for p in _PARAMS]
