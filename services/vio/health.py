"""VIO health as an explicit transition table (like services/mission/fsm.py): every frame
produces one event, the table says the next state. `consecutive_lost` counts frames in a row
without a visual fix; LOST after `lost_after_frames` of them.

    INIT      waiting for IMU, calibration and a first stereo keyframe; no output
    TRACKING  visual fix on this frame with enough inliers; the output is trustworthy
    DEGRADED  weak or missing visual fix (few features, bad image, IMU gap): output continues
              from the IMU with growing covariance; consumers down-weight it
    LOST      no visual fix for lost_after_frames frames: no output; the mission holds / RTLs
"""
from __future__ import annotations

from .dto import DEGRADED, INIT, LOST, TRACKING

# Events of one frame.
INITIALIZED = "initialized"   # the back end got its first state
GOOD = "good"                 # visual fix with enough inliers
WEAK = "weak"                 # visual fix, few inliers (or an input problem this frame)
MISS = "miss"                 # no visual fix, fewer than lost_after_frames in a row
MISS_LIMIT = "miss_limit"     # no visual fix, lost_after_frames in a row
RESET = "reset"               # re-initialise (time jump, long IMU gap, smoother failure, warm start)

TRANSITIONS: dict[tuple[int, str], int] = {
    (INIT, INITIALIZED): TRACKING,
    (INIT, RESET): INIT,
    (TRACKING, GOOD): TRACKING,
    (TRACKING, WEAK): DEGRADED,
    (TRACKING, MISS): DEGRADED,
    (TRACKING, MISS_LIMIT): LOST,
    (TRACKING, RESET): INIT,
    (DEGRADED, GOOD): TRACKING,
    (DEGRADED, WEAK): DEGRADED,
    (DEGRADED, MISS): DEGRADED,
    (DEGRADED, MISS_LIMIT): LOST,
    (DEGRADED, RESET): INIT,
    (LOST, GOOD): TRACKING,
    (LOST, WEAK): DEGRADED,
    (LOST, MISS): LOST,
    (LOST, MISS_LIMIT): LOST,
    (LOST, RESET): INIT,
}


# Level of the log line announcing a change into each state: losing the visual fix is what an
# operator must not miss (DEGRADED warns, LOST is an error); initialising and recovering are news.
LOG_LEVEL: dict[int, str] = {INIT: "info", TRACKING: "info", DEGRADED: "warn", LOST: "error"}


def next_state(state: int, event: str) -> int:
    """The table's answer; events that do not apply in a state (e.g. GOOD while INIT) keep it."""
    return TRANSITIONS.get((state, event), state)


def quality_pct(state: int, inliers: int | None, good_inliers: int, full_inliers: int) -> int:
    """A pose's quality for consumers that weigh or gate on it (MAVLink ODOMETRY quality, PX4's
    EKF2_EV_QMIN), 1-100: the health state gives the band, the visual fix's RANSAC inliers the place
    in it. TRACKING: 50 at `good_inliers` rising to 100 at `full_inliers` (enough for a new keyframe).
    DEGRADED (a weak fix, or a good one through an IMU gap or a bad image): 2-49 with the inliers;
    no visual fix (the IMU's pose alone): 1."""
    if not inliers:
        return 1
    if state != TRACKING or inliers < good_inliers:
        return max(2, min(49, round(50 * inliers / good_inliers)))
    span = max(1, full_inliers - good_inliers)
    return min(100, 50 + round(50 * (inliers - good_inliers) / span))
