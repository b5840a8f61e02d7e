"""LiDAR obstacles and rolling costmap (requirements LID-1 - LID-4)."""
