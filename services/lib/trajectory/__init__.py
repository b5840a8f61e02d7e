"""Trajectories the planner flies and the mission checks before it hands one over: the kinematic
limits, the `smooth` generator, and the evaluation of Trajectory messages (POLYNOMIAL, BSPLINE,
BEZIER, timed WAYPOINT). Following one (the planner's clock governor and feed-forward) is the
planner's own: services/planner/follow.py."""
from .blend import BlendedPath, smooth
from .core import KinematicLimits, Path, Peaks, State, peaks
from .evaluate import TrajectoryRefused, evaluate

__all__ = ["BlendedPath", "KinematicLimits", "Path", "Peaks", "State", "TrajectoryRefused", "evaluate", "peaks", "smooth"]
