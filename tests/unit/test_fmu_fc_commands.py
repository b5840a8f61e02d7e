"""A command to the flight controller and its verdict (services/fmu/fc_commands.py), fed ACKs and
STATUSTEXTs directly: accepted and confirmed by the heartbeat, refused naming the FC's reason,
OFFBOARD re-sent while TEMPORARILY_REJECTED, no ACK, no link.
"""
from __future__ import annotations

import time
from types import SimpleNamespace

from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.fmu.fc_commands import FcCommands

ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
SET_MODE = mavlink.MAV_CMD_DO_SET_MODE


class FakeFc:
    """Answers each COMMAND_LONG with the next result in `results` (none left: no answer), and
    may say why in a STATUSTEXT first."""

    def __init__(self, *results: int, statustext: str = "", fresh: bool = True):
        self.results = list(results)
        self.statustext = statustext
        self.fresh = fresh
        self.sent: list[tuple[int, list[float]]] = []
        self.sleeps: list[float] = []
        self.fc = FcCommands(self.send, lambda: self.fresh, "udpin:127.0.0.1:14540", {"commands_retried": 0},
                             sleep=self.nap)

    def nap(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        time.sleep(0.001)      # waits are recorded, not slept

    def send(self, command: int, params7: list[float]) -> None:
        self.sent.append((command, params7))
        if self.statustext:
            self.fc.on_statustext(mavlink.MAV_SEVERITY_CRITICAL, self.statustext)
        if self.results:
            self.fc.on_ack(SimpleNamespace(command=command, result=self.results.pop(0)))


def test_accepted_and_confirmed_by_the_heartbeat_succeeds_with_the_params_padded_to_seven():
    rig = FakeFc(mavlink.MAV_RESULT_ACCEPTED)
    assert rig.fc.run(ARM, [1.0], lambda: True, timeout_s=1.0) == (True, "confirmed by heartbeat")
    assert rig.sent == [(ARM, [1.0, 0, 0, 0, 0, 0, 0])]


def test_a_refusal_names_the_flight_controllers_reason():
    rig = FakeFc(mavlink.MAV_RESULT_DENIED, statustext="Arming denied: Resolve system health failures first")
    ok, msg = rig.fc.run(ARM, [1.0], lambda: True, timeout_s=1.0)
    assert not ok and msg == "flight controller answered DENIED: Arming denied: Resolve system health failures first"


def test_an_info_statustext_is_not_taken_for_the_reason():
    rig = FakeFc(mavlink.MAV_RESULT_DENIED)
    rig.fc.on_statustext(mavlink.MAV_SEVERITY_INFO, "Takeoff detected")
    assert rig.fc.run(ARM, [1.0], lambda: True, timeout_s=1.0) == (False, "flight controller answered DENIED")


def test_offboard_temporarily_rejected_is_resent_until_accepted():
    rig = FakeFc(mavlink.MAV_RESULT_TEMPORARILY_REJECTED, mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
                 mavlink.MAV_RESULT_ACCEPTED)
    assert rig.fc.run(SET_MODE, [1.0, 6.0], lambda: True, timeout_s=2.0, retry_rejected=True)[0]
    assert len(rig.sent) == 3 and rig.fc.counters["commands_retried"] == 2


def test_temporarily_rejected_without_retry_is_a_refusal():
    rig = FakeFc(mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
    ok, msg = rig.fc.run(SET_MODE, [1.0, 6.0], lambda: True, timeout_s=1.0)
    assert not ok and msg.startswith("flight controller answered TEMPORARILY_REJECTED") and len(rig.sent) == 1


def test_no_ack_within_the_timeout_says_so():
    rig = FakeFc()
    assert rig.fc.run(ARM, [1.0], lambda: True, timeout_s=0.05) == (False, "no COMMAND_ACK within 0.1 s")


def test_accepted_but_never_seen_in_the_heartbeat_is_not_a_success():
    rig = FakeFc(mavlink.MAV_RESULT_ACCEPTED)
    assert rig.fc.run(ARM, [1.0], lambda: False, timeout_s=0.05) == \
        (False, "accepted but not confirmed by the heartbeat in time")


def test_no_link_refuses_without_sending():
    rig = FakeFc(mavlink.MAV_RESULT_ACCEPTED, fresh=False)
    assert rig.fc.run(ARM, [1.0], lambda: True, timeout_s=1.0) == \
        (False, "no link to the flight controller (udpin:127.0.0.1:14540)")
    assert rig.sent == []
