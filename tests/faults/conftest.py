"""Fault-suite fixtures: one harness SimStack per test module (sim profile, free ports, the
MAVLink tap between sim and fmu), as `aero chaos` flies it; stopped by pid at teardown."""
from __future__ import annotations

import pytest

from aeroperception.tools.cli.chaos import DEFAULT_MISSION
from aeroperception.tools.harness import SimStack


@pytest.fixture(scope="module")
def chaos_stack(tmp_path_factory):
    st = SimStack(tmp_path_factory.mktemp("chaos"))
    try:
        yield st
    finally:
        st.stop()


@pytest.fixture(scope="session")
def mission_json() -> str:
    return DEFAULT_MISSION.read_text()
