"""perception: the coordinator of seed 000 §4.3 — one verdict, perception/health, from VIO, detector
and LiDAR health. The mission manager and safety gate on that single key."""
