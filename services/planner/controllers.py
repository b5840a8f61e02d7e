"""Controllers: what part of the planner's reference goes to the flight controller, keyed by name
(the planner's `controller` parameter; SetController through planner/srv/select_plugin).

The reference (a goal's velocity, a trajectory's full state, a hold point) is the same whichever
runs; the controller decides what the flight controller is asked to track:

- `feedforward`: everything valid as is — position, velocity and acceleration (+ yaw, yaw rate):
  PX4's position controller closes the position loop and uses velocity and acceleration as
  feed-forward (the smallest tracking error).
- `velocity`: velocity only (+ yaw): the planner closes the position loop itself, v = v_ref +
  kp (p_ref - p), capped at the speed limit; the flight controller never sees a position. For
  an estimate the flight controller does not share (the `vio` estimator without vision fusion),
  or a flight controller whose position loop is not to be trusted.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from aeroperception.schemas import TrajectorySetpoint, Vector3


@dataclass(frozen=True)
class Gains:
    kp: float                 # 1/s, position error -> velocity (the planner's kp)
    max_velocity_mps: float   # the velocity command's cap


def feedforward(sp: TrajectorySetpoint, position_m: np.ndarray, gains: Gains) -> TrajectorySetpoint:
    return sp


def velocity_only(sp: TrajectorySetpoint, position_m: np.ndarray, gains: Gains) -> TrajectorySetpoint:
    v = sp.velocity_mps.to_array() if sp.velocity_valid else np.zeros(3)
    if sp.position_valid:
        v = v + gains.kp * (sp.position_m.to_array() - position_m)
    speed = float(np.linalg.norm(v))
    if speed > gains.max_velocity_mps:
        v *= gains.max_velocity_mps / speed
    return TrajectorySetpoint(header=sp.header, velocity_valid=True, velocity_mps=Vector3.from_array(v),
                              yaw_valid=sp.yaw_valid, yaw_rad=sp.yaw_rad)


@dataclass(frozen=True)
class Controller:
    description: str
    apply: Callable[[TrajectorySetpoint, np.ndarray, Gains], TrajectorySetpoint]


CONTROLLERS: dict[str, Controller] = {
    "feedforward": Controller("position + velocity + acceleration feed-forward to the flight controller", feedforward),
    "velocity": Controller("velocity only: the planner closes the position loop (kp)", velocity_only),
}
