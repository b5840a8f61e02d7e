"""Contract of viz (Rerun live view): keys it watches and its parameters.

viz only reads: it publishes nothing but its own diagnostics. Each input key is sampled at the
rate its parameter says (0 = not subscribed at all), then handed newest-wins to a worker, so a
slow or absent viewer costs dropped frames (counted), never a queue or a slower stack.
"""
from aeroperception.schemas import (
    BatteryState, Detection2DArray, DiagnosticStatus, Empty, GetMissionReply, Image, MissionStatus,
    MissionGoal, OccupancyGrid, Odometry, PointCloud, SafetyStatus, TrajectorySetpoint, TrajectoryStatus,
    TrackedObjectArray, VehicleState, VioHealth, WaypointReached,
)
from aeroperception.services.runtime import Param, Queries, Query, Topic, Topics
from aeroperception.services.runtime.params import start_only_but

NAME = "viz"
INPUTS = Topics(
    Topic("state/vehicle", VehicleState, note="pose, trajectory, altitude / speed / battery series"),
    Topic("sim/truth/state", VehicleState, note="sim only: the true pose and track beside it (show_truth)"),
    Topic("state/visual_odometry", Odometry, note="VIO pose, track and covariance ellipsoid"),
    Topic("state/vio_health", VioHealth),
    Topic("sensors/camera/left/image", Image, note="<= image_rate_hz"),
    Topic("sensors/camera/right/image", Image),
    Topic("perception/detections", Detection2DArray, note="boxes on the image of the same stamp"),
    Topic("sim/truth/boxes", Detection2DArray, note="sim only (show_truth)"),
    Topic("perception/obstacles", PointCloud, note='ENU "map"'),
    Topic("perception/ground", PointCloud),
    Topic("perception/costmap", OccupancyGrid, note="drawn on the ground plane"),
    Topic("perception/objects", TrackedObjectArray, note="tracks as labelled points and their history lines"),
    Topic("mission/status", MissionStatus, note="state changes as text; distance to goal"),
    Topic("mission/active_goal", MissionGoal),
    Topic("mission/waypoint_reached", WaypointReached),
    Topic("planner/status", TrajectoryStatus),
    Topic("fmu/in/trajectory_setpoint", TrajectorySetpoint, note="the planner's velocity as an arrow on the vehicle"),
    Topic("fmu/out/battery_status", BatteryState),
    Topic("safety/status", SafetyStatus),
    Topic("diagnostics/*", DiagnosticStatus, note="level/message changes as text; loop timing series"),
)
OUTPUTS = Topics()
CALLS = Queries(
    Query("mission/srv/get", Empty, GetMissionReply, note="the mission's waypoints, when its id changes"),
)

_DECLARED = [
    # where the view goes (any combination; none at all = data is converted and dropped)
    Param("web_port", 9090, "", 0, 65535, description="serve the web viewer on this HTTP port (0 = off); implies the gRPC server"),
    Param("grpc_port", 9876, "", 0, 65535, description="port of the gRPC server viewers connect to (rerun+http://HOST:PORT/proxy)"),
    Param("serve_grpc", False, description="serve gRPC even without the web viewer (native viewers on other machines)"),
    Param("bind_ip", "0.0.0.0", description="address the gRPC server listens on (127.0.0.1 = this machine only)"),
    Param("server_memory_limit", "256MiB", description="gRPC server buffer for late viewers; oldest data dropped beyond"),
    Param("viewer_url", "", description="stream to a running viewer, e.g. rerun+http://laptop:9876/proxy ('' = off)"),
    Param("spawn", False, description="start a native Rerun viewer on this machine and stream to it"),
    Param("save_path", "", description="also write everything to this .rrd file ('' = off)"),
    # what is shown
    Param("show_truth", True, description="sim: draw sim/truth (pose, track, boxes) beside the estimate"),
    Param("pose_rate_hz", 10.0, "Hz", 0.0, 100.0, description="vehicle / truth / VIO poses (0 = off)"),
    Param("image_rate_hz", 5.0, "Hz", 0.0, 10.0, description="camera images per camera (0 = off)"),
    Param("image_jpeg_quality", 75, "", 0, 100, description="JPEG-compress images for the viewer (0 = raw pixels)"),
    Param("cloud_rate_hz", 5.0, "Hz", 0.0, 20.0, description="obstacle / ground point clouds (0 = off)"),
    Param("costmap_rate_hz", 2.0, "Hz", 0.0, 10.0, description="costmap grid (0 = off)"),
    Param("setpoint_rate_hz", 5.0, "Hz", 0.0, 50.0, description="planner setpoint arrow (0 = off)"),
    Param("objects_rate_hz", 5.0, "Hz", 0.0, 20.0, description="tracked objects and their history (0 = off)"),
    Param("trail_period_s", 0.5, "s", 0.05, 10.0, description="trajectory lines are re-sent this often"),
    Param("trail_max_points", 5000, "", 10, 100000, description="points kept per trajectory line (oldest dropped)"),
    Param("flush_timeout_s", 0.5, "s", 0.05, 5.0,
          description="a viewer that has not taken the data within this is slow: drop until it catches up"),
]
# viz opens its outputs and builds its adapters from its parameters at start: all but the rates
# and show_truth (read per sample) are read there only, so a live set of one is refused, saying so.
PARAMS = start_only_but(_DECLARED, live=("show_truth", "pose_rate_hz", "image_rate_hz", "cloud_rate_hz",
                                          "costmap_rate_hz", "setpoint_rate_hz", "objects_rate_hz"))
