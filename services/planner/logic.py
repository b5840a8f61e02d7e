"""Planner logic, free of Zenoh: state + goal in, setpoint out (ENU, SI)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aeroperception.schemas import TrajectorySetpoint, TrajectoryStatus, Vector3


@dataclass
class Goal:
    position_m: np.ndarray
    yaw_rad: float | None
    index: int = 0
    max_speed_mps: float = 0.0            # this goal's speed cap (0: max_velocity_mps only)
    max_vertical_speed_mps: float = 0.0   # ... and vertical speed cap (climb / descent rate; 0: none)


@dataclass
class Leg:
    """The way to one goal: where and when the vehicle was when it began, when it arrived."""

    start_m: np.ndarray
    started_s: float
    arrived_s: float | None = None


@dataclass
class Progress:
    """planner/status's progress fields for the active goal."""

    percent: float = 0.0
    elapsed_s: float = 0.0
    remaining_s: float = 0.0


@dataclass
class StepResult:
    setpoint: TrajectorySetpoint
    distance_m: float | None
    reached: bool


class GoalWatchdog:
    """Is the mission still there? It re-publishes its goal at 2 Hz, so a goal stream silent for
    `timeout_s` means the mission (or the link to the ground host it runs on) is gone: the planner
    then holds where it is instead of flying on, blind, to the last goal. timeout_s 0 = off."""

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.last_heard_s: float | None = None
        self.silent = False

    def heard(self, now_s: float) -> bool:
        """A goal message arrived; True when it ends a silence (the mission is back)."""
        self.last_heard_s = now_s
        was, self.silent = self.silent, False
        return was

    def expired(self, now_s: float, tracking: bool) -> bool:
        """True once, the first check after the goal stream fell silent while tracking a goal."""
        if (self.silent or not tracking or self.timeout_s <= 0 or self.last_heard_s is None
                or now_s - self.last_heard_s <= self.timeout_s):
            return False
        self.silent = True
        return True


def time_to_go_s(distance_m: float, max_velocity_mps: float, kp: float, acceptance_radius_m: float) -> float:
    """Time the P-controller's own speed profile, min(max_velocity, kp * d), takes from
    `distance_m` to the acceptance radius: cruise until kp * d drops below the cap, then the
    exponential approach d(t) = d1 * exp(-kp t)."""
    d, t = distance_m, 0.0
    slow_from_m = max(max_velocity_mps / kp, acceptance_radius_m)
    if d > slow_from_m:
        t, d = (d - slow_from_m) / max_velocity_mps, slow_from_m
    if d > acceptance_radius_m:
        t += math.log(d / acceptance_radius_m) / kp
    return t


class WaypointPlanner:
    """P-controller to the current goal; holds position (zero velocity) without one.

    `reached` fires once per goal, the cycle the vehicle enters the acceptance radius. Each goal's
    leg starts where the vehicle is at the first step after the goal arrived (`leg`, for progress).
    """

    def __init__(self, max_velocity_mps: float = 2.0, kp: float = 0.8, acceptance_radius_m: float = 0.5):
        self.max_velocity_mps = max_velocity_mps
        self.kp = kp
        self.acceptance_radius_m = acceptance_radius_m
        self.goal: Goal | None = None
        self.hold_position_m: np.ndarray | None = None
        self.hold_yaw_rad: float = 0.0
        self._reached_sent = False
        self.leg: Leg | None = None
        self.status = TrajectoryStatus.STATUS_IDLE

    def set_goal(self, goal: Goal | None) -> None:
        same = (goal is not None and self.goal is not None and goal.index == self.goal.index
                and np.allclose(goal.position_m, self.goal.position_m))
        if not same:
            self._reached_sent = False
            self.leg = None
            if goal is not None:   # planner/status must not show the last goal's COMPLETED under this one
                self.status = TrajectoryStatus.STATUS_EXECUTING
        self.goal = goal
        if goal is None:
            self.hold_position_m = None  # captured from the next state

    def retake_hold(self) -> None:
        """Holding: hold where the next state puts the vehicle, not where the hold began. For while
        the flight controller flies a mode of its own (a failsafe RTL, a pilot's HOLD) or no state
        came: the vehicle moved without our setpoints, and PX4 returns to OFFBOARD by itself once
        its offboard-loss failsafe clears, so an old hold point would be flown back to."""
        if self.goal is None:
            self.hold_position_m = None

    def step(self, position_m: np.ndarray, yaw_rad: float, now_s: float = 0.0) -> StepResult:
        if self.goal is not None and self.leg is None:
            self.leg = Leg(position_m.copy(), now_s)
        if self.goal is None:
            if self.hold_position_m is None:
                self.hold_position_m, self.hold_yaw_rad = position_m.copy(), yaw_rad
            self.status = TrajectoryStatus.STATUS_PAUSED
            return StepResult(hold_setpoint(self.hold_position_m, self.hold_yaw_rad), None, False)
        error = self.goal.position_m - position_m
        distance = float(np.linalg.norm(error))
        reached = distance < self.acceptance_radius_m and not self._reached_sent
        if reached:
            self._reached_sent = True
            self.leg.arrived_s = now_s
        speed = min(self.speed_cap_mps(error), distance * self.kp)
        velocity = error / distance * speed if distance > 1e-6 else np.zeros(3)
        yaw = self.goal.yaw_rad if self.goal.yaw_rad is not None else yaw_rad
        self.status = TrajectoryStatus.STATUS_COMPLETED if self._reached_sent else TrajectoryStatus.STATUS_EXECUTING
        sp = TrajectorySetpoint(velocity_valid=True, yaw_valid=True,
                                position_m=Vector3.from_array(self.goal.position_m),
                                velocity_mps=Vector3.from_array(velocity), yaw_rad=yaw)
        return StepResult(sp, distance, reached)

    def speed_cap_mps(self, error_m: np.ndarray) -> float:
        """Speed cap along the straight line to the goal: max_velocity_mps, the goal's own cap,
        and its vertical cap (climb / descent rate) as a cap on the whole line (the same line,
        slower)."""
        cap = self.max_velocity_mps
        if self.goal.max_speed_mps > 0:
            cap = min(cap, self.goal.max_speed_mps)
        climb = abs(float(error_m[2]))
        if self.goal.max_vertical_speed_mps > 0 and climb > 1e-9:
            cap = min(cap, self.goal.max_vertical_speed_mps * float(np.linalg.norm(error_m)) / climb)
        return cap

    def progress(self, position_m: np.ndarray, now_s: float) -> Progress:
        """Progress of the active goal: the share of the leg flown to the acceptance radius
        (by the straight distance left), time since the leg began (until arrival), and the
        time the remaining distance takes at the commanded speed profile. Zeros without a goal."""
        leg, goal = self.leg, self.goal
        if goal is None:
            return Progress()
        leg = leg or Leg(position_m, now_s)   # a new goal the next step begins its leg for
        if leg.arrived_s is not None:
            return Progress(100.0, leg.arrived_s - leg.started_s, 0.0)
        error = goal.position_m - position_m
        left = float(np.linalg.norm(error))
        span = float(np.linalg.norm(goal.position_m - leg.start_m)) - self.acceptance_radius_m
        done = 1.0 if span <= 0 else (span - (left - self.acceptance_radius_m)) / span
        return Progress(100.0 * min(1.0, max(0.0, done)), now_s - leg.started_s,
                        time_to_go_s(left, self.speed_cap_mps(error), self.kp, self.acceptance_radius_m))


def tracking_errors(setpoint: TrajectorySetpoint, planner: WaypointPlanner, position_m: np.ndarray,
                    velocity_mps: np.ndarray) -> tuple[float, float]:
    """(position error, velocity error) of the vehicle against its reference: the distance to
    the goal (the hold point without one), and the difference between the velocity last sent
    to fmu and the vehicle's velocity."""
    ref = planner.goal.position_m if planner.goal is not None else planner.hold_position_m
    position_error = float(np.linalg.norm(ref - position_m)) if ref is not None else 0.0
    return position_error, float(np.linalg.norm(setpoint.velocity_mps.to_array() - velocity_mps))


hold_setpoint = TrajectorySetpoint.hold   # one home: the schema's hold constructor

