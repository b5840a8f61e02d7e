"""Evaluations against ground truth: `aero eval ...` (VIO, LiDAR, detector, objects, trajectories)."""
