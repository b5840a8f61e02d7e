"""perception: the coordinator of requirement PERC-1 — one verdict, perception/health, from VIO, detector
and LiDAR health. The mission manager and safety gate on that single key."""
