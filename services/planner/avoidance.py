"""Obstacle-aware velocity (requirement PLAN-2) over the lidar service's costmap.

The waypoint planner says where to go; this decides how to get there horizontally without
touching anything the costmap calls inscribed or lethal:
- a path: Dijkstra from the vehicle's cell over a coarsened copy of the costmap (cells >= 99
  blocked, inflation costs make it keep its distance), to the reachable cell that minimises
  path cost + straight distance on to the goal — so a goal outside the window or behind a
  building is approached around it, and a goal inside an obstacle is reported unreachable.
  Never-seen cells are not a way, but they do not box the vehicle in either: a goal cut off
  only by them (a person's LiDAR shadow across the way round them) is approached as far as the
  seen cells go, where the new viewpoint sees into the shadow;
- a goal nearer to an obstacle than the clearance (a waypoint 1.3 m from a parked car) is still
  a goal: near it the clearance is relaxed to the goal's own distance from the obstacle, never
  below `goal_clearance_m` (nearer than that: unreachable) — judging it by the full clearance
  held the vehicle short of waypoints whenever LiDAR noise put a mark a few cm closer;
- a carrot `lookahead_m` along that path gives the direction; the speed is the waypoint
  planner's, scaled down as the nearest obstacle ahead comes within `slow_distance_m`;
- a last check: a velocity whose next `check_horizon_s` crosses a blocked cell becomes zero.
Boxed in (no path, not even through never-seen cells) -> hold, with the reason. A costmap that
stops coming (the lidar service died) -> hold until it is fresh again: flying on would be flying blind into what was just seen.
Never had one (a stack without LiDAR) -> the velocity is left alone (`no_costmap`). Vertical motion is left to the waypoint planner:
the costmap is 2D at the flight altitude.
Plain numpy + scipy.sparse.csgraph (Dijkstra in C); replanned per costmap, not per setpoint.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aeroperception.services.lib.costmap import BLOCKED
from aeroperception.services.runtime.config import param

_EPS_M = 1e-3        # float32 distances: 1.0 m is sometimes 0.99999994
GO_WEIGHT = 10.0      # goal outside the window: score = path cost + GO_WEIGHT * straight distance left


@dataclass(frozen=True)
class AvoidanceConfig:
    """The planner's avoid_* parameters (defaults, units and ranges: contract.py) and fixed tuning."""

    clearance_m: float = param("avoid_clearance_m")            # plan this far from lethal cells (tracking error included)
    goal_clearance_m: float = param("avoid_goal_clearance_m")  # a goal nearer than this to a lethal cell is unreachable
    lookahead_m: float = param("avoid_lookahead_m")
    slow_distance_m: float = param("avoid_slow_distance_m")    # full speed while the clearance zone ahead is farther
    stop_distance_m: float = param("avoid_stop_distance_m")    # zero speed this close to the clearance zone ahead
    costmap_timeout_s: float = param("costmap_timeout_s")
    cell_m: float = 0.2                 # planning resolution (costmap cells are pooled to this)
    cost_weight: float = 4.0            # path cost per metre = 1 + cost_weight * cost / 98
    check_horizon_s: float = 0.3
    sight_m: float = 9.0                # straight to the goal only if free this far (~half the window)


@dataclass
class Avoidance:
    velocity_mps: np.ndarray            # horizontal part replaced; z kept
    state: str                          # "clear" | "avoiding" | "planning" | "blocked" | "unreachable" |
                                        # "no_costmap" (never had one) | "stale_costmap" (holding)
    reason: str = ""
    path_xy: np.ndarray | None = None


class CostmapView:
    """A costmap pooled to the planning resolution (max of each block: conservative), with
    `blocked` = closer than the clearance to a lethal cell (the planner's own margin, not the
    costmap's inscribed radius: the vehicle must keep its distance, not just not touch)."""

    def __init__(self, data: np.ndarray, origin_xy: tuple[float, float], resolution_m: float,
                 cell_m: float, clearance_m: float, stamp_s: float):
        import cv2

        k = max(1, int(round(cell_m / resolution_m)))
        h, w = (data.shape[0] // k) * k, (data.shape[1] // k) * k
        pooled = data[:h, :w].astype(np.int16).reshape(h // k, k, w // k, k).max(axis=(1, 3))
        # Unknown (never seen: occluded, e.g. inside a building, or out of range) is not a way.
        self.unknown = pooled < 0
        self.cost = np.maximum(pooled, 0)
        self.origin = np.asarray(origin_xy, dtype=float)
        self.res = resolution_m * k
        self.stamp_s = stamp_s
        lethal = self.cost >= 100
        # Distance (m) from each cell to the nearest lethal one. Planning keeps `clearance_m`;
        # looking ahead along straight lines tolerates one cell less, and the last-resort stop
        # two cells less, so a line grazing the corner of a planning cell does not freeze the
        # vehicle while it still never gets near an obstacle.
        self.dist = (cv2.distanceTransform((~lethal).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                     * self.res if lethal.any() else np.full(lethal.shape, np.inf, np.float32))
        self.blocked = self.dist < clearance_m
        self.clearance_m = clearance_m
        self.relief: tuple[np.ndarray, float, float] | None = None   # (goal xy, clearance there, radius)
        self._goal_key: tuple | None = None

    def set_goal(self, goal_xy: np.ndarray, goal_clearance_m: float) -> None:
        """Relax the clearance around a goal that is nearer than it to an obstacle (but not
        nearer than goal_clearance_m): within `clearance_m` of the goal, cells as far from
        obstacles as the goal itself (less a cell) are free, so the way in exists and never
        gets closer than the goal does. Cached per goal; replaces arrays, never mutates them
        (the setpoint thread and the replan worker share the view)."""
        g = np.asarray(goal_xy, float)[:2]
        key = (round(float(g[0]), 2), round(float(g[1]), 2), goal_clearance_m)
        if key == self._goal_key:
            return
        c = self.cell(g)
        relief = None
        if self.inside(c):
            dg = float(self.dist[c[1], c[0]]) + _EPS_M
            if goal_clearance_m <= dg < self.clearance_m:
                relief = (g, max(goal_clearance_m, dg - self.res) - _EPS_M, self.clearance_m)
        blocked = self.dist < clearance_grid(self, relief)
        self.relief, self.blocked, self._goal_key = relief, blocked, key

    def threshold(self, xy: np.ndarray, relief=False) -> np.ndarray:
        """Clearance required at each point (relaxed near a goal inside the clearance)."""
        relief = self.relief if relief is False else relief
        thr = np.full(len(xy), self.clearance_m)
        if relief is not None:
            g, floor, radius = relief
            thr[np.hypot(xy[:, 0] - g[0], xy[:, 1] - g[1]) <= radius] = floor
        return thr

    def cell(self, xy: np.ndarray) -> np.ndarray:
        return np.floor((np.asarray(xy, float) - self.origin) / self.res).astype(np.int64)

    def centre(self, rc: np.ndarray) -> np.ndarray:
        return self.origin + (np.asarray(rc)[..., ::-1] + 0.5) * self.res     # (row, col) -> (x, y)

    def inside(self, cxy: np.ndarray) -> bool:
        h, w = self.cost.shape
        return 0 <= cxy[0] < w and 0 <= cxy[1] < h

    def distance_along(self, xy: np.ndarray) -> np.ndarray:
        """Distance to the nearest lethal cell at each point (inf outside the grid)."""
        c = self.cell(np.atleast_2d(xy))
        h, w = self.cost.shape
        ok = (c[:, 0] >= 0) & (c[:, 0] < w) & (c[:, 1] >= 0) & (c[:, 1] < h)
        out = np.full(len(c), np.inf)
        out[ok] = self.dist[c[ok, 1], c[ok, 0]]
        return out

    def nearest_lethal(self, xy: np.ndarray) -> str:
        """Where the lethal cell nearest to xy is, for messages."""
        cells = np.argwhere(self.cost >= 100)
        if not len(cells):
            return "none"
        c = self.centre(cells)
        k = int(np.argmin(np.hypot(c[:, 0] - xy[0], c[:, 1] - xy[1])))
        return f"at ({c[k, 0]:.1f}, {c[k, 1]:.1f})"

    def blocked_at(self, xy: np.ndarray, slack_cells: int = 0) -> bool:
        return bool(self.blocked_along(xy, slack_cells)[0])

    def blocked_along(self, xy: np.ndarray, slack_cells: int = 0) -> np.ndarray:
        xy = np.atleast_2d(np.asarray(xy, float))
        return self.distance_along(xy) < self.threshold(xy) - slack_cells * self.res


def unseen_way(passable: np.ndarray, start_xy: np.ndarray, goal_xy: np.ndarray) -> bool:
    """Whether the goal cell connects to the start cell through `passable` cells (4-connected)."""
    from scipy.ndimage import label

    labels, _ = label(passable)
    here = labels[start_xy[1], start_xy[0]]
    return bool(here) and labels[goal_xy[1], goal_xy[0]] == here


def clearance_grid(view: CostmapView, relief) -> np.ndarray | float:
    """Required clearance per planning cell (a scalar when nothing is relaxed)."""
    if relief is None:
        return view.clearance_m
    h, w = view.dist.shape
    rc = np.stack(np.meshgrid(np.arange(h), np.arange(w), indexing="ij"), axis=-1).reshape(-1, 2)
    return view.threshold(view.centre(rc), relief).reshape(h, w)


class LocalPlanner:
    def __init__(self, cfg: AvoidanceConfig):
        self.cfg = cfg
        self.view: CostmapView | None = None
        self._goal: np.ndarray | None = None
        self._plan_key: tuple | None = None
        self._path: np.ndarray | None = None
        self._path_goal: np.ndarray | None = None
        self._state = ("clear", "")

    def set_costmap(self, data: np.ndarray, origin_xy, resolution_m: float, stamp_s: float) -> None:
        view = CostmapView(data, origin_xy, resolution_m, self.cfg.cell_m, self.cfg.clearance_m, stamp_s)
        if self._goal is not None:          # ready for the current goal before anyone sees it
            view.set_goal(self._goal, self.cfg.goal_clearance_m)
        self.view = view

    def _view_for(self, goal_m) -> CostmapView | None:
        self._goal = np.asarray(goal_m, float)[:2].copy()
        view = self.view
        if view is not None:
            view.set_goal(self._goal, self.cfg.goal_clearance_m)
        return view

    def needs_plan(self, position_m: np.ndarray, goal_m: np.ndarray) -> bool:
        """Whether a (slow, ~10-30 ms) replan is worth it: only when the straight way to the goal
        is not free, and the vehicle, the goal or the costmap moved on since the last plan."""
        view = self._view_for(goal_m)
        if view is None:
            return False
        p, g = np.asarray(position_m[:2], float), np.asarray(goal_m[:2], float)
        to_goal = g - p
        dist = float(np.hypot(*to_goal))
        if dist < 1e-3 or self._free_line(p, to_goal / dist, min(dist, self.cfg.sight_m)):
            return False
        return (tuple(view.cell(p)), tuple(np.round(g, 1)), view.stamp_s) != self._plan_key

    def replan(self, position_m: np.ndarray, goal_m: np.ndarray) -> None:
        """Plan on the current costmap (off the setpoint path: the service runs it on a worker)."""
        if self._view_for(goal_m) is None:
            return
        p, g = np.asarray(position_m[:2], float), np.asarray(goal_m[:2], float)
        self._plan_key = (tuple(self.view.cell(p)), tuple(np.round(g, 1)), self.view.stamp_s)
        self._path, self._state = self._plan(p, g)
        self._path_goal = g

    def path_blocked(self, points_xy: np.ndarray, now_s: float) -> bool:
        """Whether a stretch of trajectory comes nearer an obstacle than the clearance (a cell of
        slack, as for straight lines), or the costmap is stale (flying on would be flying blind).
        No costmap ever: not blocked (a stack without LiDAR flies its trajectory)."""
        view = self.view
        if view is None or not len(points_xy):
            return False
        if now_s - view.stamp_s > self.cfg.costmap_timeout_s:
            return True
        pts = np.asarray(points_xy, float)
        if view.blocked_at(pts[0], 1):         # inside a margin already: only going deeper counts
            d = view.distance_along(pts)
            return bool(np.any(d[1:] < d[0] - 1e-6))
        return bool(view.blocked_along(pts, 1).any())

    # ------------------------------------------------------------ per setpoint (cheap)

    def adjust(self, position_m: np.ndarray, goal_m: np.ndarray, velocity_mps: np.ndarray,
               now_s: float) -> Avoidance:
        """The velocity to command now: the straight one where the way is free, else along the
        latest plan, slowed near obstacles, never into a blocked cell. No planning here."""
        cfg, view = self.cfg, self._view_for(goal_m)
        v = np.asarray(velocity_mps, float).copy()
        if view is None:
            return Avoidance(v, "no_costmap", "no perception/costmap yet: flying without obstacle handling")
        age = now_s - view.stamp_s
        if age > cfg.costmap_timeout_s:
            v[:2] = 0.0
            return Avoidance(v, "stale_costmap", f"perception/costmap {age:.1f} s old: holding until it is "
                                                 f"fresh (obstacle_avoidance=false flies without it)")
        speed = float(np.hypot(v[0], v[1]))
        if speed < 1e-3:
            return Avoidance(v, "clear")
        p, g = np.asarray(position_m[:2], float), np.asarray(goal_m[:2], float)
        to_goal = g - p
        dist_goal = float(np.hypot(*to_goal))
        straight_dir = to_goal / max(1e-6, dist_goal)
        state, reason = "clear", ""
        if self._free_line(p, straight_dir, min(dist_goal, cfg.sight_m)):
            direction = straight_dir                  # line of sight: no lattice zig-zag
        elif self._path is None or self._path_goal is None or np.hypot(*(self._path_goal - g)) > 0.1:
            # The last verdict only if it is about this goal: a new goal is "planning" until its
            # replan lands (an old goal's "unreachable" once stood for a new goal's verdict).
            same_goal = self._path_goal is not None and np.hypot(*(self._path_goal - g)) <= 0.1
            state, reason = self._state if same_goal and self._path is None else (
                "planning", "planning a way around an obstacle")
            v[:2] = 0.0
            return Avoidance(v, state, reason)
        else:
            d = self._carrot(p) - p
            n = float(np.hypot(*d))
            direction = d / n if n > 1e-6 else straight_dir
            state = "avoiding"
        # Free distance ahead: to the clearance zone straight on, but at least to the carrot,
        # which is visible by construction (the path bends before the zone ahead of it).
        reach = self._clearance(p, direction)
        if state == "avoiding":
            reach = max(reach, n)
        scale = np.clip((reach - cfg.stop_distance_m) / (cfg.slow_distance_m - cfg.stop_distance_m), 0.0, 1.0)
        # A minimum creep keeps it moving along a visible way; only a wall right ahead stops it.
        v[:2] = direction * speed * max(scale, 0.15 if reach > 0.05 else 0.0)
        if self._crosses_blocked(p, v[:2]):
            v[:2] = 0.0
            return Avoidance(v, "blocked", "obstacle ahead within the check horizon", self._path)
        if state == "clear" and scale < 1.0:
            state = "avoiding"
        return Avoidance(v, state, reason, self._path)

    # ------------------------------------------------------------ planning

    def _plan(self, p: np.ndarray, g: np.ndarray) -> tuple[np.ndarray | None, tuple[str, str]]:
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import dijkstra

        view, cfg = self.view, self.cfg
        cost = view.cost
        h, w = cost.shape
        start = view.cell(p)
        if not view.inside(start):
            return None, ("blocked", "vehicle outside the costmap")
        gcell = view.cell(g)
        if view.inside(gcell) and cost[gcell[1], gcell[0]] >= BLOCKED:
            return None, ("unreachable", f"goal ({g[0]:.1f}, {g[1]:.1f}) is inside an obstacle")
        if view.inside(gcell) and view.dist[gcell[1], gcell[0]] + _EPS_M < cfg.goal_clearance_m:
            return None, ("unreachable", f"goal ({g[0]:.1f}, {g[1]:.1f}) is {view.dist[gcell[1], gcell[0]]:.2f} m "
                                         f"from an obstacle ({view.nearest_lethal(g)}), closer than "
                                         f"{cfg.goal_clearance_m:.1f} m")
        free = ~view.blocked & ~view.unknown
        # The vehicle may already be inside its clearance of something: let it leave (but never
        # through a lethal cell).
        sr, sc = start[1], start[0]
        r = max(1, int(math.ceil(cfg.clearance_m / view.res)))
        win = (slice(max(0, sr - r), sr + r + 1), slice(max(0, sc - r), sc + r + 1))
        free[win] |= cost[win] < BLOCKED
        # Inflation costs, plus a margin term so paths run in the middle of gaps instead of
        # hugging the clearance boundary (where any tracking error means slowing to a crawl).
        margin = np.clip((cfg.clearance_m + 1.0 - view.dist) / 1.0, 0.0, 1.0)
        step_cost = 1.0 + cfg.cost_weight * (np.clip(cost, 0, 98) / 98.0 + margin)
        idx = np.arange(h * w).reshape(h, w)
        rows, cols, wts = [], [], []
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = idx[max(0, -dr):h - max(0, dr), max(0, -dc):w - max(0, dc)]
            b = idx[max(0, dr):h - max(0, -dr) or None, max(0, dc):w - max(0, -dc) or None]
            fr = free.ravel()
            ok = fr[a.ravel()] & fr[b.ravel()]
            if dr and dc:                       # no diagonal squeeze between two blocked cells
                ok &= fr[a.ravel() + dr * w] & fr[a.ravel() + dc]
            length = math.hypot(dr, dc) * view.res
            c = 0.5 * (step_cost.ravel()[a.ravel()] + step_cost.ravel()[b.ravel()]) * length
            rows += [a.ravel()[ok], b.ravel()[ok]]
            cols += [b.ravel()[ok], a.ravel()[ok]]
            wts += [c[ok], c[ok]]
        graph = csr_matrix((np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(h * w, h * w))
        s = int(start[1] * w + start[0])
        dist, pred = dijkstra(graph, indices=s, return_predecessors=True)
        reach = np.isfinite(dist)
        if reach.sum() <= 1:
            return None, ("blocked", "boxed in: no free cell around the vehicle on the costmap")
        goal_idx = int(gcell[1] * w + gcell[0]) if view.inside(gcell) else None
        if goal_idx is not None and reach[goal_idx]:
            best = goal_idx                          # go there, however long the way
        elif goal_idx is not None and not unseen_way(free | (view.unknown & ~view.blocked), start, gcell):
            return None, ("blocked", "boxed in: no way to the goal on the costmap")
        else:
            # The goal is outside the window, not seen yet, or cut off only by cells never seen
            # (the shadow of a person or a pole, one viewpoint's strip of unknown across the way):
            # the reachable cell nearest to it (the shorter way on ties), then replan from there
            # as the window moves on and the new viewpoint sees what was hidden.
            centres = view.centre(np.stack(np.unravel_index(np.arange(h * w), (h, w)), axis=1))
            to_go = np.hypot(centres[:, 0] - g[0], centres[:, 1] - g[1])
            score = np.where(reach, dist + GO_WEIGHT * to_go, np.inf)
            best = int(np.argmin(score))
            if best == s and to_go[s] > 1.0:
                return None, ("blocked", "no way towards the goal on the costmap")
        path = [best]
        for _ in range(h * w):                                  # bounded walk back to the start
            if path[-1] == s:
                break
            path.append(int(pred[path[-1]]))
        cells = np.stack(np.unravel_index(np.array(path[::-1]), (h, w)), axis=1)
        return np.vstack([p, view.centre(cells)[1:]]) if len(cells) > 1 else np.vstack([p, g]), ("avoiding", "")

    def _clearance(self, p: np.ndarray, direction: np.ndarray) -> float:
        """Distance to the first blocked cell (the clearance zone) straight ahead (m)."""
        view, cfg = self.view, self.cfg
        ds = np.arange(view.res * 0.5, cfg.slow_distance_m + view.res, view.res * 0.5)
        if view.blocked_at(p, 1):
            return math.inf          # already inside: _crosses_blocked keeps it from going deeper
        hit = view.blocked_along(p + np.outer(ds, direction), 1)
        return float(ds[np.argmax(hit)]) if hit.any() else math.inf

    def _carrot(self, p: np.ndarray) -> np.ndarray:
        """The farthest point of the plan within lookahead_m that p sees without crossing a
        blocked cell (a fixed carrot would cut the inside of corners), else the next point."""
        path, cfg = self._path, self.cfg
        i = int(np.argmin(np.hypot(*(path - p).T)))
        best = path[min(i + 1, len(path) - 1)]
        for q in path[i + 1:]:
            d = q - p
            n = float(np.hypot(*d))
            if n > cfg.lookahead_m:
                break
            if n > 1e-6 and self._free_line(p, d / n, n):
                best = q
        return best

    def _free_line(self, p: np.ndarray, direction: np.ndarray, length_m: float) -> bool:
        """No blocked cell on the segment (from inside a clearance zone: none deeper in)."""
        view = self.view
        ds = np.arange(0.0, length_m + 1e-9, 0.5 * view.res)
        pts = p + np.outer(ds, direction)
        if not view.blocked_at(p, 1):
            return not view.blocked_along(pts, 1).any()
        d = view.distance_along(pts)            # inside the margin: only lines that do not go deeper
        return bool(np.all(d[1:] >= d[0] - 1e-6))

    def _crosses_blocked(self, p: np.ndarray, v_xy: np.ndarray) -> bool:
        """Whether moving at v for check_horizon_s enters a blocked cell (from outside one), or
        goes deeper towards a lethal cell (from inside a clearance zone)."""
        view = self.view
        n = max(2, int(np.hypot(*v_xy) * self.cfg.check_horizon_s / (0.5 * view.res)) + 1)
        pts = p + np.outer(np.linspace(0, self.cfg.check_horizon_s, n)[1:], v_xy)
        if view.blocked_at(p, 2):
            return bool(view.distance_along(pts).min() < view.distance_along(p)[0] - 1e-6)
        return bool(view.blocked_along(pts, 2).any())
