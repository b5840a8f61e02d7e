"""lidar_driver: a Velodyne or Ouster LiDAR's UDP packets into whole rotations on
sensors/lidar/points (issue 34, item 1), in the sensor's frame, with per-point ring and time.

Decoding is plain numpy (services/lib/lidar), no vendor SDK. It never crashes on what the network
brings: a packet that does not decode, arrives out of order or from the wrong address is counted by
reason in diagnostics and dropped; a scan with lost packets is published with what arrived, or
dropped with its reason when it covers too little of the rotation.
"""
