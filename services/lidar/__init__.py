"""LiDAR obstacles and rolling costmap (seed 004)."""
