"""Contract of the lidar service (requirements LID-1 - LID-4): keys in/out and parameters.

Frames: scans arrive in the sensor frame (x forward, z up, mounted on the FLU body by the
mount_* parameters); everything published is ENU world ("map"), placed with the vehicle pose
from state/vehicle nearest the scan's stamp.
"""
from aeroperception.schemas import Imu, OccupancyGrid, PointCloud, VehicleState
from aeroperception.services.runtime import Param, Topic, Topics

NAME = "lidar"
CPU_BUDGET_PCT = 25.0   # % of one core for the whole pipeline at 10 scans/s
INPUTS = Topics(
    Topic("sensors/lidar/points", PointCloud, note="sensor frame"),
    Topic("state/vehicle", VehicleState, note="pose at the scan stamp (levelling + costmap placement)"),
    Topic("sensors/imu", Imu, note="gravity direction: levelling when no pose is fresh"),
)
OUTPUTS = Topics(
    Topic("perception/obstacles", PointCloud, 10.0, note='ENU "map", voxel-downsampled obstacle points'),
    Topic("perception/ground", PointCloud, 1.0, note='ENU "map", ground points'),
    Topic("perception/costmap", OccupancyGrid, 10.0, note="rolling grid centred on the vehicle"),
)
PARAMS = [
    # the filter pipeline (LID-1)
    Param("voxel_leaf_m", 0.05, "m", 0.01, 1.0, description="voxel grid leaf size"),
    Param("min_range_m", 0.5, "m", 0.0, 10.0, description="returns nearer than this are dropped (own airframe)"),
    Param("max_range_m", 50.0, "m", 1.0, 300.0, description="returns farther than this are dropped"),
    Param("ground_enabled", True, description="RANSAC ground removal"),
    Param("ground_distance_threshold_m", 0.05, "m", 0.01, 0.5, description="within this of the plane = ground"),
    Param("ground_max_iterations", 100, "", 10, 2000, description="RANSAC hypotheses per scan"),
    Param("use_imu_tilt", True, description="seed the ground normal with the vehicle/IMU gravity direction"),
    Param("ground_max_angle_deg", 10.0, "deg", 1.0, 45.0, description="ground normal within this of gravity-up"),
    Param("min_obstacle_height_m", 0.1, "m", 0.0, 2.0, description="lower edge of the obstacle band above ground"),
    Param("max_obstacle_height_m", 2.0, "m", 0.2, 50.0, description="band top above ground (ground robot; see overhead)"),
    Param("overhead_clearance_m", 1.0, "m", 0.0, 20.0,
          description="returns more than this above the vehicle are overhead, not obstacles"),
    Param("clustering_enabled", False, description="group obstacles (grid connected components)"),
    Param("cluster_tolerance_m", 0.2, "m", 0.05, 2.0, description="cluster cell size"),
    Param("min_cluster_size", 10, "", 1, 100000, description="smaller clusters are dropped"),
    Param("max_cluster_size", 5000, "", 1, 1000000, description="larger clusters are dropped"),
    Param("processing_rate_hz", 10.0, "Hz", 0.5, 50.0, description="at most this many scans per second"),
    Param("max_points", 500000, "", 1000, 5000000, description="larger scans are refused as garbage"),
    # mount of the sensor on the body (FLU), the sim's default rig
    Param("mount_x_m", 0.0, "m", -5.0, 5.0), Param("mount_y_m", 0.0, "m", -5.0, 5.0),
    Param("mount_z_m", 0.1, "m", -5.0, 5.0),
    Param("mount_roll_deg", 0.0, "deg", -180.0, 180.0), Param("mount_pitch_deg", 0.0, "deg", -90.0, 90.0),
    Param("mount_yaw_deg", 0.0, "deg", -180.0, 180.0),
    Param("pose_max_age_s", 0.1, "s", 0.01, 1.0, description="no state/vehicle this near the scan stamp: no costmap"),
    Param("deskew", True, description="move each point to the sensor's pose at the scan stamp with the vehicle's "
                                      "poses over the sweep (scans with time_offset_s: a real spinning LiDAR)"),
    # the costmap (LID-3: Nav2 semantics)
    Param("costmap_size_m", 20.0, "m", 5.0, 200.0, description="rolling window edge"),
    Param("costmap_resolution_m", 0.1, "m", 0.02, 1.0, description="cell size"),
    Param("obstacle_range_m", 10.0, "m", 0.5, 100.0, description="mark obstacles up to this range"),
    Param("raytrace_range_m", 15.0, "m", 0.5, 100.0, description="clear free space up to this range"),
    Param("mark_threshold", 2, "", 1, 100, description="points in a cell to mark it lethal"),
    Param("inscribed_radius_m", 0.4, "m", 0.05, 5.0, description="vehicle radius: closer = collision"),
    Param("inflation_radius_m", 1.5, "m", 0.05, 20.0, description="cost decays to 0 here"),
    Param("cost_scaling_factor", 3.0, "1/m", 0.1, 50.0, description="exponential decay rate of inflation"),
    Param("ground_publish_period_s", 1.0, "s", 0.1, 60.0, description="perception/ground period"),
]
