"""Contract of vio: keys in/out and parameters (stereo-inertial odometry, requirements VIO-1 - VIO-8)."""
from aeroperception.schemas import CameraInfo, Image, Imu, Odometry, Reply, VioHealth, VioResetRequest
from aeroperception.services.runtime import EXPRESS, Param, Queries, Query, Topic, Topics
from aeroperception.services.runtime.params import start_only_but

from .backend import BackendConfig
from .drift import DriftConfig
from .frontend import FrontEndConfig
from .imu import ImuNoise
from .strategy import VioConfig

NAME = "vio"
INPUTS = Topics(
    Topic("sensors/camera/left/image", Image, note="mono8 / rgb8, stamped at exposure"),
    Topic("sensors/camera/right/image", Image, note="same stamp as its left image (klt_stereo)"),
    Topic("sensors/camera/left/info", CameraInfo),
    Topic("sensors/camera/right/info", CameraInfo),
    Topic("sensors/imu", Imu, note="body FLU, specific force incl. gravity, 100-400 Hz"),
)
OUTPUTS = Topics(
    # Pose of base_link in odom (gravity-aligned, z up, origin/yaw where VIO initialised) with
    # 6x6 covariances: the smoother's marginals plus the drift accumulated since initialisation
    # (drift.py: grows with distance flown and yaw turned).
    Topic("state/visual_odometry", Odometry, note="one per processed frame; with imu_rate_hz also IMU-propagated "
                                                 "poses between frames, stamps always increasing", qos=EXPRESS),
    Topic("state/vio_health", VioHealth, 1.0, note="and on every state change"),
)
SERVICES = Queries(
    Query("vio/srv/reset", VioResetRequest, Reply,
          note="restart from a known odom pose (a warm start); INIT until the next good frame"),
)
CALLS = Queries(
    Query("sensors/camera/left/info", None, CameraInfo, note="once at start (the latched camera model)"),
    Query("sensors/camera/right/info", None, CameraInfo),
)
_DECLARED = [
    Param("strategy", "klt_stereo", description="VioStrategy at start: klt_stereo, klt_mono (okvis2, vins_mono: not built)"),
    Param("max_features", FrontEndConfig.max_features, "", 20, 1000, description="features per keyframe"),
    Param("keyframe_max_age_s", FrontEndConfig.keyframe_max_age_s, "s", 0.05, 5.0, description="new keyframe at least this often (< 0.9 lag_s)"),
    Param("ransac_threshold_px", FrontEndConfig.ransac_threshold_px, "px", 0.3, 10.0, description="PnP RANSAC inlier threshold"),
    Param("lag_s", BackendConfig.lag_s, "s", 0.3, 10.0, description="fixed-lag smoother window"),
    Param("covariance_every_frames", BackendConfig.covariance_every_frames, "", 1, 10,
          description="recompute the window's marginal covariance every this many frames with a visual fix "
                      "(always after a frame without one); in between the last is kept. 1 = every frame"),
    Param("lost_after_frames", VioConfig.lost_after_frames, "", 1, 1000, description="frames without a visual fix before LOST"),
    Param("gyro_noise_density", ImuNoise.gyro_noise_density, "rad/s/sqrt(Hz)", 1e-6, 1.0),
    Param("accel_noise_density", ImuNoise.accel_noise_density, "m/s^2/sqrt(Hz)", 1e-6, 10.0),
    Param("gyro_random_walk", ImuNoise.gyro_random_walk, "rad/s^2/sqrt(Hz)", 1e-9, 1.0),
    Param("accel_random_walk", ImuNoise.accel_random_walk, "m/s^3/sqrt(Hz)", 1e-9, 1.0),
    Param("drift_xy_pct", 100 * DriftConfig.drift_xy_frac, "%", 0.0, 10.0,
          description="1-sigma horizontal drift per axis as % of distance flown, added to the window's covariance"),
    Param("drift_z_pct", 100 * DriftConfig.drift_z_frac, "%", 0.0, 10.0,
          description="1-sigma vertical drift as % of distance flown"),
    Param("imu_gap_warn_s", VioConfig.imu_gap_warn_s, "s", 0.005, 1.0, description="longer IMU gap: DEGRADED for that frame"),
    Param("imu_gap_reset_s", VioConfig.imu_gap_reset_s, "s", 0.05, 10.0, description="longer IMU gap: re-initialise"),
    Param("imu_wait_s", 0.5, "s", 0.0, 5.0,
          description="before a frame, wait up to this long for the IMU samples up to its stamp (they can run "
                      "behind the images under load); then process it with what is in"),
    Param("imu_rate_hz", 0.0, "Hz", 0.0, 400.0,
          description="also publish the newest estimate carried forward with the IMU, stamped at IMU samples, at up "
                      "to this rate (propagate.py): for an FC estimator that needs poses more often and sooner than "
                      "frames come (PX4 EKF2: < 0.2 s apart); 0 = one pose per frame"),
    Param("imu_rate_max_horizon_s", 2.0, "s", 0.1, 10.0,
          description="no IMU-propagated pose further than this past the newest frame's estimate"),
    Param("opencv_threads", 1, "", 0, 16,
          description="OpenCV's worker threads in this process (cv2.setNumThreads; 0 = OpenCV's default, one per "
                      "core): one does the frame's work on the worker thread itself; a pool spent ~10 % more CPU "
                      "a frame (waking, spinning) for a shorter wall time VIO does not need at 20 Hz"),
]
# Every parameter configures the strategy built at start (config.py): a live set is refused, saying
# so, instead of being reported as in force while the old strategy runs.
PARAMS = start_only_but(_DECLARED)
