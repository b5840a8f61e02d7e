"""Flying a path in time: the reference the planner streams, and how far along it is.

The reference runs on its own clock from the moment the path was taken up, but it never runs away
from the vehicle: while the vehicle is within `lag_m / 2` of it, time advances at full rate, then
slower, and not at all from `lag_m` on; the velocity streamed is scaled alike (zero while it waits). A gust, a slow climb or a vehicle weaker than the limits
then costs time, not a reference metres ahead that the controller would cut corners to catch.

The acceleration streamed is what the flight controller must command now for the vehicle to
follow the reference (`FeedForward`), not the reference's own: a flight controller realises an
acceleration setpoint only after its attitude and thrust have moved (PX4's SIH quad: 0.25 s), and
its position controller models no drag, so it pays for drag with a velocity error, i.e. by
trailing the position setpoint (on SIH, drag 1 /s: 0.74 m behind at 1.9 m/s).

Nor may the flight controller's own catch-up exceed the speed limit (`SpeedGovernor`): PX4 commands
velocity = feed-forward + its position gain x (setpoint - vehicle), so a reference running on while
the vehicle trails it is flown faster than the reference itself.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aeroperception.schemas import Trajectory, TrajectorySetpoint, Vector3

from aeroperception.services.lib.trajectory.core import Path, State


@dataclass(frozen=True)
class FeedForward:
    """How the acceleration feed-forward leads the reference: `lead_s`, the flight controller's lag
    from an acceleration setpoint to the vehicle's acceleration (the reference is taken that far
    ahead); `drag_per_s`, the vehicle's linear drag (acceleration lost per m/s of velocity),
    added for the velocity it will then have; `xy_vel_d`, the flight controller's velocity-loop
    D gain on the vehicle's measured acceleration (PX4: acceleration setpoint = feed-forward +
    MPC_XY_VEL_P_ACC x velocity error + I - MPC_XY_VEL_D_ACC x the vehicle's acceleration): a
    vehicle accelerating as the reference does loses that fraction of it, which PX4 then claws
    back only through a velocity and position error (figure8 at 3 m/s, SIH: 0.23 of 1.8 m/s² in
    the turns), so the reference's current horizontal acceleration x this gain is added."""

    lead_s: float = 0.0
    drag_per_s: float = 0.0
    xy_vel_d: float = 0.0

    def acceleration(self, path: Path, t_s: float, until_s: float | None = None) -> np.ndarray:
        """The acceleration to command at path time `t_s`, looking ahead no further than `until_s`."""
        ahead = min(path.duration_s, t_s + self.lead_s, math.inf if until_s is None else until_s)
        ref = path.sample(max(t_s, ahead))
        acc = ref.acceleration_mps2 + self.drag_per_s * ref.velocity_mps
        if self.xy_vel_d:
            acc[:2] += self.xy_vel_d * path.sample(t_s).acceleration_mps2[:2]
        return acc


@dataclass(frozen=True)
class SpeedGovernor:
    """Keeps the flight controller's horizontal velocity command within the speed limit by holding
    the reference's clock back. PX4 commands velocity = feed-forward + MPC_XY_P x (position setpoint
    - its estimate) and caps it only at its own MPC_XY_VEL_MAX, so a vehicle trailing the setpoint
    is flown faster than the reference (SIH after speeding up to 2 m/s: 0.5 m behind, 2.65 m/s
    commanded, 2.4 m/s flown). Here the reference advances only as far as keeps that command within
    `(1 + margin)` x the limit (or x the reference's own speed where that is higher), never
    backwards: the setpoint then leads the vehicle by at most what the margin leaves, and a lag
    costs time, not speed. `gain_per_s` is the flight controller's position gain (0: off)."""

    gain_per_s: float = 0.0
    xy_speed_mps: float = math.inf
    margin: float = 0.05

    def command_xy_mps(self, ref: State, position_m: np.ndarray) -> float:
        """The horizontal speed the flight controller commands for setpoint `ref` at `position_m`."""
        return float(np.hypot(*(ref.velocity_mps[:2] + self.gain_per_s * (ref.position_m[:2] - position_m[:2]))))

    def _within(self, ref: State, position_m: np.ndarray) -> bool:
        cap = (1 + self.margin) * max(self.xy_speed_mps, float(np.hypot(*ref.velocity_mps[:2])))
        return self.command_xy_mps(ref, position_m) <= cap

    def latest_s(self, path: Path, t_from_s: float, t_to_s: float, position_m: np.ndarray) -> float:
        """The latest path time in [t_from_s, t_to_s] whose reference keeps the command within the
        cap (t_from_s when none does: the clock stands until the vehicle closes up)."""
        if self.gain_per_s <= 0 or t_to_s <= t_from_s or self._within(path.sample(t_to_s), position_m):
            return t_to_s
        lo, hi = t_from_s, t_to_s
        for _ in range(12):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if self._within(path.sample(mid), position_m) else (lo, mid)
        return lo


@dataclass
class FollowStep:
    setpoint: TrajectorySetpoint
    reference: State
    tracking_error_m: float      # vehicle to the reference position
    finished: bool               # the reference is at its end and the vehicle within lag_m / 2 of it


def setpoint_of(ref: State, setpoint_type: int, acceleration_mps2: np.ndarray | None = None) -> TrajectorySetpoint:
    """The setpoint fields a trajectory's `setpoint_type` provides: position only; position and
    heading; or the full state (velocity, acceleration and yaw rate as feed-forward;
    `acceleration_mps2` in place of the reference's own: FeedForward's)."""
    sp = TrajectorySetpoint(position_valid=True, position_m=Vector3.from_array(ref.position_m))
    if setpoint_type != Trajectory.SETPOINT_POSITION_ONLY and ref.yaw_rad is not None:
        sp.yaw_valid, sp.yaw_rad = True, ref.yaw_rad
    if setpoint_type == Trajectory.SETPOINT_FULL_STATE:
        sp.velocity_valid, sp.velocity_mps = True, Vector3.from_array(ref.velocity_mps)
        acc = ref.acceleration_mps2 if acceleration_mps2 is None else acceleration_mps2
        sp.acceleration_valid, sp.acceleration_mps2 = True, Vector3.from_array(acc)
        if ref.yaw_rad is not None:
            sp.yaw_rate_valid, sp.yaw_rate_radps = True, ref.yaw_rate_radps
    return sp


class Follower:
    """One path being flown from `start_s` (its time 0; a later start waits at the path's
    beginning). `step` once per setpoint; `progress` for planner/status."""

    def __init__(self, path: Path, start_s: float, setpoint_type: int = Trajectory.SETPOINT_FULL_STATE,
                 lag_m: float = 1.5, feedforward: FeedForward = FeedForward(),
                 governor: SpeedGovernor = SpeedGovernor()):
        self.path = path
        self.feedforward = feedforward
        self.governor = governor
        self.setpoint_type = setpoint_type
        self.lag_m = lag_m
        self.started_s = start_s
        self.t_s = 0.0                  # the reference's own time along the path
        self.rate = 1.0                 # how fast that time runs (< 1 while the vehicle lags)
        self.last_s: float | None = None

    def step(self, position_m: np.ndarray, now_s: float, wait_at: tuple[float, np.ndarray] | None = None,
             position_age_s: float = 0.0) -> FollowStep:
        """The setpoint now. `wait_at` (time on the path, a point): the reference may not pass that
        time; there it holds the point itself (zero velocity) until the caller lifts the wait —
        the planner waits at a waypoint the mission has not yet counted as reached.
        `position_age_s`: how old the vehicle's position is; it is compared with where the
        reference was then (a 50 ms old state at 3 m/s is not 0.15 m of tracking error)."""
        if self.last_s is not None and now_s > self.last_s:
            error = self._error(position_m, position_age_s)
            self.rate = float(np.clip(2.0 * (self.lag_m - error) / self.lag_m, 0.0, 1.0))
            t_to = min(self.path.duration_s, self.t_s + self.rate * (now_s - self.last_s))
            # where the vehicle is now (its position is position_age_s old), to judge the FC's command
            now_m = position_m + self.path.sample(self.t_s).velocity_mps * max(0.0, position_age_s)
            self.t_s = self.governor.latest_s(self.path, self.t_s, t_to, now_m)
        if now_s >= self.started_s:     # a path given a later start waits at its beginning
            self.last_s = now_s
        waiting = wait_at is not None and self.t_s >= wait_at[0]
        if waiting:
            self.t_s = wait_at[0]
            ref = self.path.sample(self.t_s)
            ref.position_m = np.asarray(wait_at[1], float).copy()
            ref.velocity_mps, ref.acceleration_mps2, ref.jerk_mps3 = np.zeros(3), np.zeros(3), np.zeros(3)
            ref.yaw_rate_radps = 0.0
            acc = ref.acceleration_mps2
        else:
            # the reference moves at its clock's rate: one that waits for the vehicle streams no
            # velocity (else the FC flies on with it, past the reference, and sits where its
            # position loop balances the feed-forward: PX4, figure8 at 3 m/s, 2.8 m ahead for 100 s)
            ref = self.path.sample(self.t_s)
            ref.velocity_mps, ref.yaw_rate_radps = self.rate * ref.velocity_mps, self.rate * ref.yaw_rate_radps
            acc = self.rate ** 2 * self.feedforward.acceleration(self.path, self.t_s, None if wait_at is None else wait_at[0])
        error = float(np.linalg.norm(ref.position_m - position_m)) if waiting else self._error(position_m, position_age_s)
        finished = self.t_s >= self.path.duration_s and error < self.lag_m / 2
        return FollowStep(setpoint_of(ref, self.setpoint_type, acc), ref, error, finished)

    def _error(self, position_m: np.ndarray, age_s: float) -> float:
        then = self.path.sample(max(0.0, self.t_s - max(0.0, age_s)))
        return float(np.linalg.norm(then.position_m - position_m))

    def progress(self, now_s: float) -> tuple[float, float, float]:
        """(percent of the path's time flown, seconds since it was taken up, seconds of path left)."""
        duration = self.path.duration_s
        percent = 100.0 if duration <= 0 else 100.0 * self.t_s / duration
        return percent, now_s - self.started_s, max(0.0, duration - self.t_s)

    def ahead_xy(self, horizon_s: float, step_s: float = 0.1) -> np.ndarray:
        """The reference's horizontal positions over the next `horizon_s` (obstacle checks)."""
        ts = np.arange(self.t_s, min(self.path.duration_s, self.t_s + horizon_s) + 1e-9, step_s)
        return np.array([self.path.sample(float(t)).position_m[:2] for t in ts]).reshape(-1, 2)
