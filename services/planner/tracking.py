"""The trajectory the mission hands the planner (mission/active_trajectory), flown while the
mission's goal is on it; without one, or off it, the planner flies goal by goal as before.

Rules, each for a reason:
- The path is made when it is first flown, from where the vehicle is then (a smooth path starts
  at the vehicle, at the velocity the planner last sent: a take-off still climbing is not braked
  first; a typed one must start there), never from where it was when sent.
- Only while the mission's current goal is one of the trajectory's waypoints (or, for a typed
  trajectory, its end): a hold, a goto or a landing is not on it and takes over at once.
- The reference waits at a waypoint the mission has not counted as reached yet (the mission
  counts by the vehicle's distance), holding the waypoint itself, so the two never disagree
  about where the vehicle is going. Unless the count is only late: once the vehicle has come
  within `acceptance_radius_m` of the waypoint, the reference runs on past it for up to
  COUNT_GRACE_S (the next goal comes a message later; on PX4 at load 9 it came 0.5 s after the
  count, and the reference stopped dead at the waypoint for 0.22 s, braking the vehicle from 1.9 m/s).
- A hold of less than RESUME_S (a late vehicle state makes the mission hold and resume, and it
  hands the same waypoints over again as a new stretch) resumes the path being flown where its
  reference stood, if the waypoints handed over are that path's: a path made anew starts at rest
  and braked the vehicle from full speed (figure8 at 3 m/s, load 10: 3.6 m/s², 16 m/s³ by truth).
- Obstacles keep today's rules: when the costmap blocks the path ahead, the planner leaves the
  path and flies to the current goal with obstacle avoidance; a smooth path is made anew from the
  next goal on (from the vehicle, at its velocity then) — clearance is never traded for smoothness.
  A typed trajectory is not re-planned: the planner leaves it for good and flies to its end goal by
  goal with obstacle avoidance, saying why.
- Waypoints are timed by the message's own `generator_name`, else the planner's active generator
  (`cfg.generator`); the `waypoint` generator makes no path: goal by goal.
- A trajectory refused for what it asks (a typed one's fields, limits above the planner's own, a
  frame other than map, an unknown generator) is not flown goal by goal instead: the planner holds
  at its goals (`holds_for`) and says why, and the mission holds (a SetTrajectory goal fails). One
  the smooth generator cannot time from here (waypoints too close for the limits) is flown goal by
  goal, saying why.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import msgspec
import numpy as np

from aeroperception.schemas import Trajectory
from aeroperception.services.lib.trajectory.core import KinematicLimits, PlanningMargin
from aeroperception.services.lib.trajectory.evaluate import TrajectoryRefused, evaluate
from aeroperception.services.lib.trajectory.generators import GENERATORS, check_frames, generator_of, limits_of, path_for
from aeroperception.services.runtime.config import param

from .follow import FeedForward, FollowStep, Follower, SpeedGovernor

ON_PATH_M = 0.01          # a goal this close to a trajectory waypoint is that waypoint
AHEAD_S = 3.0             # the stretch of path checked against the costmap
RESUME_S = 1.0            # a path left for a hold this short is resumed (braking from 3 m/s to rest takes ~1 s)
COUNT_GRACE_S = 1.0       # the longest the reference runs on past a waypoint the vehicle reached, not yet counted
STREAM_BROKEN_PERIODS = 3  # setpoints missed for this many loop periods: the vehicle no longer follows the last one


def start_velocity_mps(last_sent_mps: np.ndarray | None, sent_age_s: float, period_s: float,
                       vehicle_mps: np.ndarray) -> np.ndarray:
    """The velocity a path made now starts at: the velocity last sent (None: none, or it had no
    velocity) while the setpoint stream is unbroken -- the reference goes on without a step, so a
    take-off still climbing is not braked first; else the vehicle's own, which is what it flies
    after a broken stream (a stall, a restart, the flight controller's own hold)."""
    if last_sent_mps is not None and sent_age_s < STREAM_BROKEN_PERIODS * period_s:
        return np.asarray(last_sent_mps, float)
    return np.asarray(vehicle_mps, float)


def is_clear(msg: Trajectory) -> bool:
    """An empty trajectory message: the mission withdraws its trajectory."""
    return not (msg.waypoints or msg.poly_coeffs_x or msg.poly_coeffs_y or msg.poly_coeffs_z)


@dataclass(frozen=True)
class TrackerConfig:
    """What the planner's parameters set for trajectories (defaults, units and ranges: contract.py).
    A change applies to the next trajectory made (the one being flown keeps its timing)."""

    max_velocity_mps: float = param("max_velocity_mps")
    z_vel_max_up_mps: float = param("z_vel_max_up_mps")
    z_vel_max_dn_mps: float = param("z_vel_max_dn_mps")
    acc_hor_mps2: float = param("acc_hor_mps2")
    acc_up_mps2: float = param("acc_up_mps2")
    acc_down_mps2: float = param("acc_down_mps2")
    jerk_mps3: float = param("jerk_mps3")
    yaw_rate_max_radps: float = param("yaw_rate_max_dps", math.radians)
    acceptance_radius_m: float = param("acceptance_radius_m")
    lag_m: float = param("trajectory_lag_m")
    generator: str = param("trajectory_generator")   # the planner's active generator (a message may name its own)
    ff_lead_s: float = param("ff_lead_s")
    drag_per_s: float = param("drag_per_s")
    fc_xy_vel_d: float = param("fc_xy_vel_d")
    fc_xy_gain_per_s: float = param("fc_xy_gain_per_s")   # the FC's horizontal position gain (PX4's MPC_XY_P): SpeedGovernor; 0 = off
    fc_velocity_error_mps: float = param("fc_velocity_error_mps")   # generated paths are timed this far below the speed caps; 0 = off
    fc_jerk_error_mps3: float = param("fc_jerk_error_mps3")         # ... and planned this far below the jerk limit; 0 = off

    @property
    def limits(self) -> KinematicLimits:
        """The limits that bound every trajectory (PX4's MPC_* names; max_velocity_mps is MPC_XY_VEL_MAX)."""
        return KinematicLimits(xy_vel_max_mps=self.max_velocity_mps, z_vel_max_up_mps=self.z_vel_max_up_mps,
                               z_vel_max_dn_mps=self.z_vel_max_dn_mps, acc_hor_mps2=self.acc_hor_mps2,
                               acc_up_mps2=self.acc_up_mps2, acc_down_mps2=self.acc_down_mps2, jerk_mps3=self.jerk_mps3,
                               yaw_rate_max_radps=self.yaw_rate_max_radps)

    @property
    def feedforward(self) -> FeedForward:
        return FeedForward(self.ff_lead_s, self.drag_per_s, self.fc_xy_vel_d)

    @property
    def margin(self) -> PlanningMargin:
        """What the flight controller adds to a generated path: it is planned inside the limits by this."""
        return PlanningMargin(self.fc_velocity_error_mps, self.fc_jerk_error_mps3)


class TrajectoryTracker:
    def __init__(self, cfg: TrackerConfig):
        self.cfg = cfg
        self.msg: Trajectory | None = None
        self.follower: Follower | None = None
        self.first_index = 0            # the message's waypoint the follower's path begins with (< 0: one before it)
        self.refused = ""               # why the message (or its remaining part) cannot be flown
        self.refusal_holds = False      # ... and the planner holds at its goals rather than fly them one by one
        self.blocked = ""               # a typed trajectory blocked by an obstacle: holding, why
        self.diverted_goal: np.ndarray | None = None   # avoiding obstacles towards this goal
        self.built = 0
        self.last_index = 0              # the message's waypoint the goal matched last
        self.typed_end: np.ndarray | None = None    # where a typed trajectory ends (the mission's goal)
        self.left: tuple[Follower, Trajectory, int, float] | None = None   # (follower, its message, first_index, when)
        self.resumed = 0
        self.count: tuple[int, float, float | None] | None = None   # (goal, vehicle's closest approach, passed at)
        self.late_counts = 0             # waypoints the reference ran on past before the mission counted them

    @property
    def trajectory_id(self) -> str:
        return self.msg.trajectory_id if self.msg is not None else ""

    def offer(self, msg: Trajectory, now_s: float | None = None) -> None:
        """A new message from the mission (the caller skips repeats of the same one), at `now_s`
        (None: the path being flown is not kept to resume)."""
        if self.follower is not None and now_s is not None:
            self._leave(now_s)
        self._carry_over(msg)
        self.follower, self.refused, self.blocked, self.diverted_goal = None, "", "", None
        self.refusal_holds = False
        self.msg = None if is_clear(msg) else msg
        self.typed_end, self.last_index, self.count = None, 0, None
        if self.msg is None:
            return
        try:
            if not self._generated():
                path = evaluate(self.msg)
                self.typed_end = path.sample(path.duration_s).position_m
            check_frames(self.msg)
            limits_of(self.msg, self.cfg.limits)
            if self._generated() and self.generator() not in GENERATORS:
                raise TrajectoryRefused(f"`generator_name` {self.msg.generator_name!r} is not a generator: "
                                        f"{', '.join(GENERATORS)}")
        except TrajectoryRefused as e:
            self.refused, self.refusal_holds = str(e), True

    def holds_for(self, goal_m: np.ndarray | None) -> bool:
        """The trajectory is refused for what it asks and the goal is on it: hold, do not fly there."""
        if not (self.refused and self.refusal_holds and self.msg is not None and goal_m is not None):
            return False
        if self._generated():
            return self._index_of(goal_m) is not None
        return self.typed_end is not None and bool(np.linalg.norm(goal_m - self.typed_end) < ON_PATH_M)

    def generator(self) -> str:
        """The generator the current message's waypoints are flown with ('' for a typed one)."""
        if self.msg is None or not self._generated():
            return ""
        return generator_of(self.msg, self.cfg.generator)

    def set_generator(self, name: str) -> None:
        """The planner's active generator changed: a path of the old one is made anew with it."""
        self.cfg = dataclasses.replace(self.cfg, generator=name)
        self.left = None
        if self.msg is not None and self._generated():
            self.follower = None

    def _generated(self) -> bool:
        return (self.msg.trajectory_type == Trajectory.TRAJECTORY_WAYPOINT and not self.msg.waypoint_times_s)

    def _index_of(self, goal_m: np.ndarray) -> int | None:
        """Which waypoint of the message the goal is (a typed trajectory: only its end)."""
        if self._generated():
            # from the goal matched last on: a mission may pass the same point twice (survey_01
            # ends where it began), and the later visit is the one ahead
            n = len(self.msg.waypoints)
            for k in [*range(self.last_index, n), *range(0, self.last_index)]:
                p = self.msg.waypoints[k].pose.position
                if np.linalg.norm(goal_m - np.array([p.x, p.y, p.z])) < ON_PATH_M:
                    self.last_index = k
                    return k
            return None
        return 0 if self.typed_end is not None and np.linalg.norm(goal_m - self.typed_end) < ON_PATH_M else None

    def step(self, position_m: np.ndarray, yaw_rad: float, now_s: float, goal_m: np.ndarray | None,
             path_blocked: Callable[[np.ndarray], bool] | None = None, position_age_s: float = 0.0,
             velocity_mps: np.ndarray | None = None) -> FollowStep | None:
        """The setpoint from the trajectory, or None: fly goal by goal (no trajectory, a hold, a
        goal off the trajectory, refused, or avoiding an obstacle towards the current goal).
        `velocity_mps`: the velocity a path made now starts at (None: at rest)."""
        if self.msg is None or goal_m is None or self.refused or self.blocked:
            return None
        if self._generated() and GENERATORS[self.generator()].make is None:
            return None                   # the waypoint generator: goal by goal
        k = self._index_of(goal_m)
        if k is None:
            if self.follower is not None:
                self._leave(now_s)        # a hold, goto or landing took over
            self.follower = None
            return None
        if self.diverted_goal is not None:
            if np.linalg.norm(self.diverted_goal - goal_m) < ON_PATH_M:
                return None               # still avoiding towards this goal
            self.diverted_goal = None     # the mission moved on: a new path from here
        if self.follower is None and not self._resume(now_s, k) or (self._generated() and k < self.first_index):
            if not self._build(position_m, yaw_rad, now_s, k, velocity_mps):
                return None
        at = self._wait_at(k)
        wait = None if at is not None and self._counted_late(k, at[1], position_m, now_s) else at
        fs = self.follower.step(position_m, now_s, wait, position_age_s)
        if at is not None and wait is None and self.count[2] is None and self.follower.t_s >= at[0]:
            self.count = (k, self.count[1], now_s)       # ran on past the waypoint, not counted yet
            self.late_counts += 1
        if path_blocked is not None and path_blocked(self.follower.ahead_xy(AHEAD_S)):
            self.follower = None
            if self._generated():
                self.diverted_goal = np.asarray(goal_m, float).copy()
            else:
                self.blocked = ("the trajectory ahead is blocked by an obstacle: flying to its end around it "
                                "(a typed trajectory is not re-planned)")
            return None
        return fs

    def _leave(self, now_s: float) -> None:
        """The follower is dropped (a hold, a new message): kept RESUME_S for `_resume`."""
        if self.msg is not None and self._generated():
            self.left = (self.follower, self.msg, self.first_index, now_s)

    def _carry_over(self, msg: Trajectory) -> None:
        """A new message whose waypoints are the tail of the left path's (the same way handed over
        again from a later waypoint): the left path stays resumable, its indices shifted to it;
        an empty message (a hold) keeps it; any other drops it."""
        if self.left is None or is_clear(msg):
            return
        follower, old, first, when = self.left
        n = len(msg.waypoints)
        same = msgspec.structs.replace(old, header=msg.header, trajectory_id=msg.trajectory_id, waypoints=msg.waypoints)
        shift = len(old.waypoints) - n
        tail = msg.trajectory_type == Trajectory.TRAJECTORY_WAYPOINT and not msg.waypoint_times_s and n and shift >= 0
        if tail and same == msg and old.waypoints[shift:] == msg.waypoints:
            self.left = (follower, msg, first - shift, when)
        else:
            self.left = None

    def _resume(self, now_s: float, k: int) -> bool:
        """Take the left follower back when it flies this message, goal k is on it and it was left
        less than RESUME_S ago; its reference goes on from where it stood."""
        if self.left is None:
            return False
        follower, msg, first, when = self.left
        self.left = None
        if msg is not self.msg or now_s - when >= RESUME_S or k < first:
            return False
        follower.last_s = now_s
        self.follower, self.first_index = follower, first
        self.resumed += 1
        return True

    def _build(self, position_m: np.ndarray, yaw_rad: float, now_s: float, k: int,
               velocity_mps: np.ndarray | None) -> bool:
        msg = self.msg
        if self._generated():
            msg = msgspec.structs.replace(self.msg, waypoints=list(self.msg.waypoints[k:]))
        try:
            path = path_for(msg, position_m, yaw_rad, self.cfg.limits, self.cfg.acceptance_radius_m, self.cfg.generator,
                            self.cfg.margin, velocity_mps)
        except TrajectoryRefused as e:
            self.refused, self.refusal_holds = str(e), not self._generated()
            return False
        if path is None:
            return False
        cap = limits_of(self.msg, self.cfg.limits).inside(self.cfg.margin).xy_vel_max_mps
        governor = SpeedGovernor(self.cfg.fc_xy_gain_per_s, cap)
        self.follower = Follower(path, now_s, self.msg.setpoint_type, self.cfg.lag_m, self.cfg.feedforward, governor)
        self.first_index = k
        self.built += 1
        return True

    def _counted_late(self, k: int, waypoint_m: np.ndarray, position_m: np.ndarray, now_s: float) -> bool:
        """The vehicle has come within acceptance_radius_m of goal k's waypoint and the reference
        passed it less than COUNT_GRACE_S ago: the mission's count is only late, do not wait."""
        if self.count is None or self.count[0] != k:
            self.count = (k, float("inf"), None)
        closest = min(self.count[1], float(np.linalg.norm(np.asarray(position_m, float) - waypoint_m)))
        self.count = (k, closest, self.count[2])
        passed = self.count[2]
        return closest < self.cfg.acceptance_radius_m and (passed is None or now_s - passed < COUNT_GRACE_S)

    def _wait_at(self, k: int) -> tuple[float, np.ndarray] | None:
        """Hold at goal k's waypoint (on the follower's path: index k - first_index + 1, the
        path starting at the vehicle) until the mission counts it reached."""
        if not self._generated():
            return None
        j = k - self.first_index + 1
        times = self.follower.path.waypoint_times_s
        if not 0 < j < len(times):
            return None
        p = self.msg.waypoints[k].pose.position
        return times[j], np.array([p.x, p.y, p.z])

    def progress(self, now_s: float) -> tuple[float, float, float] | None:
        return self.follower.progress(now_s) if self.follower is not None else None
