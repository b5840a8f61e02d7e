"""Estimators: where the planner reads where the vehicle is, keyed by name (the planner's
`estimator` parameter; SetEstimator through planner/srv/select_plugin).

- `fc`: the flight controller's estimate (state/vehicle), the one it controls on.
- `vio`: VIO's odometry directly (state/visual_odometry), for progress, tracking, goals reached
  and the velocity controller's position loop. VIO's odom frame starts where VIO initialised, so
  it is aligned to the map frame (yaw and translation) with the flight controller's estimate when
  it is selected and again at each VIO reset (its reset_counter). Position setpoints sent to the
  flight controller are shifted by how far its estimate is from VIO's (`fc_offset_m`), so the
  vehicle follows the reference as VIO sees it whichever controller runs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np

from aeroperception.schemas import Odometry, Quaternion, Vector3, VehicleState
from aeroperception.services.runtime.rotations import quat_rotate


def _rz(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Alignment:
    """map = Rz(yaw_rad) odom + translation_m."""

    yaw_rad: float
    translation_m: np.ndarray
    reset_counter: int


class VioEstimate:
    """VIO odometry as a VehicleState in the map frame (the flight controller's flags kept)."""

    def __init__(self) -> None:
        self.alignment: Alignment | None = None
        self.realigned = 0

    def align(self, fc: VehicleState, odom: Odometry) -> None:
        yaw_vio = odom.pose.orientation.to_yaw()
        d_yaw = fc.yaw_rad - yaw_vio
        p_vio = odom.pose.position.to_array()
        self.alignment = Alignment(d_yaw, fc.position_m.to_array() - _rz(d_yaw) @ p_vio, odom.reset_counter)
        self.realigned += 1

    def estimate(self, odom: Odometry, fc: VehicleState | None) -> VehicleState | None:
        """The state VIO gives now, None without a flight-controller state to align with."""
        if fc is None:
            return None
        if self.alignment is None or self.alignment.reset_counter != odom.reset_counter:
            self.align(fc, odom)
        a = self.alignment
        rot = _rz(a.yaw_rad)
        q = odom.pose.orientation
        velocity = rot @ quat_rotate(q.to_array(), odom.twist.linear.to_array())
        roll, pitch, yaw = q.to_euler()
        yaw = math.atan2(math.sin(yaw + a.yaw_rad), math.cos(yaw + a.yaw_rad))
        return msgspec.structs.replace(
            fc, header=msgspec.structs.replace(fc.header, stamp_ns=odom.header.stamp_ns),
            position_m=Vector3.from_array(rot @ odom.pose.position.to_array() + a.translation_m),
            velocity_mps=Vector3.from_array(velocity), orientation=Quaternion.from_euler(roll, pitch, yaw),
            roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, estimator_name="vio",
            pose_covariance=None, twist_covariance=None)


def fc_offset_m(fc: VehicleState | None, estimate: VehicleState) -> np.ndarray:
    """Where the flight controller thinks the vehicle is, relative to the estimate the planner
    uses: added to position setpoints so the flight controller's loop tracks the estimate's."""
    if fc is None or fc is estimate:
        return np.zeros(3)
    return fc.position_m.to_array() - estimate.position_m.to_array()


@dataclass(frozen=True)
class Estimator:
    description: str
    key: str


ESTIMATORS: dict[str, Estimator] = {
    "fc": Estimator("the flight controller's estimate", "state/vehicle"),
    "vio": Estimator("VIO's odometry directly, aligned to the map with the flight controller's estimate",
                     "state/visual_odometry"),
}
