"""The zenoh-cli codec (tools/zenoh_codec.py) without a router: schema by key, strict put."""
import json

import msgpack
import pytest

from aeroperception.schemas import TrajectorySetpoint, Vector3, VehicleState, decode, encode
from aeroperception.tools.zenoh_codec import decode_payload, encode_value


def test_decoder_picks_the_schema_the_contracts_declare_for_the_key_with_or_without_a_vehicle_prefix():
    raw = encode(VehicleState(position_m=Vector3(x=1.0), armed=True))
    for key in ("state/vehicle", "uav7/state/vehicle"):
        shown = json.loads(decode_payload(key, raw))
        assert shown["schema"] == "VehicleState" and shown["data"]["position_m"]["x"] == 1.0


def test_decoder_shows_undeclared_keys_as_plain_msgpack():
    shown = json.loads(decode_payload("someone/else", msgpack.packb({"a": 1})))
    assert shown == {"schema": None, "data": {"a": 1}}


def test_encoder_builds_the_declared_type_strictly():
    msg = decode(encode_value("fmu/in/trajectory_setpoint", "{yaw_valid: true, yaw_rad: 0.25}"), TrajectorySetpoint)
    assert msg.yaw_valid and msg.yaw_rad == 0.25 and msg.header.stamp_ns > 0
    with pytest.raises(SystemExit, match="yaw_rda"):
        encode_value("fmu/in/trajectory_setpoint", '{"yaw_rda": 1}')
    with pytest.raises(SystemExit, match="name the schema"):
        encode_value("nobody/declares/this", "{}")
    assert decode(encode_value("nobody/declares/this", "TrajectorySetpoint {yaw_rad: 2}"), TrajectorySetpoint).yaw_rad == 2.0


def test_service_keys_decode_replies_and_encode_requests():
    from aeroperception.schemas import MissionCommand, Reply

    shown = json.loads(decode_payload("mission/srv/command", encode(Reply(success=True, message="ok"))))
    assert shown["schema"] == "Reply" and shown["data"]["success"] is True
    assert decode(encode_value("mission/srv/command", "{command: LAND}"), MissionCommand).command == "LAND"
