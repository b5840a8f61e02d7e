"""Contract of the lidar_driver: keys out and parameters (requirements: the LiDAR driver node of
the source spec, device_ip / frame_id / scan_rate / min_range / max_range / expected_points).

Frames: points in the sensor's own frame (`frame_id`; x forward, y left, z up, as the vendor
defines it); where the sensor sits on the body is the consumer's mount (the lidar service's
mount_* parameters), never assumed here.
"""
from aeroperception.schemas import Imu, PointCloud
from aeroperception.services.lib.lidar.velodyne import MODELS
from aeroperception.services.runtime import BULK, SMALL, Param, Topic, Topics

NAME = "lidar_driver"
CPU_BUDGET_PCT = 15.0    # % of one core: a VLP-16 at 10 Hz (754 packets/s)
OUTPUTS = Topics(
    Topic("sensors/lidar/points", PointCloud, 10.0, note="sensor frame; whole rotations with ring and time_offset_s",
          qos=BULK),
    Topic("sensors/lidar/imu", Imu, 100.0, note="Ouster with imu_port: the sensor's own IMU, in the sensor frame "
                                                "(not sensors/imu: that is the vehicle's)", qos=SMALL),
)
PARAMS = [
    Param("vendor", "velodyne", choices=("velodyne", "ouster"), start_only=True, description="packet format"),
    Param("model", "auto", choices=("auto", *MODELS), start_only=True,
          description="Velodyne model (calibration and timing tables); auto = each packet's product byte"),
    Param("metadata_path", "", start_only=True, description="Ouster: the sensor's metadata JSON (required)"),
    Param("device_ip", "192.168.1.201", start_only=True,
          description="accept packets only from this address ('' = any; Velodyne's factory default)"),
    Param("bind_address", "0.0.0.0", start_only=True, description="local address the UDP socket binds"),
    Param("port", 2368, "", 1, 65535, start_only=True, description="UDP data port (Velodyne 2368, Ouster 7502)"),
    Param("imu_port", 0, "", 0, 65535, start_only=True,
          description="Ouster: the IMU packets' UDP port (7503), published on sensors/lidar/imu; 0 = not read"),
    Param("frame_id", "lidar", description="header.frame_id of the published scans"),
    Param("scan_rate_hz", 10.0, "Hz", 5.0, 20.0,
          description="the sensor's rotation rate: no packet for 2 periods ends the scan in progress"),
    Param("min_range_m", 0.5, "m", 0.0, 10.0, description="nearer returns are dropped (own airframe)"),
    Param("max_range_m", 100.0, "m", 1.0, 300.0, description="farther returns are dropped"),
    Param("expected_points", 30000, "", 100, 5000000,
          description="returns in a whole rotation (VLP-16 ~29k, HDL-32E ~44k, OS-1-128 ~108k): diagnostics WARN "
                      "below half"),
    Param("min_coverage", 0.5, "", 0.0, 1.0,
          description="a scan covering less of the rotation than this (lost packets, start mid-sweep) is dropped"),
    Param("time_source", "host", choices=("host", "sensor"),
          description="host = the packet's arrival time (sensor timing within it); sensor = the sensor's own "
                      "clock (GPS/PTP-synchronised sensors: Velodyne's us past the hour, Ouster's ns)"),
]
