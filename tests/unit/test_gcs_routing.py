"""Which received MAVLink messages are gcs's to answer (services/gcs/routing.py), as the vehicle
and as the flight controller's onboard computer."""
from __future__ import annotations

import pytest

from aeroperception.services.gcs import contract
from aeroperception.services.gcs.config import GcsConfig
from aeroperception.services.gcs.routing import ignored_because
from aeroperception.services.runtime.config import build, check_covers

SYS, AUTOPILOT, COMPANION = 1, 1, contract.COMPANION_COMPONENT_ID


@pytest.mark.parametrize("msg_type, target_sys, target_comp, companion, why", [
    ("COMMAND_LONG", 1, 1, False, None),
    ("COMMAND_LONG", 0, 0, False, None),                           # to every system
    ("HEARTBEAT", None, None, False, None),                        # no target at all
    ("COMMAND_LONG", 7, 1, False, "other_target"),
    ("FILE_TRANSFER_PROTOCOL", 7, 1, False, None),                 # answered whatever its target
    ("COMMAND_LONG", 1, AUTOPILOT, True, "other_component"),       # the FC's own: it answers
    ("COMMAND_LONG", 1, COMPANION, True, None),
    ("PARAM_REQUEST_LIST", 1, 0, True, None),                      # parameters of every component: ours too
    ("PARAM_SET", 1, 0, True, "other_component"),
    ("COMMAND_LONG", 7, COMPANION, True, "other_target"),
])
def test_only_what_is_addressed_to_us_is_answered(msg_type, target_sys, target_comp, companion, why):
    comp = COMPANION if companion else AUTOPILOT
    assert ignored_because(msg_type, target_sys, target_comp, SYS, comp, companion) == why


def test_the_config_references_every_parameter_and_splits_the_exposed_services():
    check_covers(GcsConfig, contract.PARAMS, "gcs")
    assert build(GcsConfig, contract.PARAMS).param_services == ("planner", "mission", "fmu", "gcs", "safety")
