"""`aero bench objects`: the objects service's CPU per detection frame on a rendered pair from the
search flight's height, beside a full-frame disparity map in the same run."""
from __future__ import annotations

import pytest

from aeroperception.tools.bench.objects import run

# extended: building a scene and rendering a pair takes 10-30 s on a loaded 2-core machine;
# test_objects_logic's ten-box frame holds the per-frame cost on the default run.
pytestmark = pytest.mark.extended


def test_bench_times_the_service_against_a_full_frame_disparity_map(capsys):
    assert run(n=2, scenario="open_field", counts=(1, 3)) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line.strip().startswith(("1 |", "3 |"))]
    assert [r[0] for r in rows] == ["1", "3"], out
    for r in rows:                                  # boxes | p50 p99 | baseline p50 p99 | ratio
        assert float(r[2]) > 0 and float(r[5]) > 0 and float(r[8]) > 0
