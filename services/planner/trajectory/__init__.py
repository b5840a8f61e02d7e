"""Trajectories the planner flies: the kinematic limits, the `smooth` generator, and the
evaluation of Trajectory messages (POLYNOMIAL, BSPLINE, BEZIER, timed WAYPOINT)."""
from .blend import BlendedPath, smooth
from .core import Limits, Path, Peaks, State, peaks
from .evaluate import TrajectoryRefused, evaluate

__all__ = ["BlendedPath", "Limits", "Path", "Peaks", "State", "TrajectoryRefused", "evaluate", "peaks", "smooth"]
