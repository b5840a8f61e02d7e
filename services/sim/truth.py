"""Ground-truth vehicle state: the one type the simulated vehicle produces and the sensor
renderers consume. ENU world, FLU body. Never published to the autonomy services, only on
sim/truth/** (eval tools)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class VehicleTruth:
    """True state at `stamp_ns` (sim clock).

    q_enu_flu is (w, x, y, z) and rotates FLU body vectors into the ENU world frame
    (v_world = R(q) @ v_body), as ROS geometry_msgs/Pose orientation does.
    """

    stamp_ns: int = 0
    position_enu_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity_enu_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_enu_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q_enu_flu: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    angular_velocity_flu_radps: np.ndarray = field(default_factory=lambda: np.zeros(3))
