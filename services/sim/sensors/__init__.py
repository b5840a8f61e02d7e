"""Simulated sensors rendered from a scenario world: cameras, IMU, LiDAR, detection truth.

Pure models (numpy in, numpy out) so they are testable without Zenoh; the sim service wraps
them and publishes on sensors/**.
"""
