"""Flight-mode encoding: PX4 custom_mode packing and the ArduCopter map behind one Autopilot type."""
import pytest
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.mavlink import px4
from aeroperception.services.mavlink.px4 import Autopilot


@pytest.mark.parametrize("name, value", [
    ("OFFBOARD", 6 << 16),
    ("POSCTL", 3 << 16),
    ("MANUAL", 1 << 16),
    ("STABILIZED", 7 << 16),
    ("HOLD", 4 << 16 | 3 << 24),      # AUTO.LOITER = 0x03040000
    ("TAKEOFF", 4 << 16 | 2 << 24),
    ("MISSION", 4 << 16 | 4 << 24),
    ("RTL", 4 << 16 | 5 << 24),
    ("LAND", 4 << 16 | 6 << 24),
    ("PRECLAND", 4 << 16 | 9 << 24),
])
def test_px4_encode_decode_by_hand(name, value):
    assert px4.encode(name) == value
    assert px4.decode(value) == name


def test_px4_hold_hex():
    assert px4.encode("HOLD") == 0x03040000
    assert px4.unpack(0x03040000) == (4, 3)


def test_px4_round_trip_all_names():
    for name in px4.PX4_MODES:
        assert px4.decode(px4.encode(name)) == name


def test_px4_decode_ignores_sub_for_plain_main_modes_and_flags_unknown():
    assert px4.decode(px4.pack(6, 7)) == "OFFBOARD"
    assert px4.decode(px4.pack(4, 0)) == "PX4(4.0)"
    assert px4.decode(px4.pack(99, 0)) == "PX4(99.0)"


def test_px4_encode_is_case_insensitive_and_rejects_unknown():
    assert px4.encode("offboard") == px4.encode("OFFBOARD")
    with pytest.raises(KeyError):
        px4.encode("GUIDED")


def test_autopilot_from_heartbeat():
    assert Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_PX4).name == "px4"
    assert Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA).name == "ardupilot"
    assert Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_GENERIC).name == "px4"


def test_px4_autopilot_mode_params():
    ap = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_PX4)
    assert ap.set_mode_params("HOLD") == (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), 4.0, 3.0)
    assert ap.set_mode_params("OFFBOARD")[1:] == (6.0, 0.0)
    assert ap.mode_name(ap.custom_mode("RTL")) == "RTL"
    assert ap.takeoff_param7(5.0, 488.0) == 493.0  # PX4: AMSL


def test_ardupilot_copter_map():
    ap = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert ap.custom_mode("OFFBOARD") == 4      # GUIDED
    assert ap.custom_mode("HOLD") == 5          # LOITER
    assert ap.custom_mode("RTL") == 6
    assert ap.custom_mode("LAND") == 9
    assert ap.custom_mode("STABILIZED") == 0
    assert ap.custom_mode("BRAKE") == 17
    assert ap.mode_name(4) == "OFFBOARD"
    assert ap.mode_name(5) == "HOLD"
    assert ap.mode_name(17) == "HOLD"           # BRAKE also holds position
    assert ap.mode_name(16) == "POSCTL"         # POSHOLD
    assert ap.mode_name(3) == "MISSION"         # AUTO
    assert ap.mode_name(21) == "SMART_RTL"      # no neutral equivalent: keeps its name
    assert ap.mode_name(250) == "APM(250)"
    assert ap.set_mode_params("OFFBOARD") == (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), 4.0, 0.0)
    assert ap.takeoff_param7(5.0, 488.0) == 5.0  # ArduPilot: relative
    with pytest.raises(KeyError):
        ap.custom_mode("TAKEOFF")


def test_ardupilot_round_trip_for_every_name_but_brake():
    ap = Autopilot.for_heartbeat(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    for name in ap.mode_names():
        expected = "HOLD" if name == "BRAKE" else name
        assert ap.mode_name(ap.custom_mode(name)) == expected
