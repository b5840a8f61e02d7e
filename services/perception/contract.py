"""Contract of the perception coordinator: keys in/out and parameters."""
from aeroperception.schemas import DiagnosticStatus, PerceptionHealth, VioHealth
from aeroperception.services.runtime import Param, Topic, Topics

NAME = "perception"
INPUTS = Topics(
    Topic("state/vio_health", VioHealth, note="vio's tracking state"),
    Topic("perception/detector_health", DiagnosticStatus, note="detector (DET-2: OK / WARN / ERROR)"),
    Topic("diagnostics/lidar", DiagnosticStatus, note="the LiDAR obstacle service's own health"),
)
OUTPUTS = Topics(
    Topic("perception/health", PerceptionHealth, 1.0, note="and at once on every change of a status"),
)
PARAMS = [
    Param("sources", "vio,detector,lidar",
          description="sources this stack runs (aero up: those its --sensors feed); the others are NOT_CONFIGURED"),
    Param("vio_timeout_s", 3.0, "s", 0.5, 30.0, description="no state/vio_health this long -> VIO UNKNOWN (unhealthy)"),
    Param("detector_timeout_s", 3.0, "s", 0.5, 30.0, description="no detector health this long -> detector UNKNOWN"),
    Param("lidar_timeout_s", 3.0, "s", 0.5, 30.0, description="no lidar diagnostics this long -> lidar UNKNOWN"),
    Param("publish_rate_hz", 1.0, "Hz", 0.2, 20.0, description="perception/health repeat rate (changes go out at once)"),
    Param("check_rate_hz", 10.0, "Hz", 1.0, 50.0, description="how often timeouts are checked"),
]
