"""What every trajectory is: a time-parameterised reference the planner samples at its rate, and
the kinematic limits it must stay within (PX4's multicopter position-controller parameters, so a
trajectory that respects them is one PX4's own controller can follow)."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class PlanningMargin:
    """What a flight controller adds to the trajectory it tracks, planned inside the limits
    (KinematicLimits.inside). `speed_mps`: its velocity estimate's error (it flies its estimate: at the cap
    by the estimate, the vehicle is this much faster). `jerk_mps3`: the jerk its tracking adds to
    the reference's (its loops correcting the estimate's error and trailing the reference, and its
    height hold; PX4 SIH, figure8 at 3 m/s: the vehicle's jerk 0.5-1.1 m/s^3 above the reference's
    horizontally, 1-3 m/s^3 vertically with none planned)."""

    speed_mps: float = 0.0
    jerk_mps3: float = 0.0


@dataclass(frozen=True)
class KinematicLimits:
    """Kinematic limits, each named after the PX4 parameter it mirrors."""

    xy_vel_max_mps: float = 2.0          # MPC_XY_VEL_MAX
    z_vel_max_up_mps: float = 3.0        # MPC_Z_VEL_MAX_UP
    z_vel_max_dn_mps: float = 1.5        # MPC_Z_VEL_MAX_DN
    acc_hor_mps2: float = 3.0            # MPC_ACC_HOR
    acc_up_mps2: float = 4.0             # MPC_ACC_UP_MAX
    acc_down_mps2: float = 3.0           # MPC_ACC_DOWN_MAX
    jerk_mps3: float = 4.0               # MPC_JERK_AUTO
    yaw_rate_max_radps: float = math.radians(45.0)   # MPC_YAWRAUTO_MAX

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"limit `{name}` must be a positive number, got {value!r}")

    def inside(self, margin: PlanningMargin) -> KinematicLimits:
        """These limits lowered by `margin` (each never below half of itself): what a trajectory is
        planned with for a flight controller that adds `margin` to it, so that what the vehicle
        flies stays within these limits."""
        if margin.speed_mps <= 0 and margin.jerk_mps3 <= 0:
            return self
        lowered = {name: max(getattr(self, name) - max(0.0, by), getattr(self, name) / 2)
                   for name, by in (("xy_vel_max_mps", margin.speed_mps), ("z_vel_max_up_mps", margin.speed_mps),
                                    ("z_vel_max_dn_mps", margin.speed_mps), ("jerk_mps3", margin.jerk_mps3))}
        return dataclasses.replace(self, **lowered)

    def speed_cap_mps(self, direction: np.ndarray) -> float:
        """The highest speed along unit `direction` within the horizontal and vertical caps."""
        cap = math.inf
        horizontal = math.hypot(direction[0], direction[1])
        if horizontal > 1e-9:
            cap = self.xy_vel_max_mps / horizontal
        if abs(direction[2]) > 1e-9:
            cap = min(cap, (self.z_vel_max_up_mps if direction[2] > 0 else self.z_vel_max_dn_mps) / abs(direction[2]))
        return cap


@dataclass
class State:
    """The reference at one instant (ENU, SI); `yaw_rad` None when the trajectory gives no heading."""

    position_m: np.ndarray
    velocity_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acceleration_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    jerk_mps3: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float | None = None
    yaw_rate_radps: float = 0.0


class Path(Protocol):
    """A trajectory: sample(t) for 0 <= t <= duration_s (clamped outside), and the times at
    which it passes its waypoints (for progress and waypoint-reached events)."""

    duration_s: float
    waypoint_times_s: list[float]

    def sample(self, t_s: float) -> State: ...


@dataclass
class Peaks:
    """The largest speed, acceleration and jerk of a path (sampled), horizontal and vertical apart."""

    xy_speed_mps: float = 0.0
    z_up_mps: float = 0.0
    z_down_mps: float = 0.0
    xy_acc_mps2: float = 0.0
    z_acc_mps2: float = 0.0
    jerk_mps3: float = 0.0
    yaw_rate_radps: float = 0.0

    def excess(self, limits: KinematicLimits, tolerance: float = 0.0) -> list[str]:
        """Each limit exceeded by more than `tolerance` (a fraction), named with both values."""
        pairs = [("xy speed", self.xy_speed_mps, limits.xy_vel_max_mps, "MPC_XY_VEL_MAX"),
                 ("climb rate", self.z_up_mps, limits.z_vel_max_up_mps, "MPC_Z_VEL_MAX_UP"),
                 ("descent rate", self.z_down_mps, limits.z_vel_max_dn_mps, "MPC_Z_VEL_MAX_DN"),
                 ("horizontal acceleration", self.xy_acc_mps2, limits.acc_hor_mps2, "MPC_ACC_HOR"),
                 ("vertical acceleration", self.z_acc_mps2, max(limits.acc_up_mps2, limits.acc_down_mps2),
                  "MPC_ACC_UP_MAX/MPC_ACC_DOWN_MAX"),
                 ("jerk", self.jerk_mps3, limits.jerk_mps3, "MPC_JERK_AUTO"),
                 ("yaw rate", self.yaw_rate_radps, limits.yaw_rate_max_radps, "MPC_YAWRAUTO_MAX")]
        return [f"{what} {value:.2f} exceeds {param} {limit:.2f}" for what, value, limit, param in pairs
                if value > limit * (1 + tolerance) + 1e-9]


def peaks(path: Path, step_s: float = 0.01) -> Peaks:
    """Peaks of `path` sampled every `step_s` (the planner's 50 Hz sees no more than this)."""
    out = Peaks()
    n = max(2, int(math.ceil(path.duration_s / step_s)) + 1)
    for t in np.linspace(0.0, path.duration_s, n):
        s = path.sample(float(t))
        out.xy_speed_mps = max(out.xy_speed_mps, float(np.hypot(*s.velocity_mps[:2])))
        out.z_up_mps = max(out.z_up_mps, float(s.velocity_mps[2]))
        out.z_down_mps = max(out.z_down_mps, float(-s.velocity_mps[2]))
        out.xy_acc_mps2 = max(out.xy_acc_mps2, float(np.hypot(*s.acceleration_mps2[:2])))
        out.z_acc_mps2 = max(out.z_acc_mps2, abs(float(s.acceleration_mps2[2])))
        out.jerk_mps3 = max(out.jerk_mps3, float(np.linalg.norm(s.jerk_mps3)))
        out.yaw_rate_radps = max(out.yaw_rate_radps, abs(s.yaw_rate_radps))
    return out


def wrap_pi(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi
