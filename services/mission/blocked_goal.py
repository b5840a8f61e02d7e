"""A goal the planner cannot reach: planner/status reports it blocked or unreachable for
blocked_timeout_s, or refuses the trajectory handed over. The mission never stays EXECUTING
silently for ever: blocked_action hold -> HOLDING with the reason, skip -> the next waypoint (a
goto holds), rtl -> RTL; each reported in `message`.

A mixin of MissionManager (fsm.py): it reads and writes the manager's fields and fires its events;
it never decides a state change itself, TRANSITIONS does.
"""
from __future__ import annotations

from .states import Event as E, State

BLOCKED_STATES = ("blocked", "unreachable")   # planner/status obstacle_state: no way to the goal
BLOCKED_ACTIONS = ("hold", "skip", "rtl")


class BlockedGoal:
    """planner/status -> GOAL_BLOCKED / GOAL_BLOCKED_RTL / the next waypoint."""

    blocked_since_s: float | None   # planner/status blocked/unreachable since (this goal)

    def on_planner(self, obstacle_state: str, message: str, now_s: float) -> None:
        """planner/status: a goal the planner reports blocked or unreachable for blocked_timeout_s
        reaches the mission (never EXECUTING silently for ever): blocked_action hold -> HOLDING
        with the reason (START retries, SET_CURRENT skips, LAND/RTL); skip -> the next waypoint
        (a goto holds); rtl -> RTL. Each reported in `message`."""
        self.now_s = now_s
        if self.state != State.EXECUTING or obstacle_state not in BLOCKED_STATES:
            self.blocked_since_s = None
            return
        if self.blocked_since_s is None:
            self.blocked_since_s = now_s
        held_s = now_s - self.blocked_since_s
        if held_s < self.cfg.blocked_timeout_s:
            return
        self.blocked_since_s = None
        goal = self.goto_target or self._waypoint(self.wp_index)
        x, y, z = goal.position_m
        what = "goto target" if self.goto_target is not None else \
            f"waypoint {self.wp_index + 1}/{len(self.mission.waypoints)}"
        reason = f"{what} ({x:.1f}, {y:.1f}, {z:.1f}) unreachable for {held_s:.0f} s (planner {obstacle_state}: {message})"
        action = self.cfg.blocked_action
        self.log("goal_blocked", goal=what, planner=obstacle_state, reason=message, action=action)
        if action == "rtl":
            self.fire(E.GOAL_BLOCKED_RTL, f"{reason}: returning home (blocked_action rtl)")
        elif action == "skip" and self.goto_target is None:
            self.message = f"skipped {reason}"
            self._next_waypoint()
        else:
            self.fire(E.GOAL_BLOCKED, f"holding: {reason}; START retries, SET_CURRENT skips, LAND/RTL")

    def on_trajectory_refused(self, why: str) -> None:
        """planner/status: the trajectory handed over is refused for what it asks (limits above the
        planner's own, a frame, a generator; a SetTrajectory one against the planner's live limits).
        The planner holds rather than fly it goal by goal: so does the mission, saying why."""
        if self.state == State.EXECUTING:
            self.fire(E.GOAL_BLOCKED, f"holding: {why}; START retries, LAND/RTL")
