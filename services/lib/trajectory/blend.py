"""The `smooth` generator: straight legs between waypoints flown at constant speed, joined by
minimum-jerk velocity blends.

Why this shape (and not minimum-snap polynomials through the waypoints): a survey or an obstacle
detour is a polyline someone chose, and a polynomial through its corners bulges off the straight
legs between them, which trades clearance and cross-track error for smoothness. Here the vehicle is
exactly on the straight legs except inside a corner blend, and a blend cuts its corner by at most a
set distance (a share of the acceptance radius, so the waypoint still counts as reached); corners
are rounded, not passed through, and the legs are slowed near a corner only as much as that bound
needs.

The reference is a piecewise-constant velocity timeline (the legs, a slower piece at each end of a
leg where its corner needs one, rest before and after), each change of velocity spread over a
blend with the quintic smoothstep s(u) = 10u^3 - 15u^4 + 6u^5: acceleration and jerk are continuous
and zero at the blend's ends, the peaks are 1.875 dv/T (acceleration) and 5.774 dv/T^2 (jerk), and,
s being antisymmetric about the blend's middle, the position after a blend is the same as without
it: the blends never move the legs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .core import KinematicLimits, State, wrap_pi

ACC_PEAK = 1.875                  # max s'(u)
JERK_PEAK = 10.0 / math.sqrt(3)   # max |s''(u)| = 5.774
CUT_AT_MIDDLE = 0.078125          # S(1/2), S(u) = integral of s: a corner is cut by |dv| T S(1/2)
CORNER_SHARE = 0.5                # a corner is cut by at most this share of the acceptance radius (the rest is
                                  # left for tracking error: the mission counts a waypoint by the vehicle's distance)
MIN_SPEED_MPS = 0.05
SLOWER = (0.85, 0.97)             # a leg too short to hold its blends is slowed in steps within these, by the
                                  # square root of the share of its length it has (the length a leg's blends
                                  # take grows with speed^1.5 to speed^2): fast when far off, fine when close
                                  # (in fixed 15 % steps figure8's 4 m legs lost 15 % where 3-6 % was enough)
MAX_PASSES = 60
REBASE_PASSES = 20                # the first leg's start (which moves its direction, speed and blend): a fixed point


def smoothstep(u: np.ndarray | float):
    """s, s', s'', s''' and the integral S of the quintic smoothstep at u in [0, 1]."""
    u2, u3 = u * u, u * u * u
    s = u3 * (10 - 15 * u + 6 * u2)
    ds = 30 * u2 * (1 - u) ** 2
    dds = 60 * u - 180 * u2 + 120 * u3
    ddds = 60 - 360 * u + 360 * u2
    integral = u2 * u2 * (2.5 - 3 * u + u2)
    return s, ds, dds, ddds, integral


def blend_time_s(dv: np.ndarray, limits: KinematicLimits) -> float:
    """The shortest blend that changes velocity by `dv` within the acceleration and jerk limits."""
    dv_xy, dv_z = math.hypot(dv[0], dv[1]), float(dv[2])
    if math.hypot(dv_xy, dv_z) < 1e-9:
        return 0.0
    acc_z = limits.acc_up_mps2 if dv_z > 0 else limits.acc_down_mps2
    return max(ACC_PEAK * dv_xy / limits.acc_hor_mps2, ACC_PEAK * abs(dv_z) / acc_z,
               math.sqrt(JERK_PEAK * math.hypot(dv_xy, dv_z) / limits.jerk_mps3))


def corner_cut_m(dv: np.ndarray, limits: KinematicLimits) -> float:
    """How far a blend of `dv` passes from the corner it rounds."""
    return CUT_AT_MIDDLE * float(np.linalg.norm(dv)) * blend_time_s(dv, limits)


@dataclass
class Piece:
    velocity_mps: np.ndarray
    duration_s: float


class BlendedPath:
    """The timeline of pieces, sampled. Built by `smooth()`."""

    def __init__(self, start_m: np.ndarray, pieces: list[Piece], limits: KinematicLimits,
                 corner_piece: list[int], yaws: list[float | None]):
        self.limits = limits
        self.velocities = np.array([p.velocity_mps for p in pieces])
        durations = np.array([p.duration_s for p in pieces])
        self.starts_s = np.concatenate([[0.0], np.cumsum(durations)])   # piece i: [starts[i], starts[i+1]]
        self.positions_m = start_m + np.concatenate(
            [np.zeros((1, 3)), np.cumsum(self.velocities * durations[:, None], axis=0)])
        # blend b joins piece b and b+1, centred on starts[b+1]
        self.blend_s = np.array([blend_time_s(self.velocities[b + 1] - self.velocities[b], limits)
                                 for b in range(len(pieces) - 1)])
        self.motion_s = float(self.starts_s[-1])
        # the corners' times are their blends' middles (nearest the corner); the ends are at rest
        self.waypoint_times_s = [float(self.starts_s[i]) for i in corner_piece]
        self.waypoint_times_s[0], self.waypoint_times_s[-1] = 0.0, self.motion_s
        self._yaw = _YawProfile(self.waypoint_times_s, yaws, limits.yaw_rate_max_radps)
        self.duration_s = max(self.motion_s, self._yaw.end_s)   # a last turn may go on after the stop

    def sample(self, t_s: float) -> State:
        yaw, yaw_rate = self._yaw.at(min(max(t_s, 0.0), self.duration_s))
        t = min(max(t_s, 0.0), self.motion_s)
        i = int(np.clip(np.searchsorted(self.starts_s, t, side="right") - 1, 0, len(self.velocities) - 1))
        velocity = self.velocities[i].copy()
        position = self.positions_m[i] + velocity * (t - self.starts_s[i])
        acc, jerk = np.zeros(3), np.zeros(3)
        for b in (i - 1, i):   # the blends that may cover t: ending the piece before, starting the next
            if b < 0 or b >= len(self.blend_s) or self.blend_s[b] <= 0:
                continue
            width, centre = self.blend_s[b], self.starts_s[b + 1]
            u = (t - (centre - width / 2)) / width
            if not 0.0 <= u <= 1.0:
                continue
            dv = self.velocities[b + 1] - self.velocities[b]
            s, ds, dds, _, integral = smoothstep(u)
            # velocity relative to the unblended piece that holds t (b's before the centre, b+1's after)
            before = t < centre
            velocity += dv * (s if before else s - 1.0)
            position += dv * width * (integral if before else integral - (u - 0.5))
            acc += dv * ds / width
            jerk += dv * dds / width ** 2
        return State(position, velocity, acc, jerk, yaw, yaw_rate)


class _YawProfile:
    """Heading: each waypoint's yaw reached by a minimum-jerk turn that starts as the leg to it
    begins, within the yaw-rate limit (a turn longer than its leg ends later)."""

    def __init__(self, times_s: list[float], yaws: list[float | None], max_rate_radps: float):
        self.turns: list[tuple[float, float, float, float]] = []   # (start, duration, from, delta)
        current = next((y for y in yaws if y is not None), None)
        self.initial = current
        free_at = 0.0
        for k in range(1, len(yaws)):
            yaw = yaws[k]
            if yaw is None or current is None:
                continue
            delta = wrap_pi(yaw - current)
            if abs(delta) > 1e-9:
                start = max(times_s[k - 1], free_at)
                duration = max(times_s[k] - start, ACC_PEAK * abs(delta) / max_rate_radps)
                self.turns.append((start, duration, current, delta))
                free_at = start + duration
            current = yaw
        self.end_s = free_at

    def at(self, t: float) -> tuple[float | None, float]:
        yaw = self.initial
        for start, duration, origin, delta in self.turns:
            if t >= start + duration:
                yaw = origin + delta
            elif t >= start:
                s, ds, *_ = smoothstep((t - start) / duration)
                return wrap_pi(origin + delta * s), delta * ds / duration
            else:
                break
        return (wrap_pi(yaw) if yaw is not None else None), 0.0


def smooth(points_m: np.ndarray, limits: KinematicLimits, acceptance_radius_m: float,
           speed_caps_mps: list[float] | None = None, yaws_rad: list[float | None] | None = None,
           start_velocity_mps: np.ndarray | None = None) -> BlendedPath:
    """A path from points_m[0] through every point to rest at the last one.

    It starts at `start_velocity_mps` (None: at rest): a vehicle handed a path while it moves (the
    take-off still climbing, a re-plan) is not braked first; that velocity is blended into the
    first leg's, which then starts where the blend's middle leaves it, so the waypoints stay exact.
    `speed_caps_mps[k]` caps leg k (0 or None: the limits only); `yaws_rad[k]` is the heading at
    point k (None: keep the previous one). Repeated points are merged.
    """
    pts = np.asarray(points_m, dtype=float).reshape(-1, 3)
    n = len(pts)
    caps = list(speed_caps_mps) if speed_caps_mps is not None else [0.0] * max(n - 1, 0)
    yaws = list(yaws_rad) if yaws_rad is not None else [None] * n
    if len(caps) != max(n - 1, 0) or len(yaws) != n:
        raise ValueError(f"{n} points need {n - 1} speed caps and {n} yaws, got {len(caps)} and {len(yaws)}")
    if acceptance_radius_m <= 0:
        raise ValueError("acceptance_radius_m must be positive")
    keep = [0] + [k for k in range(1, n) if np.linalg.norm(pts[k] - pts[k - 1]) > 1e-6]
    merged_yaws = [yaws[0]] + [yaws[k] for k in keep[1:]]
    for j, k in enumerate(keep[1:], 1):      # a merged point keeps the last heading asked of it
        nxt = keep[j + 1] if j + 1 < len(keep) else n
        merged_yaws[j] = next((yaws[m] for m in range(nxt - 1, k - 1, -1) if yaws[m] is not None), yaws[k])
    caps = [caps[k - 1] for k in keep[1:]]
    pts = pts[keep]
    if len(pts) == 1:
        return BlendedPath(pts[0], [Piece(np.zeros(3), 0.0)], limits, [0], merged_yaws)

    v0 = np.zeros(3) if start_velocity_mps is None else np.asarray(start_velocity_mps, float).reshape(3)
    slowed = np.ones(len(pts) - 1)       # each leg's share of its speed cap, lowered while a leg is too short
    max_cut = CORNER_SHARE * acceptance_radius_m
    first_leg_from = pts[0]              # where the first leg starts: the start, moved on by v0 for half a blend
    for _ in range(MAX_PASSES):
        for _rebase in range(REBASE_PASSES):
            legs = np.diff(np.vstack([first_leg_from, pts[1:]]), axis=0)
            lengths = np.linalg.norm(legs, axis=1)
            if lengths[0] < 1e-6:
                raise ValueError("the start velocity carries the vehicle onto the first waypoint")
            dirs = legs / lengths[:, None]
            speed = slowed * [min(limits.speed_cap_mps(d), c if c and c > 0 else math.inf) for d, c in zip(dirs, caps)]
            moved = pts[0] + v0 * blend_time_s(speed[0] * dirs[0] - v0, limits) / 2
            done = np.linalg.norm(moved - first_leg_from) < 1e-9
            first_leg_from = moved
            if done:
                break
        alphas = [_corner_scale(speed[j - 1] * dirs[j - 1], speed[j] * dirs[j], max_cut, limits)
                  for j in range(1, len(pts) - 1)]
        pieces, corner_piece, short = _timeline(dirs, lengths, speed, alphas, limits, v0)
        if not short:
            return BlendedPath(pts[0], pieces, limits, corner_piece, merged_yaws)
        for k, share in short.items():
            slowed[k] *= min(max(math.sqrt(max(share, 0.0)), SLOWER[0]), SLOWER[1])
        if speed.min() < MIN_SPEED_MPS:
            break
    raise ValueError("waypoints too close together for the limits (a leg cannot hold its blends)")


def _corner_scale(v_in: np.ndarray, v_out: np.ndarray, max_cut_m: float, limits: KinematicLimits) -> float:
    """The largest share of the legs' speeds (<= 1) at which the corner's blend cuts it by at most
    `max_cut_m` (bisection: the cut grows with the speeds)."""
    if corner_cut_m(v_out - v_in, limits) <= max_cut_m:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if corner_cut_m(mid * (v_out - v_in), limits) <= max_cut_m else (lo, mid)
    return lo


def _timeline(dirs, lengths, speed, alphas, limits: KinematicLimits, start_velocity_mps: np.ndarray):
    """Pieces start (the start velocity), [head, cruise, tail] per leg, rest, with each piece long
    enough for half of the blends at both its ends. Returns (pieces, the piece index each
    waypoint's time starts, legs too short at their speed: {leg: the share of the length it needs
    that it has})."""
    n_legs = len(lengths)
    scale_in = [1.0] + list(alphas)      # leg k starts at scale_in[k] * its speed
    scale_out = list(alphas) + [1.0]     # ... and ends at scale_out[k] * its speed
    velocities: list[np.ndarray] = [start_velocity_mps]
    legs_of: list[int] = [-1]
    for k in range(n_legs):
        v = speed[k] * dirs[k]
        velocities += [scale_in[k] * v, v, scale_out[k] * v]
        legs_of += [k, k, k]
    velocities.append(np.zeros(3))
    legs_of.append(-1)
    blends = [blend_time_s(velocities[i + 1] - velocities[i], limits) for i in range(len(velocities) - 1)]
    durations = [blends[0] / 2]          # the start velocity before: the first blend starts at t = 0
    short: dict[int, float] = {}
    for k in range(n_legs):
        head, cruise, tail = 1 + 3 * k, 2 + 3 * k, 3 + 3 * k
        d_head = (blends[head - 1] + blends[head]) / 2
        d_tail = (blends[tail - 1] + blends[tail]) / 2
        left = lengths[k] - speed[k] * (scale_in[k] * d_head + scale_out[k] * d_tail)
        d_cruise = left / speed[k]
        cruise_min = (blends[cruise - 1] + blends[cruise]) / 2
        if d_cruise < cruise_min - 1e-9:    # the share of the length the leg needs at this speed that it has
            short[k] = lengths[k] / (lengths[k] - speed[k] * (d_cruise - cruise_min))
        durations += [d_head, d_cruise, d_tail]
    durations.append(blends[-1] / 2)
    pieces = [Piece(v, d) for v, d in zip(velocities, durations)]
    # waypoint k is where the unblended timeline is at a leg boundary: leg k's head starts there
    corner_piece = [1 + 3 * k for k in range(n_legs)] + [len(pieces) - 1]
    return pieces, corner_piece, short
