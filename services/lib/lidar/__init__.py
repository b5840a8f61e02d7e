"""LiDAR packets from the wire: a pcap reader for recorded captures and the vendors' packet
decoders (Velodyne, Ouster), plain numpy, no vendor SDK. Shared by the lidar_driver service (live
UDP) and the tools that replay captures. Points are in the sensor's frame as the vendor defines it
(x forward, y left, z up); nothing here knows where the sensor sits on the vehicle.
"""
