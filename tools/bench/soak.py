"""`aero bench soak`: the sim stack flying missions in a loop for N minutes, with the memory and
CPU of every process sampled from /proc: leaks and runaway loops show up as growth per hour.

Per process (each service, its children such as the sim's render workers counted with it, and
`aero up` itself, which hosts the router): RSS at start / end / max (MB), mean CPU % of one core,
and RSS growth in MB/h (least-squares slope after the first minute, when imports and caches have
settled). Missions flown / failed and service restarts are reported too.
"""
from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from aeroperception.tools.cli.chaos import DEFAULT_MISSION
from aeroperception.tools.harness import SimStack, StackStartError, poll_until, proc_stats
from aeroperception.tools.common import CliError

WARMUP_S = 60.0


def _children(pid: int) -> list[int]:
    """Direct children of `pid` (from /proc/*/stat's ppid field)."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        if int(stat[stat.rindex(")") + 2:].split()[1]) == pid:
            out.append(int(entry))
    return out


SUPERVISOR, ROUTER = "aero up", "router"   # processes of the stack that are not services


def router_pid(st) -> int | None:
    """The router `aero up` runs as its own child (<log dir>/router.pid), if it does."""
    folder = getattr(st, "run_dir", None) or getattr(st, "log_dir", None)
    try:
        return int((Path(folder) / "router.pid").read_text().split()[0])
    except (OSError, TypeError, ValueError, IndexError):
        return None


class Sampler:
    """Samples {name: (t, rss_bytes, cpu_s)} every period_s in its own thread."""

    def __init__(self, st: SimStack, period_s: float):
        self.st, self.period_s = st, period_s
        self.samples: dict[str, list[tuple[float, int, float]]] = {}
        self.pids: dict[str, set[int]] = {}
        self.stop_ev = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "Sampler":
        self.thread.start()
        return self

    def sample(self) -> None:
        now = time.monotonic()
        procs = dict(self.st.pids())
        if self.st.proc is not None:
            procs[SUPERVISOR] = self.st.proc.pid
        router = router_pid(self.st)
        if router is not None:
            procs[ROUTER] = router
        for name, pid in procs.items():
            rss, cpu = 0, 0.0
            for p in [pid, *(_children(pid) if name not in (SUPERVISOR, ROUTER) else [])]:
                s = proc_stats(p)
                if s is not None:
                    rss, cpu = rss + s[0], cpu + s[1]
            if rss:
                self.samples.setdefault(name, []).append((now, rss, cpu))
                self.pids.setdefault(name, set()).add(pid)

    def _run(self) -> None:
        while not self.stop_ev.wait(self.period_s):
            self.sample()

    def stop(self) -> None:
        self.stop_ev.set()
        self.thread.join(2 * self.period_s)


def summarize(samples: dict[str, list[tuple[float, int, float]]], pids: dict[str, set[int]]) -> list[dict]:
    rows = []
    for name, s in samples.items():
        t = np.array([x[0] for x in s])
        rss = np.array([x[1] for x in s]) / 1e6
        cpu = np.array([x[2] for x in s])
        # CPU %: sum of positive cpu-second increments (a restarted process starts again at 0).
        inc = np.clip(np.diff(cpu), 0, None).sum() if len(cpu) > 1 else 0.0
        span = t[-1] - t[0] if len(t) > 1 else 0.0
        late = t >= t[0] + WARMUP_S
        slope = float(np.polyfit(t[late] - t[0], rss[late], 1)[0]) * 3600 if late.sum() >= 3 else float("nan")
        rows.append(dict(process=name, samples=len(s), rss_start_mb=round(float(rss[0]), 1),
                         rss_end_mb=round(float(rss[-1]), 1), rss_max_mb=round(float(rss.max()), 1),
                         cpu_mean_pct=round(100.0 * inc / span, 1) if span else float("nan"),
                         growth_mb_per_h=round(slope, 2), restarts=len(pids.get(name, ())) - 1))
    return rows


def format_table(rows: list[dict]) -> str:
    head = f"{'process':<18} {'start MB':>9} {'end MB':>8} {'max MB':>8} {'CPU %':>7} {'MB/h':>8} {'restarts':>8}"
    lines = [head]
    for r in rows:
        lines.append(f"{r['process']:<18} {r['rss_start_mb']:>9.1f} {r['rss_end_mb']:>8.1f} {r['rss_max_mb']:>8.1f} "
                     f"{r['cpu_mean_pct']:>7.1f} {r['growth_mb_per_h']:>8.2f} {r['restarts']:>8}")
    return "\n".join(lines)


def fly_once(st: SimStack, mission_json: str, timeout_s: float = 180.0) -> str | None:
    """One mission from the ground back to landed+disarmed; None on success, else why not."""
    if not st.ensure_ground():
        return "could not get back to the ground"
    why = st.start_mission(mission_json)
    if why:
        return why
    if not poll_until(lambda: st.mission_state() == "IDLE" and st.landed(), timeout_s, 1.0):
        return f"mission not finished within {timeout_s:.0f} s (state {st.mission_state()})"
    return None


def run(minutes: float, sensors: str = "all", period_s: float = 5.0, json_path: str | None = None,
        mission: str = str(DEFAULT_MISSION), log_dir: str | None = None) -> int:
    try:
        mission_json = Path(mission).read_text()
    except OSError as e:
        raise CliError(f"cannot read mission {mission}: {e.strerror}") from None
    try:
        st = SimStack(log_dir, sensors=sensors, startup_timeout_s=90.0)
    except StackStartError as e:
        raise CliError(f"the sim stack did not come up: {str(e).splitlines()[0]}") from None
    print(f"aero bench soak: {minutes:g} min, sensors={sensors}, sampling every {period_s:g} s, "
          f"logs {st.log_dir}", flush=True)
    sampler = Sampler(st, period_s)
    sampler.sample()
    sampler.start()
    flown, failed, errors = 0, 0, []
    t_end = time.monotonic() + minutes * 60.0
    try:
        while time.monotonic() < t_end:
            why = fly_once(st, mission_json, timeout_s=max(30.0, min(180.0, t_end - time.monotonic() + 60.0)))
            if why:
                failed += 1
                errors.append(why)
                print(f"  mission {flown + failed}: FAILED: {why}", flush=True)
            else:
                flown += 1
                print(f"  mission {flown + failed}: ok ({(t_end - time.monotonic()) / 60:.1f} min left)", flush=True)
    finally:
        sampler.stop()
        sampler.sample()
        st.stop()
    rows = summarize(sampler.samples, sampler.pids)
    print(f"\nsoak {minutes:g} min, sensors={sensors}: {flown} missions flown, {failed} failed, "
          f"{os.cpu_count()} cores")
    print(format_table(rows))
    if json_path:
        Path(json_path).write_text(json.dumps(dict(minutes=minutes, sensors=sensors, missions_flown=flown,
                                                   missions_failed=failed, errors=errors[:20], processes=rows),
                                              indent=1) + "\n")
    return 0 if failed == 0 else 1
