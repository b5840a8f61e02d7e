"""A service process's own CPU and memory, reported in every diagnostics/<service>, and its CPU
budget.

cpu_pct is % of one core (100 = one core busy; a process with several busy threads can exceed
100) over the interval since the previous report (about 1 s, the diagnostics period); rss_mb is
the resident set now. Threads are counted, child processes are not (they are separate processes,
with diagnostics of their own when they run a Node).

Budget rule: a service's contract may declare CPU_BUDGET_PCT (% of one core). The service is over
budget when its mean CPU over the last SUSTAIN_S seconds exceeds the budget; only then do its
diagnostics say WARN. A busy second (start-up, one slow input) does not warn; a service that is
steadily too expensive for its share of the machine does, within SUSTAIN_S.
"""
from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

SUSTAIN_S = 10.0
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def own_usage() -> tuple[float, float, int | None]:
    """(monotonic s, CPU s used by this process's threads, RSS bytes or None where unknown)."""
    t = os.times()
    try:
        with open("/proc/self/statm", "rb") as f:
            rss: int | None = int(f.read().split()[1]) * _PAGE
    except (OSError, IndexError, ValueError):
        rss = None
    return time.monotonic(), t.user + t.system, rss


@dataclass(frozen=True)
class CpuReport:
    cpu_pct: float                  # over the last interval
    sustained_pct: float | None     # mean over the last SUSTAIN_S (None until that much history)
    rss_mb: float | None
    budget_pct: float | None

    @property
    def over_budget(self) -> bool:
        return self.budget_pct is not None and self.sustained_pct is not None and self.sustained_pct > self.budget_pct

    def values(self) -> dict[str, str]:
        out = {"cpu_pct": f"{self.cpu_pct:.1f}"}
        if self.sustained_pct is not None:
            out[f"cpu_pct_{SUSTAIN_S:g}s"] = f"{self.sustained_pct:.1f}"
        if self.rss_mb is not None:
            out["rss_mb"] = f"{self.rss_mb:.1f}"
        if self.budget_pct is not None:
            out["cpu_budget_pct"] = f"{self.budget_pct:g}"
        return out

    def problem(self) -> str:
        """What to say when over budget, else ""."""
        if not self.over_budget:
            return ""
        return f"cpu {self.sustained_pct:.0f} % of a core over {SUSTAIN_S:g} s > budget {self.budget_pct:g} %"


class CpuMeter:
    """Successive `report()` calls measure the CPU used between them (and over SUSTAIN_S)."""

    def __init__(self, budget_pct: float | None = None, sustain_s: float = SUSTAIN_S,
                 usage: Callable[[], tuple[float, float, int | None]] = own_usage):
        if budget_pct is not None and budget_pct <= 0:
            raise ValueError(f"CPU budget must be > 0 % of a core, got {budget_pct}")
        self.budget_pct, self.sustain_s, self._usage = budget_pct, sustain_s, usage
        wall, cpu, _ = usage()
        self._history: deque[tuple[float, float]] = deque([(wall, cpu)])

    def report(self) -> CpuReport:
        wall, cpu, rss = self._usage()
        last_wall, last_cpu = self._history[-1]
        self._history.append((wall, cpu))
        # Keep the newest sample at least sustain_s old as the window's start.
        while len(self._history) > 2 and wall - self._history[1][0] >= self.sustain_s:
            self._history.popleft()
        first_wall, first_cpu = self._history[0]
        sustained = _pct(cpu - first_cpu, wall - first_wall) if wall - first_wall >= self.sustain_s else None
        return CpuReport(cpu_pct=_pct(cpu - last_cpu, wall - last_wall), sustained_pct=sustained,
                         rss_mb=None if rss is None else rss / 1e6, budget_pct=self.budget_pct)


def _pct(cpu_s: float, wall_s: float) -> float:
    return 100.0 * max(cpu_s, 0.0) / wall_s if wall_s > 0 else 0.0
