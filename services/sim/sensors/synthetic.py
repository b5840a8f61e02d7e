"""Analytic trajectories with exactly consistent derivatives, for testing and benchmarking the
sensor models without the vehicle dynamics (position, velocity, acceleration, attitude and body
rates all come from closed forms)."""
from __future__ import annotations

import math

import numpy as np

from ..truth import VehicleTruth
from .frames import rot_to_quat, rpy_to_rot


def orbit_truth(stamp_ns: int, center_enu_m=(0.0, 0.0, 3.0), radius_m: float = 5.0,
                period_s: float = 20.0, bob_m: float = 0.5, roll_amp_rad: float = 0.15,
                pitch_amp_rad: float = 0.1) -> VehicleTruth:
    """Circle (counter-clockwise) with vertical bobbing, heading along the path, and roll/pitch
    oscillations so all three body rates are exercised."""
    t = stamp_ns * 1e-9
    w = 2 * math.pi / period_s
    cx, cy, cz = center_enu_m
    pos = np.array([cx + radius_m * math.cos(w * t), cy + radius_m * math.sin(w * t),
                    cz + bob_m * math.sin(2 * w * t)])
    vel = np.array([-radius_m * w * math.sin(w * t), radius_m * w * math.cos(w * t),
                    2 * w * bob_m * math.cos(2 * w * t)])
    acc = np.array([-radius_m * w * w * math.cos(w * t), -radius_m * w * w * math.sin(w * t),
                    -4 * w * w * bob_m * math.sin(2 * w * t)])
    # Z-Y-X Euler angles and their rates.
    w_r, w_p = 3 * w, 5 * w
    roll, droll = roll_amp_rad * math.sin(w_r * t), roll_amp_rad * w_r * math.cos(w_r * t)
    pitch, dpitch = pitch_amp_rad * math.cos(w_p * t), -pitch_amp_rad * w_p * math.sin(w_p * t)
    yaw, dyaw = w * t + math.pi / 2, w
    body_rates = np.array([
        droll - dyaw * math.sin(pitch),
        dpitch * math.cos(roll) + dyaw * math.sin(roll) * math.cos(pitch),
        -dpitch * math.sin(roll) + dyaw * math.cos(roll) * math.cos(pitch),
    ])
    q = rot_to_quat(rpy_to_rot(roll, pitch, yaw))
    return VehicleTruth(stamp_ns=int(stamp_ns), position_enu_m=pos, velocity_enu_mps=vel,
                        accel_enu_mps2=acc, q_enu_flu=q, angular_velocity_flu_radps=body_rates)


def hover_truth(position_enu_m, yaw_rad: float = 0.0, stamp_ns: int = 0) -> VehicleTruth:
    """Level and still at a point."""
    return VehicleTruth(stamp_ns=stamp_ns, position_enu_m=np.asarray(position_enu_m, float),
                        q_enu_flu=np.array([math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)]))
