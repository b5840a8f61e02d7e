"""The mission protocol with pymavlink message objects: upload, download, refusals, retries,
the plan id, one upload at a time between ground stations."""
from __future__ import annotations

import pytest
from gcs_support import HOME, Loader, from_gcs, from_mav, item_int, proto, square, upload
from pymavlink.dialects.v20 import common as M

from aeroperception.services.gcs.link import make_mav
from aeroperception.services.gcs.messages import extension_fields
from aeroperception.services.gcs.mission_items import plan_id
from aeroperception.services.gcs.telemetry import TelemetryState


def test_upload_requests_each_item_then_acks_and_download_returns_it():
    loader = Loader()
    p, sent = proto(loader)
    ack = upload(p, sent, square())
    assert ack.get_type() == "MISSION_ACK" and ack.type == M.MAV_MISSION_ACCEPTED
    assert len(loader.calls) == 1 and len(p.items) == 4
    sent.clear()
    p.handle(from_gcs(M.MAVLink_mission_request_list_message(1, 1, 0)), 1.0)
    assert sent[-1].get_type() == "MISSION_COUNT" and sent[-1].count == 4
    for i in range(4):
        p.handle(from_gcs(M.MAVLink_mission_request_int_message(1, 1, i, 0)), 1.0)
        it = sent[-1]
        assert it.get_type() == "MISSION_ITEM_INT" and it.seq == i
        assert it.x == int(round(square()[i][0] * 1e7)) and it.z == pytest.approx(5.0)
    p.handle(from_gcs(M.MAVLink_mission_ack_message(1, 1, 0, 0)), 1.0)
    assert p.transfer is None


def test_rejected_upload_keeps_previous_mission():
    p, sent = proto(Loader(accept=True))
    upload(p, sent, square())
    p.load = Loader(accept=False)
    ack = upload(p, sent, square(2))
    assert ack.type == M.MAV_MISSION_DENIED
    assert len(p.items) == 4


def test_ack_waits_for_asynchronous_load():
    loader = Loader(sync=False)
    p, sent = proto(loader)
    upload(p, sent, square(1))
    assert sent[-1].get_type() == "MISSION_ITEM_INT" or sent[-1].get_type() == "MISSION_REQUEST_INT"
    assert loader.pending is not None and p.loading
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 1, 0)), 0.0)   # busy meanwhile
    assert sent[-1].type == M.MAV_MISSION_DENIED
    loader.pending(True, "ok", 0)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_ACCEPTED


def test_rerequest_on_timeout_then_give_up():
    p, sent = proto(item_timeout_s=0.1, retries=2)
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 2, 0)), 0.0)
    assert len(sent) == 1
    p.tick(0.05)
    assert len(sent) == 1
    p.tick(0.15)
    assert len(sent) == 2 and sent[-1].seq == 0
    p.tick(0.30)
    p.tick(0.45)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_OPERATION_CANCELLED
    assert p.transfer is None and p.errors["upload_timeout"] == 1


def test_out_of_order_items_and_absurd_count_are_counted_not_fatal():
    p, sent = proto(max_items=100)
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 60000, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_NO_SPACE
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 3, 0)), 0.0)
    lat, lon, alt = square()[0]
    p.handle(item_int(2, lat, lon, alt), 0.0)            # ahead: re-request seq 0
    assert sent[-1].get_type() == "MISSION_REQUEST_INT" and sent[-1].seq == 0
    p.handle(item_int(0, lat, lon, alt), 0.0)
    p.handle(item_int(0, lat, lon, alt), 0.0)            # duplicate: ignored
    assert sent[-1].seq == 1
    p.handle(item_int(7, lat, lon, alt), 0.0)
    assert p.errors["item_out_of_order"] == 3
    p.handle(from_gcs(M.MAVLink_mission_request_int_message(1, 1, 99, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_INVALID_SEQUENCE


def test_legacy_mission_item_and_request_accepted():
    p, sent = proto()
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 1, 0)), 0.0)
    lat, lon, alt = square()[1]
    p.handle(from_gcs(M.MAVLink_mission_item_message(1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                                                     M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, lat, lon, alt, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_ACCEPTED
    p.handle(from_gcs(M.MAVLink_mission_request_message(1, 1, 0, 0)), 0.0)
    assert sent[-1].get_type() == "MISSION_ITEM" and sent[-1].x == pytest.approx(lat)


def test_clear_all_and_fence_rally_are_empty():
    p, sent = proto()
    upload(p, sent, square())
    p.handle(from_gcs(M.MAVLink_mission_request_list_message(1, 1, M.MAV_MISSION_TYPE_FENCE)), 0.0)
    assert sent[-1].count == 0 and sent[-1].mission_type == M.MAV_MISSION_TYPE_FENCE
    p.handle(from_gcs(M.MAVLink_mission_clear_all_message(1, 1, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_ACCEPTED and p.items == []


def test_plan_id_in_mission_current_ack_and_count():
    p, sent = proto()
    assert p.plan_id == 0 and plan_id([]) == 0
    ack = upload(p, sent, square())
    pid = p.plan_id
    assert pid != 0 and ack.opaque_id == pid
    mav = make_mav(1, 1)
    assert extension_fields(from_mav(mav, ack))["opaque_id"] == pid      # as a ground station parses it
    p.handle(from_gcs(M.MAVLink_mission_request_list_message(1, 1, 0)), 1.0)
    count = from_mav(mav, sent[-1])
    assert count.count == 4 and extension_fields(count)["opaque_id"] == pid
    p.handle(from_gcs(M.MAVLink_mission_ack_message(1, 1, 0, 0)), 1.0)

    tel = TelemetryState(HOME, mission_seq=2, mission_total=4, mission_id=pid)
    mc = from_mav(mav, tel.mission_current())
    assert (mc.seq, mc.total) == (2, 4)                                   # stock pymavlink still reads it
    assert extension_fields(mc) == {"seq": 2, "total": 4, "mission_state": M.MISSION_STATE_NOT_STARTED,
                                    "mission_mode": 0, "mission_id": pid, "fence_id": 0, "rally_points_id": 0}
    assert extension_fields(from_mav(mav, TelemetryState(HOME).mission_current()))["mission_id"] == 0

    upload(p, sent, square())                 # the same plan again: the same id
    assert p.plan_id == pid
    upload(p, sent, square(alt=6.0))          # another plan: another id
    assert p.plan_id not in (0, pid)
    p.handle(from_gcs(M.MAVLink_mission_clear_all_message(1, 1, 0)), 2.0)
    assert p.plan_id == 0


def test_one_upload_at_a_time_between_ground_stations():
    other = make_mav(246, 190)
    p, sent = proto()
    pts = square(2)
    p.handle(from_gcs(M.MAVLink_mission_count_message(1, 1, 2, 0)), 0.0)
    assert sent[-1].get_type() == "MISSION_REQUEST_INT" and sent[-1].target_system == 255
    n = len(sent)
    # another ground station meanwhile: its upload, download and clear are refused, its items ignored
    p.handle(from_mav(other, M.MAVLink_mission_count_message(1, 1, 1, 0)), 0.0)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_DENIED
    assert sent[-1].target_system == 246
    p.handle(from_mav(other, M.MAVLink_mission_request_list_message(1, 1, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_DENIED and sent[-1].target_system == 246
    p.handle(from_mav(other, M.MAVLink_mission_clear_all_message(1, 1, 0)), 0.0)
    assert sent[-1].type == M.MAV_MISSION_DENIED
    lat, lon, alt = pts[0]
    p.handle(from_mav(other, M.MAVLink_mission_item_int_message(
        1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
        int(lat * 1e7), int(lon * 1e7), alt, 0)), 0.0)
    p.handle(from_mav(other, M.MAVLink_mission_ack_message(1, 1, M.MAV_MISSION_OPERATION_CANCELLED, 0)), 0.0)
    assert p.errors["busy"] == 3 and p.errors["item_from_other_peer"] == 1
    assert p.transfer is not None and p.transfer.expected == 0 and len(sent) == n + 3
    # the first one finishes its upload undisturbed; then the other may download it
    for i, (lat, lon, alt) in enumerate(pts):
        p.handle(item_int(i, lat, lon, alt), 0.1)
    assert sent[-1].get_type() == "MISSION_ACK" and sent[-1].type == M.MAV_MISSION_ACCEPTED and len(p.items) == 2
    p.handle(from_mav(other, M.MAVLink_mission_request_list_message(1, 1, 0)), 0.2)
    assert sent[-1].get_type() == "MISSION_COUNT" and sent[-1].count == 2 and sent[-1].target_system == 246
