"""Rolling costmap (Nav2 costmap_2d semantics, requirement LID-3): marking, clearing, inflation, rolling;
and the runtime's newest-wins worker the lidar service processes scans with."""
import math
import threading
import time

import numpy as np
import pytest

from aeroperception.services.lidar.costmap import FREE, INSCRIBED, LETHAL, UNKNOWN, CostmapConfig, RollingCostmap
from aeroperception.services.lidar import contract
from aeroperception.services.runtime import LatestWorker
from aeroperception.services.runtime.config import build


def ring(radius_m, n=2000, center=(0.0, 0.0)):
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.column_stack([center[0] + radius_m * np.cos(a), center[1] + radius_m * np.sin(a)])


def wall(x_m, y0=-2.0, y1=2.0, n=400):
    return np.column_stack([np.full(n, x_m), np.linspace(y0, y1, n)])


def cell_value(cm, grid, x, y):
    c, r = cm.world_to_cell(np.array([[x, y]]))[0]
    return int(grid[r, c])


def scan(cm, obstacles, ground):
    cm.update((0.0, 0.0), obstacles, np.vstack([obstacles, ground]), ground)


def test_wall_is_lethal_free_space_in_front_unknown_behind():
    cm = RollingCostmap(build(CostmapConfig, contract.PARAMS))
    cm.recenter(0, 0)
    ground = ring(8.0, 4000)
    scan(cm, wall(5.0), ground[ground[:, 0] < 4.9])     # the wall hides the ground behind it
    g = cm.grid
    assert cell_value(cm, g, 5.0, 0.0) == LETHAL
    assert cell_value(cm, g, 2.5, 0.0) == FREE and cell_value(cm, g, -6.0, 0.0) == FREE
    assert cell_value(cm, g, 7.0, 0.0) == UNKNOWN                   # behind the wall: never seen


def test_inflation_follows_nav2_decay():
    cfg = build(CostmapConfig, contract.PARAMS, inscribed_radius_m=0.4, inflation_radius_m=1.5, cost_scaling_factor=3.0)
    cm = RollingCostmap(cfg)
    cm.recenter(0, 0)
    scan(cm, wall(5.0), ring(9.0, 4000))
    g = cm.inflated()
    assert cell_value(cm, g, 5.0, 0.0) == LETHAL
    assert cell_value(cm, g, 4.7, 0.0) == INSCRIBED                  # 0.3 m from the wall
    for d in (0.6, 1.0, 1.4):
        want = math.floor(98 * math.exp(-3.0 * (d - 0.4)))
        # The wall's cells are centred at x = 5.05 (0.1 m grid): query the cell d metres in front.
        assert abs(cell_value(cm, g, 5.05 - d, 0.0) - want) <= 1
    assert cell_value(cm, g, 3.0, 0.0) == FREE                       # beyond the inflation radius


def test_mark_threshold_ignores_a_lone_return():
    cm = RollingCostmap(build(CostmapConfig, contract.PARAMS, mark_threshold=2))
    cm.recenter(0, 0)
    scan(cm, np.array([[3.05, 3.05]]), ring(6.0))
    assert cell_value(cm, cm.grid, 3.05, 3.05) != LETHAL
    scan(cm, np.array([[3.05, 3.05], [3.06, 3.04]]), ring(6.0))
    assert cell_value(cm, cm.grid, 3.05, 3.05) == LETHAL


def test_obstacle_that_moved_away_is_cleared_by_later_rays():
    cm = RollingCostmap(build(CostmapConfig, contract.PARAMS))
    cm.recenter(0, 0)
    scan(cm, wall(4.0), ring(8.0, 4000))
    assert cell_value(cm, cm.grid, 4.0, 0.0) == LETHAL
    scan(cm, np.zeros((0, 2)), ring(8.0, 4000))                     # now the rays pass through
    assert cell_value(cm, cm.grid, 4.0, 0.0) == FREE


def test_obstacles_beyond_obstacle_range_are_not_marked():
    cm = RollingCostmap(build(CostmapConfig, contract.PARAMS, obstacle_range_m=5.0, size_m=30.0))
    cm.recenter(0, 0)
    scan(cm, wall(7.0), ring(12.0, 4000))
    assert cell_value(cm, cm.grid, 7.0, 0.0) != LETHAL


def test_rolling_window_keeps_what_it_saw():
    cm = RollingCostmap(build(CostmapConfig, contract.PARAMS))
    cm.recenter(0, 0)
    scan(cm, wall(5.0), ring(8.0, 4000))
    cm.recenter(3.0, 1.0)
    assert cell_value(cm, cm.grid, 5.0, 0.0) == LETHAL
    ox, oy = cm.origin_m
    assert ox == pytest.approx(3.0 - 10.0, abs=0.11) and oy == pytest.approx(1.0 - 10.0, abs=0.11)
    cm.recenter(500.0, 0.0)                                         # jumped out of the window
    assert (cm.grid == UNKNOWN).all()


def test_latest_worker_drops_older_inputs_never_queues():
    seen, gate = [], threading.Event()

    def slow(item):
        gate.wait(2.0)
        seen.append(item)

    w = LatestWorker(slow, "test")
    try:
        w.offer(0)
        time.sleep(0.05)                                            # 0 is being processed
        for i in range(1, 50):
            w.offer(i)                                              # 1..48 replaced in turn
        gate.set()
        deadline = time.monotonic() + 2.0
        while len(seen) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert seen == [0, 49] and w.dropped == 48
    finally:
        w.stop()


def test_latest_worker_survives_a_failing_input():
    errors, done = [], []
    w = LatestWorker(lambda x: done.append(1 / x), "test", on_error=errors.append)
    try:
        w.offer(0)
        deadline = time.monotonic() + 2.0
        while not errors and time.monotonic() < deadline:
            time.sleep(0.01)
        w.offer(2)
        while not done and time.monotonic() < deadline:
            time.sleep(0.01)
        assert isinstance(errors[0], ZeroDivisionError) and done == [0.5]
    finally:
        w.stop()
