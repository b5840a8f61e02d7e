"""The planner's configuration: every parameter of contract.PARAMS, referenced once (runtime
config.py rebuilds it on a live change and calls PlannerService.on_config once)."""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.services.runtime import param, section

from .avoidance import AvoidanceConfig
from .tracking import TrackerConfig


@dataclass(frozen=True)
class PlannerConfig:
    tracker: TrackerConfig = section(TrackerConfig)           # trajectories (tracking.py)
    avoidance: AvoidanceConfig = section(AvoidanceConfig)     # obstacles (avoidance.py)
    max_velocity_mps: float = param("max_velocity_mps")       # goal by goal: the P-controller's speed cap
    kp: float = param("kp")
    acceptance_radius_m: float = param("acceptance_radius_m")
    rate_hz: float = param("rate_hz")
    state_timeout_s: float = param("state_timeout_s")
    goal_timeout_s: float = param("goal_timeout_s")
    obstacle_avoidance: bool = param("obstacle_avoidance")
    trajectory_generator: str = param("trajectory_generator")  # the swappable parts (plugins.py)
    controller: str = param("controller")
    estimator: str = param("estimator")
    state_dir: str = param("state_dir")
    hover_speed_mps: float = param("hover_speed_mps")
