"""`aero bench stack`: the whole sim profile hovering, measured from outside (tools/bench/stack.py).

Short (LiDAR only, a 5 s window: the CLI's minimum, ~250 hot-path samples at 50 Hz): the table
lists every service the profile starts with the CPU /proc saw and the CPU the service reports itself
in diagnostics/<service> (the runtime's accounting, no per-service code), the key topics' achieved
vs rated rates, the hot path and a verdict. Loose bounds: the machine is shared, so only
"plausible" is asserted, not the goals.
"""
from __future__ import annotations

import numpy as np

from aeroperception.tools.bench.stack import STREAMS, measure
from aeroperception.tools.cli.up import fed_services
from aeroperception.tools.harness import profile_services


def test_bench_stack_reports_every_process_rates_hot_path_and_a_verdict():
    report = measure("sim", "lidar", duration_s=5.0, settle_s=4.0)
    started, _ = fed_services(profile_services("sim"), "lidar")
    rows = {r["process"]: r for r in report.processes}
    assert set(started) | {"aero up", "router"} <= set(rows), sorted(rows)
    for name in started:
        r = rows[name]
        assert r["cpu_mean_pct"] > 0 and 20 < r["rss_end_mb"] < 4000, r
        assert float(r["diag_cpu_pct"]) > 0, r   # the runtime's own report, every service
    assert rows["lidar"]["budget_pct"] == "25"

    rates = {label: (hz, rated) for label, hz, rated in report.rates}
    assert [s.label for s in STREAMS] == list(rates)
    assert rates["camera (left+right)"] == (None, 20.0) and rates["VIO odometry"][0] is None   # not rendered
    assert rates["state/vehicle"][0] > 40 and rates["state/vehicle"][1] == 50.0, rates
    assert rates["setpoints"][0] > 40 and rates["setpoints"][1] == 50.0, rates
    assert rates["LiDAR scans"][0] > 0 and rates["LiDAR scans"][1] == 10.0, rates

    hp = report.hot_path
    assert len(hp.lat) > 100 and 0 < np.median(hp.lat) < 50, hp.rows()[0]
    assert 0.0 <= report.idle_pct <= 100.0

    text = report.format()
    for section in ("process", "topic", "control hot path", "verdict: "):
        assert section in text, text
    verdict = text.splitlines()[-1]
    assert verdict.startswith("verdict: big enough") == (not report.problems()), verdict
