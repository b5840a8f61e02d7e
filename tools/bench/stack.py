"""`aero bench stack`: is this machine big enough for the stack? One command: `aero up --scenario
village` (profile and sensors as asked), the vehicle taken off and hovering, then N seconds measured:

- per process: CPU % of one core (mean over the window, from /proc; a service's child processes
  such as the sim's renderers counted with it) and RSS, beside what the service reports itself in
  diagnostics/<service> (its own process only, 10 s mean) and its CPU budget;
- achieved vs rated rate of the key topics (rated: the producer's contract; camera and LiDAR from
  the sim's frame counters, so the bench does not pull 40 MB/s of images through the router);
- the control hot path, exactly as `aero bench flight` measures it (same run);
- the machine's idle %, and a verdict against the stack's goals.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from aeroperception.schemas import DiagnosticStatus
from aeroperception.services.runtime.cpu import SUSTAIN_S
from aeroperception.services.runtime.service import SWITCH_INTERVAL_S

from .flight import HotPath, HoverRun
from .soak import Sampler, summarize
from aeroperception.tools.common import CliError
from aeroperception.tools.contracts import load_contracts

RATE_OK = 0.9           # achieved >= 90 % of rated counts as at rate
IDLE_GOAL_PCT = 25.0    # the machine keeps this much idle with the whole stack running
HOT_PATH_P99_MS = 5.0   # state -> setpoint on the wire
GAP_P99_MS = 25.0       # 50 Hz setpoints: a gap of more than 25 ms is a missed tick


@dataclass(frozen=True)
class Stream:
    """A key topic: its label, key, producing service and how it is counted."""

    label: str
    key: str
    producer: str
    sim_counter: str = ""     # counted from the sim's diagnostics (<name>_frames) instead of subscribing
    rated_like: str = ""      # rated at this other key's rate (VIO: one odometry per camera frame)


STREAMS = (
    Stream("camera (left+right)", "sensors/camera/left/image", "sim", sim_counter="camera"),
    Stream("LiDAR scans", "sensors/lidar/points", "sim", sim_counter="lidar"),
    Stream("costmap", "perception/costmap", "lidar"),
    Stream("VIO odometry", "state/visual_odometry", "vio", rated_like="sensors/camera/left/image"),
    Stream("detections", "perception/detections", "detector"),
    Stream("state/vehicle", "state/vehicle", "fmu"),
    Stream("setpoints", "fmu/in/trajectory_setpoint", "planner"),
)


def rated_rates() -> dict[str, float]:
    """{key: rate_hz} as the producers' contracts declare them."""
    out: dict[str, float] = {}
    for c in load_contracts():
        out.update({k: hz for k, hz in c.rates_hz.items() if k in c.outputs})
    return out


def cpu_times() -> tuple[float, float]:
    """(idle, total) jiffies of the whole machine from /proc/stat (idle includes iowait)."""
    with open("/proc/stat") as f:
        fields = [float(x) for x in f.readline().split()[1:]]
    return fields[3] + fields[4], sum(fields[:8])   # user nice system idle iowait irq softirq steal


def idle_pct(before: tuple[float, float], after: tuple[float, float]) -> float:
    total = after[1] - before[1]
    return 100.0 * (after[0] - before[0]) / total if total > 0 else float("nan")


class Counter:
    """Arrivals per key (no decoding) while `counting`."""

    def __init__(self, session, keys: list[str]):
        self.counts = dict.fromkeys(keys, 0)
        self.counting = False
        self.lock = threading.Lock()
        self.subs = [session.declare_subscriber(k, self._cb(k)) for k in keys]

    def _cb(self, key: str):
        def on_sample(_s) -> None:
            if self.counting:
                with self.lock:
                    self.counts[key] += 1
        return on_sample


@dataclass
class StackReport:
    processes: list[dict]      # bench_soak.summarize rows + diag_cpu_pct, budget_pct, level
    rates: list[tuple[str, float | None, float | None]]   # (label, achieved Hz or None: not running, rated)
    hot_path: HotPath
    idle_pct: float
    duration_s: float
    cores: int
    bench_pct: float = 0.0     # this bench's own process (its tap, counters, sampler), % of one core

    def others_pct(self) -> float:
        """CPU (% of one core) the machine spent outside the stack's processes and this bench."""
        busy = (100.0 - self.idle_pct) * self.cores
        return max(0.0, busy - sum(r["cpu_mean_pct"] for r in self.processes) - self.bench_pct)

    def stack_idle_pct(self) -> float:
        """The machine's idle % with this bench's own CPU given back: what the stack leaves idle."""
        return min(100.0, self.idle_pct + self.bench_pct / self.cores)

    def problems(self) -> list[str]:
        """Why this machine is not big enough ([] when it is)."""
        out = [f"{label} {hz:.1f} of {rated:g} Hz" for label, hz, rated in self.rates
               if hz is not None and rated and hz < RATE_OK * rated]
        if not self.stack_idle_pct() >= IDLE_GOAL_PCT:
            out.append(f"idle {self.stack_idle_pct():.0f} % < {IDLE_GOAL_PCT:g} %")
        lat, gaps = self.hot_path.lat, self.hot_path.gaps
        if not (len(lat) and np.percentile(lat, 99) < HOT_PATH_P99_MS):
            out.append(f"hot path p99 {_p(lat, 99):.1f} ms >= {HOT_PATH_P99_MS:g} ms")
        if not (len(gaps) and np.percentile(gaps, 99) < GAP_P99_MS):
            out.append(f"setpoint gap p99 {_p(gaps, 99):.1f} ms >= {GAP_P99_MS:g} ms")
        return out

    def format(self) -> str:
        lines = [f"{'process':<18} {'CPU %':>6} {'RSS MB':>7} {'own CPU %':>9} {'budget %':>8}  diagnostics"]
        for r in sorted(self.processes, key=lambda r: -r["cpu_mean_pct"]):
            lines.append(f"{r['process']:<18} {r['cpu_mean_pct']:>6.1f} {r['rss_end_mb']:>7.1f} "
                         f"{r['diag_cpu_pct']:>9} {r['budget_pct']:>8}  {r['level']}")
        total = sum(r["cpu_mean_pct"] for r in self.processes)
        lines.append(f"{'sum':<18} {total:>6.1f}   (of {100 * self.cores} % for {self.cores} cores); "
                     f"machine idle {self.idle_pct:.1f} % ({self.stack_idle_pct():.1f} % without this bench's "
                     f"own {self.bench_pct:.0f} % of a core), other programs {self.others_pct():.0f} %")
        lines.append("")
        lines.append(f"{'topic':<22} {'achieved Hz':>11} {'rated Hz':>9} {'ratio':>6}")
        for label, hz, rated in self.rates:
            got = "off" if hz is None else f"{hz:.1f}"
            ratio = f"{hz / rated:.2f}" if hz is not None and rated else "-"
            lines.append(f"{label:<22} {got:>11} {rated or float('nan'):>9g} {ratio:>6}")
        lines.append("")
        lines.append(f"{'control hot path':<44} {'n':>6} {'median_ms':>10} {'p99_ms':>8}")
        for name, n, med, p99 in self.hot_path.rows():
            lines.append(f"{name:<44} {n:>6} {med:>10.3f} {p99:>8.3f}")
        problems = self.problems()
        if problems and self.others_pct() > 25.0:
            problems.append(f"other programs used {self.others_pct():.0f} % of a core meanwhile: measure on a "
                            "quiet machine to judge it")
        lines.append("")
        lines.append("verdict: big enough for this profile (every rate >= 90 % of rated, idle >= 25 %, hot path "
                     "p99 < 5 ms, setpoint gap p99 < 25 ms)" if not problems else
                     "verdict: NOT big enough: " + "; ".join(problems))
        return "\n".join(lines)


def _p(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if len(a) else float("nan")


def _diag_row(d: DiagnosticStatus | None) -> dict:
    if d is None:
        return dict(diag_cpu_pct="-", budget_pct="-", level="no diagnostics")
    v = d.values
    own = v.get(f"cpu_pct_{SUSTAIN_S:g}s", v.get("cpu_pct", "-"))
    level = ["OK", "WARN", "ERROR", "STALE"][d.level] if 0 <= d.level < 4 else str(d.level)
    return dict(diag_cpu_pct=own, budget_pct=v.get("cpu_budget_pct", "-"),
                level=level if d.level == DiagnosticStatus.OK else f"{level}: {d.message[:60]}")


def measure(profile: str = "sim", sensors: str = "all", duration_s: float = 30.0, scenario: str = "village",
            links: str = "direct",
            settle_s: float = 8.0) -> StackReport:
    """Bring the stack up, hover, measure `duration_s`; stop it. RuntimeError if it did not come up."""
    rated = rated_rates()
    hover = HoverRun(sensors, True, ("--profile", profile, "--scenario", scenario, "--sensors", sensors,
                                     "--links", links))
    try:
        hover.take_off(timeout_s=120.0, settle_s=settle_s)
        services = set(hover.pids())
        counted = [s.key for s in STREAMS if not s.sim_counter]
        counter = Counter(hover.session, counted)
        sampler = Sampler(hover, period_s=1.0)
        sim0 = hover.last_diag.get("sim", DiagnosticStatus())
        idle0, t0, own0 = cpu_times(), time.monotonic(), time.process_time()
        sampler.sample()
        sampler.start()
        counter.counting = True
        hover.begin()
        time.sleep(duration_s)
        hot = hover.end()
        counter.counting = False
        span = time.monotonic() - t0
        sampler.stop()
        sampler.sample()
        idle = idle_pct(idle0, cpu_times())
        bench_pct = 100.0 * (time.process_time() - own0) / span
        time.sleep(1.2)   # the diagnostics that cover the window's end
        diags = dict(hover.last_diag)
    finally:
        hover.close()
    sim1 = diags.get("sim", DiagnosticStatus())
    sim_span = (sim1.header.stamp_ns - sim0.header.stamp_ns) / 1e9   # between the two frame counts
    rates = []
    for s in STREAMS:
        hz: float | None
        if s.producer not in services:
            hz = None
        elif s.sim_counter:
            key = f"{s.sim_counter}_frames"
            counts = [int(d.values[key]) for d in (sim0, sim1) if key in d.values]
            hz = (counts[1] - counts[0]) / sim_span if len(counts) == 2 and sim_span > 0 else None
        else:
            hz = counter.counts[s.key] / span
        rates.append((s.label, hz, rated.get(s.rated_like or s.key)))
    rows = summarize(sampler.samples, sampler.pids)
    for r in rows:
        r.update(_diag_row(diags.get(r["process"])) if r["process"] in services else
                 dict(diag_cpu_pct="-", budget_pct="-", level="(not a service)"))
    return StackReport(rows, rates, hot, idle, duration_s, os.cpu_count() or 1, bench_pct)


def run(profile: str = "sim", sensors: str = "all", duration_s: float = 30.0, scenario: str = "village",
        links: str = "direct") -> int:
    sys.setswitchinterval(SWITCH_INTERVAL_S)   # the tap timing the hot path must not wait for the GIL
    if duration_s < 5.0:
        raise CliError(f"--duration {duration_s:g}: measure at least 5 s (rates and p99 need samples)")
    try:
        report = measure(profile, sensors, duration_s, scenario, links)
    except RuntimeError as e:
        raise CliError(str(e)) from None
    print(f"aero bench stack: profile {profile}, scenario {scenario}, sensors {sensors}, {links} links, hovering, "
          f"{duration_s:g} s measured, {report.cores} cores")
    print(report.format())
    return 0
