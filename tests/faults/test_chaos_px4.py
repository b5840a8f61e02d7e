"""The fault table against real PX4 SITL (SIH): the `aero chaos --profile px4` rows as tests, on one
module-scoped Px4Stack (PX4 instance picked free from 1, the tap between PX4 and fmu), each judged
by SIH's ground truth (HIL_STATE_QUATERNION), never by the stack's account.

The default run flies the pilot's HOLD (PX4's own mode switch, what only a real PX4 shows); the rest
of the table is `extended` (`pytest -m "px4 and extended" tests/faults/test_chaos_px4.py`, or
`aero chaos --profile px4`): each row is a survey flight, and the kill rows repeat test_px4's.
"""
from __future__ import annotations

import pytest

from aerotest import assert_chaos_row, chaos_row_param
from aeroperception.tools.cli.chaos import build_rows
from aeroperception.tools.harness import Px4Stack
from aeroperception.tools.harness.px4_stack import PX4_FLIGHT_SERVICES

ROWS = build_rows(PX4_FLIGHT_SERVICES, "px4")
CI_ROWS = ("pilot_hold",)

pytestmark = [pytest.mark.px4, pytest.mark.slow]


@pytest.fixture(scope="module")
def px4_chaos(px4_build, tmp_path_factory):
    st = Px4Stack(px4_build, tmp_path_factory.mktemp("chaos-px4"))
    try:
        yield st
    finally:
        st.stop()


@pytest.mark.timeout(240)
@pytest.mark.parametrize("name", [chaos_row_param(n, CI_ROWS, pytest.mark.extended) for n in ROWS])
def test_px4_fault_row_meets_its_expected_outcome_and_vehicle_stays_safe(px4_chaos, mission_json, name):
    assert_chaos_row(px4_chaos, ROWS[name], mission_json)
