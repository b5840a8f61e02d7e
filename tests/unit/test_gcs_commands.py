"""COMMAND_LONG / COMMAND_INT: one final ACK with the real outcome, retransmissions not run twice,
the command table."""
from __future__ import annotations

import math

import pytest
from gcs_support import HOME, FakeOps, cmd_long, from_gcs
from pymavlink.dialects.v20 import common as M

from aeroperception.services.gcs.commands import CommandHandler, mode_from_set_mode
from aeroperception.services.gcs.ops import Outcome
from aeroperception.services.mavlink import px4


def handler():
    sent, ops = [], FakeOps()
    h = CommandHandler(sent.append, ops, HOME, position_enu=lambda: (1.0, 2.0, 3.0),
                       request_message=lambda mid, p2: M.MAV_RESULT_ACCEPTED if mid == 148 else M.MAV_RESULT_UNSUPPORTED,
                       set_interval=lambda mid, us: True, set_current=lambda s: s < 3)
    return h, sent, ops


def test_arm_acks_real_outcome_once_and_no_double_execution():
    """One final ACK, never IN_PROGRESS (MAVSDK takes it as the outcome); a retry while
    the first runs is neither run again nor answered; a refusal comes with a STATUSTEXT reason."""
    h, sent, ops = handler()
    notes = []
    h.notify = lambda text, peer: notes.append((text, peer))
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), 0.0)
    assert ops.calls == [("arm", True, False)] and sent == []
    h.tick(0.35)
    assert sent == []                                                  # no IN_PROGRESS
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), 0.5)      # MAVSDK's retransmission
    assert len(ops.calls) == 1 and sent == [] and h.retransmissions == 1
    ops.dones[0](Outcome(False, "pre-arm check failed"))
    assert [m.result for m in sent] == [M.MAV_RESULT_DENIED] and sent[-1].target_system == 255
    assert notes == [("COMPONENT_ARM_DISARM denied: pre-arm check failed", (255, 190))]
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, math.nan), 0.9)      # MAVSDK leaves param2 NaN
    assert ops.calls[-1] == ("arm", True, False)
    ops.dones[-1](Outcome(True, "ok"))
    h.handle(cmd_long(M.MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 21196.0), 1.0)
    assert ops.calls[-1] == ("arm", False, True)
    ops.dones[-1](Outcome(True, "ok"))
    assert sent[-1].result == M.MAV_RESULT_ACCEPTED
    assert M.MAV_RESULT_IN_PROGRESS not in [m.result for m in sent]


def test_mode_change_final_ack_failed_when_the_stack_does_not_answer():
    h, sent, ops = handler()
    notes = []
    h.notify = lambda text, peer: notes.append(text)
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 3), 0.0)   # POSCTL
    assert ops.calls == [("set_mode", "POSCTL")]
    ops.dones[0](Outcome(False, "timeout calling fmu/srv/set_mode", failed=True))   # the call failed: FAILED
    assert sent[-1].result == M.MAV_RESULT_FAILED and notes[-1].startswith("DO_SET_MODE failed: timeout")
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 3), 1.0)
    h.tick(7.0, timeout_s=5.0)                                            # nothing ever came back
    assert sent[-1].result == M.MAV_RESULT_FAILED and len(sent) == 2
    ops.dones[1](Outcome(True, "late"))                                   # too late: not answered twice
    assert len(sent) == 2


def test_do_change_speed_command():
    h, sent, ops = handler()
    h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, 1.0, 3.5, -1.0), 0.0)      # ground speed 3.5 m/s
    assert ops.calls[-1] == ("speed", 3.5) and sent == []
    ops.dones[-1](Outcome(True, "ok"))
    assert sent[-1].command == M.MAV_CMD_DO_CHANGE_SPEED and sent[-1].result == M.MAV_RESULT_ACCEPTED
    h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, 0.0, 20.0), 0.0)           # the planner refuses it
    assert ops.calls[-1] == ("speed", 20.0)
    ops.dones[-1](Outcome(False, "above max"))
    assert sent[-1].result == M.MAV_RESULT_DENIED
    h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, 1.0, -2.0), 0.0)           # back to the default
    assert ops.calls[-1] == ("speed", None)
    ops.dones[-1](Outcome(True, "ok"))
    n = len(ops.calls)
    for p1, p2, result in ((1.0, -1.0, M.MAV_RESULT_ACCEPTED),             # no change
                           (1.0, math.nan, M.MAV_RESULT_ACCEPTED),
                           (2.0, 1.0, M.MAV_RESULT_UNSUPPORTED),            # climb speed
                           (1.0, 0.0, M.MAV_RESULT_DENIED),
                           (1.0, -3.0, M.MAV_RESULT_DENIED),
                           (9.0, 2.0, M.MAV_RESULT_DENIED)):
        h.handle(cmd_long(M.MAV_CMD_DO_CHANGE_SPEED, p1, p2), 0.0)
        assert sent[-1].result == result, (p1, p2)
    assert len(ops.calls) == n                       # none of those reached the planner


def test_command_table():
    h, sent, ops = handler()
    h.handle(cmd_long(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, HOME.alt_m + 5.0), 0.0)
    assert ops.calls[-1] == ("takeoff", pytest.approx(5.0))
    h.handle(cmd_long(M.MAV_CMD_NAV_LAND), 0.0)
    assert ops.calls[-1] == ("mission", "LAND")
    h.handle(cmd_long(M.MAV_CMD_NAV_RETURN_TO_LAUNCH), 0.0)
    assert ops.calls[-1] == ("mission", "RTL")
    h.handle(cmd_long(M.MAV_CMD_MISSION_START), 0.0)
    assert ops.calls[-1] == ("start",)
    base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, base, 4, 3), 0.0)
    assert ops.calls[-1] == ("set_mode", "HOLD")
    lat, lon = HOME.projection.reproject(10.0, 0.0)
    h.handle(from_gcs(M.MAVLink_command_int_message(1, 1, M.MAV_FRAME_GLOBAL, M.MAV_CMD_DO_REPOSITION, 0, 0,
                                                    -1, 0, 0, math.nan, int(lat * 1e7), int(lon * 1e7),
                                                    HOME.alt_m + 4.0)), 0.0)
    kind, enu, yaw = ops.calls[-1]
    assert kind == "goto" and enu == pytest.approx((0.0, 10.0, 4.0), abs=0.02) and yaw is None
    for c in (M.MAV_CMD_REQUEST_PROTOCOL_VERSION, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
        h.handle(cmd_long(c, 1.0), 0.0)
        assert sent[-1].command == c and sent[-1].result == M.MAV_RESULT_ACCEPTED
    h.handle(cmd_long(M.MAV_CMD_REQUEST_MESSAGE, 148), 0.0)
    assert sent[-1].result == M.MAV_RESULT_ACCEPTED
    h.handle(cmd_long(M.MAV_CMD_REQUEST_MESSAGE, 9999), 0.0)
    assert sent[-1].result == M.MAV_RESULT_UNSUPPORTED
    for done in ops.dones:
        done(Outcome(True, "ok"))
    h.handle(cmd_long(M.MAV_CMD_DO_SET_MODE, base, 99, 0), 0.0)
    assert sent[-1].result == M.MAV_RESULT_DENIED
    h.handle(cmd_long(M.MAV_CMD_DO_FLIGHTTERMINATION, 1), 0.0)
    assert sent[-1].result == M.MAV_RESULT_UNSUPPORTED
    assert mode_from_set_mode(base, 6, 0) == "OFFBOARD"


def test_set_mode_message_is_acked_with_the_stacks_answer_and_an_unknown_mode_denied_at_once():
    h, sent, ops = handler()
    hold = from_gcs(M.MAVLink_set_mode_message(1, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, px4.encode("HOLD")))
    h.on_set_mode(hold, 0.0)
    assert ops.calls == [("set_mode", "HOLD")] and sent == []
    ops.dones[0](Outcome(False, "refused"))
    assert [(m.command, m.result) for m in sent] == [(M.MAVLINK_MSG_ID_SET_MODE, M.MAV_RESULT_DENIED)]
    h.on_set_mode(hold, 0.1)
    ops.dones[1](Outcome(True, "ok"))
    assert sent[-1].result == M.MAV_RESULT_ACCEPTED and sent[-1].target_system == 255
    h.on_set_mode(from_gcs(M.MAVLink_set_mode_message(1, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 99 << 16)), 0.2)
    assert len(ops.calls) == 2 and sent[-1].result == M.MAV_RESULT_DENIED
