"""The UDP link: garbage counted and dropped, ground stations learnt, telemetry to every live one
and replies to the asker, MAVLink 2 signing."""
from __future__ import annotations

import os
import socket
import struct
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")   # mavutil picks the MAVLink 2 dialect (signing needs it)
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as M  # noqa: E402

from gcs_support import GCS, HOME, drain, poll, types, udp_peer  # noqa: E402

from aeroperception.services.gcs.link import (  # noqa: E402
    Parser, UdpLink, load_signing_key, make_mav, parse_signing_key, signing_timestamp,
)
from aeroperception.services.gcs.messages import statustext  # noqa: E402
from aeroperception.services.gcs.telemetry import TelemetryState  # noqa: E402


def test_garbage_bad_crc_and_unknown_ids_are_counted():
    p = Parser()
    good = M.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(GCS)
    bad = bytearray(good)
    bad[-1] ^= 0xFF
    assert p.feed(b"\x00\xff garbage \xfd\x01") == []
    assert p.feed(bytes(bad)) == []
    assert p.feed(bytes(range(256))) == []
    assert p.feed(bytes(good[:7])) == []           # truncated frame
    unknown = bytearray(good)
    unknown[7:10] = (60000).to_bytes(3, "little")  # a message id nobody defines
    assert p.feed(bytes(unknown)) == []
    invalid = p.invalid_total
    assert invalid >= 4
    msgs = p.feed(good)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT"] and p.invalid_total == invalid
    for chunk in (b"", b"\xfd", b"\xfe" * 300, bytes(1000)):
        p.feed(chunk)   # never raises


def test_udp_link_learns_the_ground_station_address():
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", 9, 1, 1)
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.settimeout(2.0)
    try:
        got = []
        link.start(got.append)
        gcs.sendto(M.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(GCS), link.local_address)
        deadline = time.monotonic() + 2.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got and link.remote == gcs.getsockname()
        link.send(TelemetryState(HOME).heartbeat())
        data, _ = gcs.recvfrom(1000)
        (hb,) = Parser().feed(data)
        assert hb.get_type() == "HEARTBEAT" and hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    finally:
        link.close()
        gcs.close()


class FakeClock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_several_ground_stations_telemetry_to_all_alive_replies_to_the_asker():
    clock = FakeClock()
    initial, a, b = udp_peer(), udp_peer(), udp_peer()
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", initial.getsockname()[1], 1, 1, timeout_s=3.0, clock=clock)
    mav_a, mav_b = make_mav(255, 190), make_mav(246, 190)
    hb_gcs = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 4)
    hb = TelemetryState(HOME).heartbeat()

    def on_message(m):
        if m.get_type() == "PARAM_REQUEST_READ":   # answered at once, as gcs does: to the asker only
            link.send(M.MAVLink_param_value_message(b"GCS_X", 1.0, M.MAV_PARAM_TYPE_REAL32, 1, 0))

    def hb_from(sock, mav):
        n = link.parser.received
        sock.sendto(hb_gcs.pack(mav), link.local_address)
        poll(lambda: link.parser.received > n)

    try:
        link.start(on_message)
        link.send(hb)                                  # nobody heard yet: the initial address
        assert types(drain(initial, until=1)) == ["HEARTBEAT"]
        assert link.destinations() == [initial.getsockname()] and not link.alive()

        hb_from(a, mav_a)                              # A talks: telemetry to A, and still to the
        link.send(hb)                                  # initial address (a listen-only station)
        assert types(drain(a, until=1)) == ["HEARTBEAT"] and types(drain(initial, until=1)) == ["HEARTBEAT"]
        hb_from(b, mav_b)                              # B too: telemetry to both
        assert {p.address for p in link.alive()} == {a.getsockname(), b.getsockname()}
        link.send(hb)
        assert types(drain(a, until=1)) == ["HEARTBEAT"] and types(drain(b, until=1)) == ["HEARTBEAT"]
        assert types(drain(initial, until=1)) == ["HEARTBEAT"]

        # B asks: only B gets the answer
        b.sendto(M.MAVLink_param_request_read_message(1, 1, b"GCS_X", -1).pack(mav_b), link.local_address)
        assert types(drain(b, until=1)) == ["PARAM_VALUE"] and drain(a, 0.1) == [] and drain(initial, 0.1) == []
        # a later reply with a target goes where that target spoke from
        link.send(M.MAVLink_command_ack_message(M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 255, 190))
        assert types(drain(a, until=1)) == ["COMMAND_ACK"] and drain(b, 0.1) == []
        link.send(M.MAVLink_mission_ack_message(246, 0, 0, 0))         # target_component 0: that system
        assert types(drain(b, until=1)) == ["MISSION_ACK"] and drain(a, 0.1) == []
        for m in statustext(M.MAV_SEVERITY_CRITICAL, "to B"):           # explicit peer
            link.send(m, peer=(246, 190))
        assert types(drain(b, until=1)) == ["STATUSTEXT"] and drain(a, 0.1) == []
        link.send(M.MAVLink_param_value_message(b"GCS_X", 2.0, M.MAV_PARAM_TYPE_REAL32, 1, 0), broadcast=True)
        assert types(drain(a, until=1)) == ["PARAM_VALUE"] and types(drain(b, until=1)) == ["PARAM_VALUE"]
        assert types(drain(initial, until=1)) == ["PARAM_VALUE"]

        # A goes silent: after the timeout only B (still beating) gets telemetry
        clock.t += 2.0
        hb_from(b, mav_b)
        clock.t += 1.5                                 # A's heartbeat 3.5 s old, B's 1.5 s
        assert [p.address for p in link.alive()] == [b.getsockname()]
        link.send(hb)
        assert types(drain(b, until=1)) == ["HEARTBEAT"] and drain(a, 0.1) == []
        assert types(drain(initial, until=1)) == ["HEARTBEAT"]
        # nobody left: the initial address and the last ground station heard
        clock.t += 10.0
        assert not link.alive() and link.destinations() == [initial.getsockname(), b.getsockname()]
        link.send(hb)
        assert types(drain(initial, until=1)) == ["HEARTBEAT"] and types(drain(b, until=1)) == ["HEARTBEAT"]
        assert drain(a, 0.1) == []
    finally:
        link.close()
        for s in (initial, a, b):
            s.close()


KEY = bytes(range(1, 33))
OTHER_KEY = bytes(32)


def test_signing_key_from_hex_raw_bytes_or_file(tmp_path):
    assert parse_signing_key(KEY.hex()) == KEY
    assert parse_signing_key(f"  {KEY.hex().upper()}\n") == KEY
    assert parse_signing_key(KEY) == KEY
    for bad in ("abc", "zz" * 32, KEY.hex()[:-2], KEY[:31], KEY.hex() + "00"):
        with pytest.raises(ValueError) as e:
            parse_signing_key(bad)
        assert KEY.hex()[:8] not in str(e.value) and "zz" not in str(e.value)   # never echoes the key
    f = tmp_path / "gcs.key"
    f.write_text(KEY.hex() + "\n")
    f.chmod(0o600)
    assert load_signing_key(f) == (KEY, False)
    f.chmod(0o644)
    assert load_signing_key(f) == (KEY, True)                 # readable by others: gcs warns
    with pytest.raises(ValueError, match="signing key file"):
        load_signing_key(tmp_path / "missing.key")


def ground_station(port: int, system_id: int, key: bytes | None = None, link_id: int = 0):
    """A pymavlink ground station (mavutil), signing with `key` if given."""
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=system_id, source_component=190,
                                      dialect="common")
    if key is not None:
        conn.setup_signing(key, sign_outgoing=True, link_id=link_id)
    return conn


def recv_type(conn, mtype: str, timeout_s: float = 2.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = conn.recv_match(type=mtype, blocking=True, timeout=0.05)
        if m is not None:
            return m
    return None


def signed_frame(msg, system_id: int, key: bytes, link_id: int, timestamp: int) -> bytes:
    mav = make_mav(system_id, 190)
    mav.signing.secret_key, mav.signing.sign_outgoing = key, True
    mav.signing.link_id, mav.signing.timestamp = link_id, timestamp
    return msg.pack(mav)


def test_signing_signed_ground_station_works_unsigned_and_wrongly_signed_are_dropped_and_counted():
    link = UdpLink("127.0.0.1", 0, "127.0.0.1", 9, 1, 1, signing_key=KEY, signing_link_id=7)
    port = link.local_address[1]
    got = []

    def on_message(m):
        got.append((m.get_srcSystem(), m.get_type()))
        if m.get_type() == "PARAM_REQUEST_READ":
            link.send(M.MAVLink_param_value_message(b"GCS_X", 1.0, M.MAV_PARAM_TYPE_REAL32, 1, 0))

    good = ground_station(port, 255, KEY)
    plain = ground_station(port, 254)
    wrong = ground_station(port, 253, OTHER_KEY)
    raw = udp_peer()
    hb_gcs = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 4)
    try:
        link.start(on_message)
        for c in (good, plain, wrong):
            c.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            c.mav.param_request_read_send(1, 1, b"GCS_X", -1)
        poll(lambda: len(got) >= 2 and link.parser.invalid["unsigned"] >= 2
             and link.parser.invalid["bad_signature"] >= 2)
        assert got == [(255, "HEARTBEAT"), (255, "PARAM_REQUEST_READ")]
        assert [p.system_id for p in link.alive()] == [255]

        # the signed ground station gets its answer, signed with our link id and a current timestamp
        # (its pymavlink, holding the key, would drop anything unsigned or wrongly signed)
        pv = recv_type(good, "PARAM_VALUE")
        assert pv is not None and pv._signed and pv._link_id == 7
        tlow, thigh = struct.unpack("<IH", bytes(pv.get_msgbuf())[-12:-6])
        assert abs((tlow + (thigh << 32)) - signing_timestamp()) < 5 * 100_000
        assert good.mav.signing.goodsig_count >= 1 and good.mav.signing.badsig_count == 0
        link.send(TelemetryState(HOME).heartbeat())             # telemetry: to the signed one only
        assert recv_type(good, "HEARTBEAT") is not None
        assert plain.recv_match(blocking=True, timeout=0.3) is None
        assert wrong.recv_match(blocking=True, timeout=0.1) is None

        # replay protection: a signed frame is accepted once; a copy, or a new stream from long
        # ago, is refused
        now = signing_timestamp()
        frame = signed_frame(hb_gcs, 252, KEY, 3, now)
        for _ in range(2):
            raw.sendto(frame, link.local_address)
        raw.sendto(signed_frame(hb_gcs, 251, KEY, 3, now - 120 * 100_000), link.local_address)
        poll(lambda: link.parser.invalid["replayed"] == 1 and link.parser.invalid["stale_timestamp"] == 1)
        assert got[-1] == (252, "HEARTBEAT") and got.count((252, "HEARTBEAT")) == 1

        # a wrongly signed frame with a far-future timestamp on the good station's stream does not
        # lock it out (pymavlink alone would record that timestamp before checking the signature)
        raw.sendto(signed_frame(hb_gcs, 255, OTHER_KEY, 0, now + 3600 * 100_000), link.local_address)
        poll(lambda: link.parser.invalid["bad_signature"] >= 3)
        n = len(got)
        good.mav.param_request_read_send(1, 1, b"GCS_X", -1)
        poll(lambda: len(got) > n)
        assert got[-1] == (255, "PARAM_REQUEST_READ")
        assert link.parser.signing_rejected == link.parser.invalid_total >= 7
    finally:
        link.close()
        for c in (good, plain, wrong):
            c.close()
        raw.close()
