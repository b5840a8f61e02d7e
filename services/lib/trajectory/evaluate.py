"""A Trajectory message as a path the planner can fly, field by field as its type defines them.

- POLYNOMIAL: `poly_coeffs_x/y/z` (and `poly_coeffs_yaw` for a heading) hold m segments of
  `poly_order + 1` coefficients each, lowest order first, in each segment's own time (seconds from
  the segment's start); the m segments split `total_duration_s` equally.
- BSPLINE: the waypoints are the control points of a clamped B-spline of degree `poly_order` with
  uniform knots over `total_duration_s` (it starts at the first waypoint and ends at the last).
- BEZIER: the waypoints are the control points of m Bezier curves of degree `poly_order` joined
  end to end (m * poly_order + 1 points; piece i uses points i*d .. (i+1)*d), splitting
  `total_duration_s` equally.
- WAYPOINT: with `waypoint_times_s`, a cubic spline through every waypoint at its time, at rest
  at the first and the last; without, a generator from the registry allocates the times.
Headings come from the waypoints' orientations (unwrapped). A field the type does not use is
refused by name, never ignored.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import BPoly, BSpline, CubicSpline, PPoly

from aeroperception.schemas import Trajectory

from .core import State, wrap_pi

MAX_ORDER = 9


class TrajectoryRefused(ValueError):
    """The message cannot be flown as given; the text names the field."""


class SplinePath:
    """A path from scipy piecewise polynomials of (x, y, z[, yaw]) over [0, duration_s]."""

    def __init__(self, curve, duration_s: float, waypoint_times_s: list[float], has_yaw: bool):
        order = getattr(curve, "k", 3)      # a B-spline has no derivative above its degree: zero there
        zero = np.zeros(curve(0.0).shape)
        self.derivs = [curve, *(curve.derivative(k) if k <= order else (lambda _t: zero) for k in (1, 2, 3))]
        self.duration_s = float(duration_s)
        self.waypoint_times_s = waypoint_times_s
        self.has_yaw = has_yaw

    def sample(self, t_s: float) -> State:
        t = min(max(t_s, 0.0), self.duration_s)
        p, v, a, j = (np.asarray(d(t), dtype=float).reshape(-1) for d in self.derivs)
        yaw = wrap_pi(float(p[3])) if self.has_yaw else None
        return State(p[:3].copy(), v[:3].copy(), a[:3].copy(), j[:3].copy(), yaw,
                     float(v[3]) if self.has_yaw else 0.0)


def _yaw_of(pose) -> float:
    return pose.orientation.to_euler()[2]


def _points(msg: Trajectory) -> np.ndarray:
    return np.array([[w.pose.position.x, w.pose.position.y, w.pose.position.z] for w in msg.waypoints], dtype=float)


def _with_yaw(msg: Trajectory, points: np.ndarray) -> np.ndarray:
    yaws = np.unwrap([_yaw_of(w.pose) for w in msg.waypoints])
    return np.column_stack([points, yaws])


def _refuse_unused(msg: Trajectory, fields: tuple[str, ...], kind: str) -> None:
    for name in fields:
        if getattr(msg, name):
            raise TrajectoryRefused(f"`{name}` is not used by a {kind} trajectory: leave it empty")


def _duration(msg: Trajectory, kind: str) -> float:
    T = msg.total_duration_s
    if not (math.isfinite(T) and T > 0):
        raise TrajectoryRefused(f"`total_duration_s` must be positive for a {kind} trajectory, got {T}")
    return T


def _order(msg: Trajectory, kind: str, least: int = 1) -> int:
    if not least <= msg.poly_order <= MAX_ORDER:
        raise TrajectoryRefused(f"`poly_order` must be {least}..{MAX_ORDER} for a {kind} trajectory, got {msg.poly_order}")
    return msg.poly_order


def polynomial(msg: Trajectory) -> SplinePath:
    _refuse_unused(msg, ("waypoints", "waypoint_times_s"), "POLYNOMIAL")
    T, order = _duration(msg, "POLYNOMIAL"), _order(msg, "POLYNOMIAL", 0)
    n = order + 1
    axes = [msg.poly_coeffs_x, msg.poly_coeffs_y, msg.poly_coeffs_z]
    has_yaw = bool(msg.poly_coeffs_yaw)
    if has_yaw:
        axes.append(msg.poly_coeffs_yaw)
    names = ["poly_coeffs_x", "poly_coeffs_y", "poly_coeffs_z", "poly_coeffs_yaw"]
    if not msg.poly_coeffs_x or len(msg.poly_coeffs_x) % n:
        raise TrajectoryRefused(f"`poly_coeffs_x` must hold m x (poly_order + 1) = m x {n} coefficients, "
                                f"got {len(msg.poly_coeffs_x)}")
    for name, coeffs in zip(names, axes):
        if len(coeffs) != len(msg.poly_coeffs_x):
            raise TrajectoryRefused(f"`{name}` has {len(coeffs)} coefficients, `poly_coeffs_x` {len(msg.poly_coeffs_x)}")
        if not all(math.isfinite(c) for c in coeffs):
            raise TrajectoryRefused(f"`{name}` holds a non-finite coefficient")
    m = len(msg.poly_coeffs_x) // n
    # PPoly wants c[power from highest, segment, axis]
    c = np.array(axes, dtype=float).reshape(len(axes), m, n).transpose(2, 1, 0)[::-1]
    breaks = np.linspace(0.0, T, m + 1)
    return SplinePath(PPoly(c, breaks), T, [float(b) for b in breaks], has_yaw)


def bspline(msg: Trajectory) -> SplinePath:
    _refuse_unused(msg, ("waypoint_times_s", "poly_coeffs_x", "poly_coeffs_y", "poly_coeffs_z", "poly_coeffs_yaw"),
                   "BSPLINE")
    T, degree = _duration(msg, "BSPLINE"), _order(msg, "BSPLINE")
    n = len(msg.waypoints)
    if n < degree + 1:
        raise TrajectoryRefused(f"`waypoints`: a degree-{degree} B-spline needs at least {degree + 1} control points, got {n}")
    inner = np.linspace(0.0, T, n - degree + 1)[1:-1]
    knots = np.concatenate([np.zeros(degree + 1), inner, np.full(degree + 1, T)])
    curve = BSpline(knots, _with_yaw(msg, _points(msg)), degree)
    return SplinePath(curve, T, [0.0, T], True)


def bezier(msg: Trajectory) -> SplinePath:
    _refuse_unused(msg, ("waypoint_times_s", "poly_coeffs_x", "poly_coeffs_y", "poly_coeffs_z", "poly_coeffs_yaw"),
                   "BEZIER")
    T, degree = _duration(msg, "BEZIER"), _order(msg, "BEZIER")
    n = len(msg.waypoints)
    if n < degree + 1 or (n - 1) % degree:
        raise TrajectoryRefused(f"`waypoints`: Bezier pieces of degree {degree} need m x {degree} + 1 control points, got {n}")
    m = (n - 1) // degree
    ctrl = _with_yaw(msg, _points(msg))
    c = np.stack([ctrl[i * degree:(i + 1) * degree + 1] for i in range(m)], axis=1)   # [k, piece, axis]
    breaks = np.linspace(0.0, T, m + 1)
    return SplinePath(BPoly(c, breaks), T, [float(b) for b in breaks], True)


def timed_waypoints(msg: Trajectory) -> SplinePath:
    _refuse_unused(msg, ("poly_coeffs_x", "poly_coeffs_y", "poly_coeffs_z", "poly_coeffs_yaw", "poly_order"), "WAYPOINT")
    times = np.asarray(msg.waypoint_times_s, dtype=float)
    if len(times) < 2:
        raise TrajectoryRefused("`waypoints`: a timed WAYPOINT trajectory needs at least 2 waypoints")
    if times[0] != 0.0 or not np.all(np.diff(times) > 0) or not np.all(np.isfinite(times)):
        raise TrajectoryRefused("`waypoint_times_s` must start at 0 and strictly increase")
    if msg.total_duration_s and abs(msg.total_duration_s - times[-1]) > 1e-6:
        raise TrajectoryRefused(f"`total_duration_s` {msg.total_duration_s} differs from the last waypoint time "
                                f"{times[-1]}: give 0 or the same")
    curve = CubicSpline(times, _with_yaw(msg, _points(msg)), bc_type="clamped")
    return SplinePath(curve, float(times[-1]), [float(t) for t in times], True)


EVALUATORS = {Trajectory.TRAJECTORY_POLYNOMIAL: polynomial, Trajectory.TRAJECTORY_BSPLINE: bspline,
              Trajectory.TRAJECTORY_BEZIER: bezier}


def evaluate(msg: Trajectory) -> SplinePath:
    """The path a POLYNOMIAL, BSPLINE, BEZIER or timed WAYPOINT message defines. An untimed
    WAYPOINT message is a generator's job (`generate`), so it is refused here."""
    if msg.trajectory_type == Trajectory.TRAJECTORY_WAYPOINT:
        if not msg.waypoint_times_s:
            raise TrajectoryRefused("`waypoint_times_s` is empty: an untimed WAYPOINT trajectory is generated, not evaluated")
        return timed_waypoints(msg)
    fn = EVALUATORS.get(msg.trajectory_type)
    if fn is None:
        raise TrajectoryRefused(f"`trajectory_type` {msg.trajectory_type} is not one of WAYPOINT 0, POLYNOMIAL 1, "
                                "BSPLINE 2, BEZIER 3")
    return fn(msg)
