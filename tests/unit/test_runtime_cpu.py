"""CPU and memory accounting in every service's diagnostics (services/runtime/cpu.py), without Zenoh."""
from __future__ import annotations

import time

import pytest

from aeroperception.schemas import DiagnosticStatus
from aeroperception.services.runtime import Node, Service
from aeroperception.services.runtime.cpu import SUSTAIN_S, CpuMeter, own_usage
from aeroperception.services.runtime.service import cpu_budget


class FakeUsage:
    """A process whose CPU use per second the test sets; (wall, cpu_s, rss) like own_usage."""

    def __init__(self):
        self.wall, self.cpu, self.rss = 100.0, 5.0, 50_000_000

    def __call__(self):
        return self.wall, self.cpu, self.rss

    def run(self, seconds: float, pct: float) -> None:
        self.wall += seconds
        self.cpu += seconds * pct / 100.0


def test_cpu_pct_is_the_last_interval_and_rss_is_reported():
    u = FakeUsage()
    m = CpuMeter(usage=u)
    u.run(1.0, 40.0)
    r = m.report()
    assert r.cpu_pct == pytest.approx(40.0) and r.rss_mb == pytest.approx(50.0)
    u.run(0.5, 150.0)   # two busy threads: more than one core
    assert m.report().cpu_pct == pytest.approx(150.0)
    assert m.report().cpu_pct == 0.0   # no time passed: nothing to divide by, not a crash


def test_budget_warns_only_when_the_sustained_mean_is_over_it():
    u = FakeUsage()
    m = CpuMeter(budget_pct=25.0, usage=u)
    u.run(1.0, 100.0)   # a busy start-up second
    r = m.report()
    assert r.sustained_pct is None and not r.over_budget and r.problem() == ""
    for _ in range(int(SUSTAIN_S) - 1):
        u.run(1.0, 10.0)
        r = m.report()
    # 10 s: one second at 100 % and nine at 10 % = 19 % mean, under 25 %.
    assert r.sustained_pct == pytest.approx(19.0) and not r.over_budget
    for _ in range(int(SUSTAIN_S)):
        u.run(1.0, 30.0)
        r = m.report()
    assert r.cpu_pct == pytest.approx(30.0) and r.sustained_pct == pytest.approx(30.0) and r.over_budget
    assert "30 % of a core" in r.problem() and "budget 25 %" in r.problem()
    assert r.values() == {"cpu_pct": "30.0", f"cpu_pct_{SUSTAIN_S:g}s": "30.0", "rss_mb": "50.0",
                          "cpu_budget_pct": "25"}
    for _ in range(3):   # back under budget: the window forgets the old load within SUSTAIN_S
        u.run(SUSTAIN_S / 2, 5.0)
        r = m.report()
    assert r.sustained_pct == pytest.approx(5.0) and not r.over_budget


def test_a_negative_cpu_step_and_a_bad_budget():
    u = FakeUsage()
    m = CpuMeter(usage=u)
    u.wall += 1.0
    u.cpu -= 1.0   # a clock that went backwards is never a negative load
    assert m.report().cpu_pct == 0.0
    with pytest.raises(ValueError, match="budget"):
        CpuMeter(budget_pct=0.0)


def test_own_usage_sees_this_process_burn_cpu():
    t0 = time.monotonic()
    m = CpuMeter(usage=own_usage)
    c0 = time.process_time()
    while time.process_time() - c0 < 0.3 and time.monotonic() - t0 < 5.0:   # 0.3 s of CPU, however shared
        pass
    r = m.report()
    wall = time.monotonic() - t0
    assert r.cpu_pct * wall / 100.0 == pytest.approx(0.3, abs=0.05), (r, wall)   # clock ticks are 10 ms
    assert r.rss_mb is not None and 10.0 < r.rss_mb < 10_000.0


def test_node_diagnostics_carry_cpu_and_warn_over_budget():
    node = Node("cpu_test", cpu_budget_pct=25.0, log_level="error")
    u = FakeUsage()
    node.cpu = CpuMeter(25.0, usage=u)
    u.run(1.0, 20.0)
    d = node.diagnostics()
    assert d.level == DiagnosticStatus.OK and d.values["cpu_pct"] == "20.0" and d.values["cpu_budget_pct"] == "25"
    for _ in range(int(SUSTAIN_S) + 1):
        u.run(1.0, 60.0)
        d = node.diagnostics()
    assert d.level == DiagnosticStatus.WARN and "budget 25 %" in d.message, d.message
    assert d.values[f"cpu_pct_{SUSTAIN_S:g}s"] == "60.0"


def test_node_without_budget_reports_cpu_and_never_warns_for_it():
    node = Node("cpu_test", log_level="error")
    d = node.diagnostics()
    assert d.level == DiagnosticStatus.OK and "cpu_pct" in d.values and "rss_mb" in d.values
    assert "cpu_budget_pct" not in d.values


def test_budget_from_the_class_else_from_the_services_contract():
    class Fixed(Service):
        NAME = "fixed"
        CPU_BUDGET_PCT = 12.5

    class NoContract(Service):
        NAME = "none"

    from aeroperception.services.lidar import contract as lidar_contract
    from aeroperception.services.lidar.main import LidarService
    from aeroperception.services.planner.main import PlannerService

    assert cpu_budget(Fixed) == 12.5
    assert cpu_budget(NoContract) is None   # tests.unit has no contract module
    assert cpu_budget(LidarService) == lidar_contract.CPU_BUDGET_PCT == 25.0
    assert cpu_budget(PlannerService) is None   # a contract without a budget
