"""vio: stereo-inertial visual odometry (requirements VIO-1 - VIO-8).

A `VioStrategy` (selected by the `strategy` parameter at start) turns stereo frames and the IMU
samples between them into a pose in the gravity-aligned `odom` frame (ENU-like: z up, origin and
yaw where VIO initialised) with honest 6x6 covariances from a GTSAM fixed-lag smoother, and a
health state (INIT / TRACKING / DEGRADED / LOST). It never sees ground truth: sim/truth/** is for
`aero eval vio` only.
"""
