"""Obstacle-aware velocity over a costmap: around walls, never into blocked
cells, stop when boxed in, refuse goals inside obstacles; unchanged in free space."""
import math

import numpy as np
import pytest

from aeroperception.services.planner import contract
from aeroperception.services.planner.avoidance import AvoidanceConfig, LocalPlanner
from aeroperception.services.runtime.config import build


def costmap(walls=(), size=200, res=0.1):
    """A 20 x 20 m grid centred on (0, 0): each wall (x0, y0, x1, y1) lethal, inflated like the
    lidar service (inscribed 0.4 m, decay to 1.5 m)."""
    import cv2

    g = np.zeros((size, size), np.int8)
    o = -size * res / 2
    for x0, y0, x1, y1 in walls:
        c0, r0 = int((x0 - o) / res), int((y0 - o) / res)
        c1, r1 = int((x1 - o) / res), int((y1 - o) / res)
        g[r0:r1 + 1, c0:c1 + 1] = 100
    lethal = g == 100
    d = cv2.distanceTransform((~lethal).astype(np.uint8), cv2.DIST_L2, 5) * res
    infl = np.where(d <= 0.4, 99, np.floor(98 * np.exp(-3 * (d - 0.4))))
    infl = np.where(d <= 1.5, infl, 0)
    g = np.where(lethal, 100, infl).astype(np.int8)
    return g, (o, o), res


def fly(lp, start, goal, speed=2.0, dt=0.1, steps=400):
    """Integrate the commanded horizontal velocity; returns the track."""
    p = np.array(start, float)
    track = [p.copy()]
    for _ in range(steps):
        err = np.array(goal, float) - p
        dist = float(np.hypot(*err))
        if dist < 0.3:
            break
        v = np.array([*(err / dist * min(speed, dist)), 0.0])
        if lp.needs_plan(p, goal):                         # the service replans on a worker
            lp.replan(p, goal)
        out = lp.adjust(np.array([*p, 3.0]), np.array([*goal, 3.0]), v, now_s=0.0)
        p = p + out.velocity_mps[:2] * dt
        track.append(p.copy())
    return np.array(track), out


def lethal_distance(track, walls):
    d = math.inf
    for x0, y0, x1, y1 in walls:
        dx = np.maximum(0, np.maximum(x0 - track[:, 0], track[:, 0] - x1))
        dy = np.maximum(0, np.maximum(y0 - track[:, 1], track[:, 1] - y1))
        d = min(d, float(np.min(np.hypot(dx, dy))))
    return d


def planner(walls=(), at=(0.0, 0.0), goal=None):
    lp = LocalPlanner(build(AvoidanceConfig, contract.PARAMS))
    lp.set_costmap(*costmap(walls), stamp_s=0.0)
    if goal is not None and lp.needs_plan(np.array(at), np.array(goal)):
        lp.replan(np.array(at), np.array(goal))
    return lp


def test_free_space_leaves_the_velocity_alone():
    lp = planner()
    out = lp.adjust(np.array([0, 0, 3.0]), np.array([8, 0, 3.0]), np.array([2.0, 0, 0.5]), 0.0)
    assert out.state == "clear" and out.velocity_mps == pytest.approx([2.0, 0, 0.5], abs=1e-6)


def test_goes_around_a_wall_across_the_straight_line_and_keeps_clear():
    walls = [(3.0, -3.0, 3.4, 3.0)]                        # 6 m wall across the way at x = 3
    track, out = fly(planner(walls), (-4, 0), (8, 0))
    assert np.hypot(*(track[-1] - (8, 0))) < 0.3, "goal not reached"
    assert lethal_distance(track, walls) > 0.4             # never into the inscribed radius


def test_goal_inside_an_obstacle_is_unreachable_and_holds():
    lp = planner([(4.0, -1.0, 6.0, 1.0)], goal=(5, 0))
    out = lp.adjust(np.array([0, 0, 3.0]), np.array([5, 0, 3.0]), np.array([2.0, 0, 0]), 0.0)
    assert out.state == "unreachable" and "inside an obstacle" in out.reason
    assert out.velocity_mps[:2] == pytest.approx([0, 0])


def test_an_old_goals_verdict_never_stands_for_a_new_goal():
    """A new goal behind the same building is "planning" until its own replan lands: an old
    goal's "unreachable" once stood for it (and a test waiting for the new verdict took it)."""
    lp = planner([(4.0, -1.0, 6.0, 1.0)], goal=(5, 0))
    new = np.array([5.0, 0.6, 3.0])                            # inside too, but another goal
    out = lp.adjust(np.array([0, 0, 3.0]), new, np.array([2.0, 0, 0]), 0.0)
    assert out.state == "planning" and out.velocity_mps[:2] == pytest.approx([0, 0])
    lp.replan(np.array([0.0, 0.0]), new[:2])
    out = lp.adjust(np.array([0, 0, 3.0]), new, np.array([2.0, 0, 0]), 0.0)
    assert out.state == "unreachable" and "(5.0, 0.6)" in out.reason


def test_boxed_in_holds_with_the_reason():
    walls = [(-2, -2, 2, -1.8), (-2, 1.8, 2, 2), (-2, -2, -1.8, 2), (1.8, -2, 2, 2)]
    lp = planner(walls, goal=(8, 0))
    out = lp.adjust(np.array([0, 0, 3.0]), np.array([8, 0, 3.0]), np.array([2.0, 0, 0]), 0.0)
    assert out.state == "blocked" and "boxed in" in out.reason and out.velocity_mps[:2] == pytest.approx([0, 0])


def test_a_way_cut_only_by_a_shadow_goes_to_look_and_then_reaches_the_goal():
    """The obstacle mission's last leg: past a parked car, a person 1.35 m beside it
    closes the gap, and the person's LiDAR shadow (a strip of never-seen cells) runs from behind
    them to the window's edge, cutting the way round them off from the goal. That was "boxed in"
    (the vehicle held for minutes where it stood, seeing the same shadow). Now the planner flies
    the seen way to where the goal is nearest, the new viewpoint sees into the shadow, and the
    goal is reached, never nearer the obstacles than the clearance zone allows."""
    car, person, wall = (1.5, -3.4, 6.0, -1.6), (5.5, -0.25, 6.0, 0.25), (-10.0, -6.5, 10.0, -6.3)
    walls = [car, person, wall]
    goal = (8.75, -2.5)
    grid, origin, res = costmap(walls)
    o = origin[0]
    rows = slice(round((-0.2 - o) / res), round((0.2 - o) / res))   # y -0.2..0.2: two planning cells
    grid[rows, round((7.6 - o) / res):] = -1                   # beyond the person's inflation
    lp = LocalPlanner(build(AvoidanceConfig, contract.PARAMS))
    lp.set_costmap(grid, origin, res, stamp_s=0.0)
    p = np.array([-3.0, -0.5])
    track, states = [p.copy()], set()
    for _ in range(600):
        if p[0] > 7.6 and p[1] > 0.1:                            # past the person: the shadow is seen
            lp.set_costmap(*costmap(walls), stamp_s=0.0)
        if np.hypot(*(p - goal)) < 0.3:
            break
        if lp.needs_plan(p, goal):
            lp.replan(p, goal)
        err = np.array(goal) - p
        v = np.array([*(err / np.hypot(*err) * min(2.0, np.hypot(*err))), 0.0])
        out = lp.adjust(np.array([*p, 1.5]), np.array([*goal, 1.5]), v, now_s=0.0)
        states.add(out.state)
        p = p + out.velocity_mps[:2] * 0.1
        track.append(p.copy())
    track = np.array(track)
    assert "blocked" not in states, states
    assert np.hypot(*(track[-1] - goal)) < 0.3, f"stopped at {track[-1].round(2)}: {out.state} {out.reason}"
    assert lethal_distance(track, walls) > 1.0                 # the clearance zone, less the slack cells


def test_a_goal_walled_off_on_the_costmap_is_boxed_in_although_unknown_cells_are_about():
    """Unknown cells elsewhere do not make a known wall passable: still boxed in."""
    walls = [(4.0, -10.0, 4.4, 10.0)]                           # across the whole window
    g, origin, res = costmap(walls)
    g[:20, :20] = -1                                           # an unseen corner far from the wall
    lp = LocalPlanner(build(AvoidanceConfig, contract.PARAMS))
    lp.set_costmap(g, origin, res, stamp_s=0.0)
    lp.replan(np.array([0.0, 0.0]), np.array([8.0, 0.0]))
    out = lp.adjust(np.array([0, 0, 3.0]), np.array([8, 0, 3.0]), np.array([2.0, 0, 0]), 0.0)
    assert out.state == "blocked" and "boxed in" in out.reason


def test_never_commands_into_a_blocked_cell_even_when_told_to():
    lp = planner([(1.0, -5, 1.2, 5)], goal=(9, 0))        # a long wall 1 m ahead
    out = lp.adjust(np.array([0, 0, 3.0]), np.array([9, 0, 3.0]), np.array([2.0, 0, 0]), 0.0)
    assert out.velocity_mps[0] <= 1e-6 or out.state in ("avoiding", "blocked")
    p = np.array([0.0, 0.0])
    for _ in range(100):
        if lp.needs_plan(p, (9, 0)):
            lp.replan(p, (9, 0))
        out = lp.adjust(np.array([*p, 3.0]), np.array([9, 0, 3.0]), np.array([2.0, 0, 0]), 0.0)
        p = p + out.velocity_mps[:2] * 0.05
        assert p[0] < 1.0 - 0.4 + 1e-6 or abs(p[1]) > 5.4


def test_stale_costmap_holds_instead_of_flying_blind():
    """The lidar service died mid-flight: the last costmap ages out and the vehicle holds
    (horizontally; vertical motion is the waypoint planner's) until a fresh one arrives."""
    lp = planner([(3.0, -3.0, 3.4, 3.0)], goal=(8, 0))
    out = lp.adjust(np.array([0, 0, 3.0]), np.array([8, 0, 3.0]), np.array([2.0, 0, 0.5]), now_s=5.0)
    assert out.state == "stale_costmap" and "5.0 s old" in out.reason
    assert out.velocity_mps == pytest.approx([0, 0, 0.5])
    lp.set_costmap(*costmap([(3.0, -3.0, 3.4, 3.0)]), stamp_s=5.0)          # fresh again: flies on
    out = lp.adjust(np.array([-4, 0, 3.0]), np.array([-8, 0, 3.0]), np.array([-2.0, 0, 0]), now_s=5.1)
    assert out.state == "clear" and out.velocity_mps[0] == pytest.approx(-2.0)


def test_no_costmap_ever_leaves_the_velocity_alone():
    lp = LocalPlanner(build(AvoidanceConfig, contract.PARAMS))
    out = lp.adjust(np.array([0, 0, 3.0]), np.array([8, 0, 3.0]), np.array([2.0, 0, 0]), now_s=5.0)
    assert out.state == "no_costmap" and out.velocity_mps == pytest.approx([2.0, 0, 0])


def test_goal_nearer_than_the_clearance_is_reached_without_getting_closer_than_it():
    """A waypoint 1.2 m from a parked car (clearance 1.5 m): reached, from around the car, and
    the way in never gets nearer to it than the goal itself (less a planning cell)."""
    walls = [(2.0, -1.0, 6.0, 1.0)]                         # a car across the straight way
    goal = (7.2, 0.0)                                      # 1.2 m behind it
    track, out = fly(planner(walls, at=(-4, 0), goal=goal), (-4, 0), goal)
    assert np.hypot(*(track[-1] - goal)) < 0.3, f"goal not reached: {out.state} {out.reason}"
    assert lethal_distance(track, walls) >= 1.2 - 0.2 - 0.05
    far = track[np.hypot(track[:, 0] - goal[0], track[:, 1] - goal[1]) > 1.5]
    assert lethal_distance(far, walls) >= 1.5 - 0.2        # full clearance away from the goal


def test_goal_nearer_than_goal_clearance_is_unreachable_with_the_distance():
    lp = planner([(2.0, -1.0, 6.0, 1.0)], at=(-4, 0), goal=(6.7, 0.0))   # 0.7 m from the car
    out = lp.adjust(np.array([-4, 0, 3.0]), np.array([6.7, 0, 3.0]), np.array([2.0, 0, 0]), 0.0)
    assert out.state == "unreachable" and out.velocity_mps[:2] == pytest.approx([0, 0])
    assert "m from an obstacle" in out.reason and "closer than 1.0 m" in out.reason
