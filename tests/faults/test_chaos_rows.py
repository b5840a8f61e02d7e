"""Every `aero chaos` row as a test, on one module-scoped sim stack: fly survey_01, inject one
fault mid-leg (or on the ground for the FC reboot), assert the row's expected outcome (ARCHITECTURE
§8, stated in each Row) and that the vehicle stayed safe by sim/truth/state.
"""
from __future__ import annotations

import pytest

from aerotest import assert_chaos_row, chaos_row_param
from aeroperception.tools.cli.chaos import build_rows
from aeroperception.tools.harness import profile_services

ROWS = build_rows(profile_services("sim"))
# The rows the default run (and CI) flies: a hang and a reboot. The kills are chaos_full because the
# default run kills services mid-flight elsewhere (test_mission_faults: mission killed -> restarts
# holding, resumes, lands; fmu killed -> the mission holds; test_fmu_faults: no stale motion
# replayed), and CI's 30 minutes on 2 cores (the compose flights included) have no room for the
# copies. Every row: `pytest -m chaos_full tests/faults`.
CI_ROWS = ("hang_fmu", "fc_reboot")


@pytest.mark.slow
@pytest.mark.timeout(150)
@pytest.mark.parametrize("name", [chaos_row_param(n, CI_ROWS, pytest.mark.chaos_full) for n in ROWS])
def test_fault_row_meets_its_expected_outcome_and_vehicle_stays_safe(chaos_stack, mission_json, name):
    assert_chaos_row(chaos_stack, ROWS[name], mission_json)
