"""Camera optical frames against the body (ARCHITECTURE.md §2): optical x right, y down, z
forward (OpenCV / ROS), body FLU. Shared by the simulator's cameras and the camera driver, so a
real camera and a rendered one declare where they look the same way."""
from __future__ import annotations

import numpy as np

from aeroperception.services.runtime.rotations import quat_from_euler, quat_to_rotmat

# Optical frame axes expressed in the body (FLU) frame for a camera looking straight forward:
# optical x (right) = -body y, optical y (down) = -body z, optical z (forward) = +body x.
R_FLU_OPTICAL_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def r_body_optical(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """R_body_optical of a camera whose own FLU axes (x along the optical axis) sit at these
    Euler angles in the body: (0, 0, 0) looks forward, pitch +90 deg straight down."""
    return quat_to_rotmat(quat_from_euler(roll_rad, pitch_rad, yaw_rad)) @ R_FLU_OPTICAL_FORWARD
