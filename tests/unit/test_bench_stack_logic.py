"""`aero bench stack`'s verdict rule and table (tools/bench/stack.py), on figures given here."""
from __future__ import annotations

import numpy as np

from aeroperception.tools.bench.flight import HotPath
from aeroperception.tools.bench.stack import StackReport, idle_pct, rated_rates


def report(idle: float = 40.0, state_hz: float = 50.0, lat_ms: float = 2.0, gap_ms: float = 20.0,
           sim_cpu: float = 60.0) -> StackReport:
    rows = [dict(process="sim", cpu_mean_pct=sim_cpu, rss_end_mb=900.0, diag_cpu_pct="40.0", budget_pct="-",
                 level="OK"),
            dict(process="lidar", cpu_mean_pct=20.0, rss_end_mb=200.0, diag_cpu_pct="20.0", budget_pct="25",
                 level="OK")]
    rates = [("camera (left+right)", None, 20.0), ("state/vehicle", state_hz, 50.0), ("setpoints", 49.0, 50.0)]
    hot = HotPath(lat=np.full(100, lat_ms), stages={}, gaps=np.full(100, gap_ms), period_error=("500", 0.1, 0.5),
                  sched="test")
    return StackReport(rows, rates, hot, idle, 30.0, 2)


def test_big_enough_when_every_goal_holds_and_a_sensor_that_is_off_is_no_shortfall():
    r = report()
    assert r.problems() == []
    assert r.format().splitlines()[-1].startswith("verdict: big enough")


def test_each_shortfall_is_named():
    r = report(idle=10.0, state_hz=30.0, lat_ms=8.0, gap_ms=40.0, sim_cpu=60.0)
    p = r.problems()
    assert p == ["state/vehicle 30.0 of 50 Hz", "idle 10 % < 25 %", "hot path p99 8.0 ms >= 5 ms",
                 "setpoint gap p99 40.0 ms >= 25 ms"], p
    verdict = r.format().splitlines()[-1]
    # 90 % busy of 200 % = 180 %, the stack's processes 80 %: 100 % spent elsewhere.
    assert verdict.startswith("verdict: NOT big enough: state/vehicle 30.0 of 50 Hz") and \
        "other programs used 100 % of a core" in verdict, verdict


def test_rates_are_the_producers_contracts_and_idle_is_from_proc_stat_deltas():
    rated = rated_rates()
    assert rated["sensors/camera/left/image"] == 20.0 and rated["perception/costmap"] == 10.0
    assert rated["state/vehicle"] == 50.0 and rated["fmu/in/trajectory_setpoint"] == 50.0
    assert idle_pct((100.0, 1000.0), (130.0, 1100.0)) == 30.0


def test_the_bench_s_own_cpu_is_given_back_to_idle_and_not_counted_as_other_programs():
    r = report(idle=20.0)
    r.bench_pct = 10.0                       # this bench's tap, counters and sampler: 10 % of one core
    assert r.stack_idle_pct() == 25.0        # 20 % idle + 10 % of one core over 2 cores
    assert r.problems() == []
    assert r.others_pct() == 70.0            # 160 % busy - the stack's 80 % - the bench's 10 %: other programs
    assert "machine idle 20.0 % (25.0 % without this bench's own 10 % of a core), other programs 70 %" in r.format()
