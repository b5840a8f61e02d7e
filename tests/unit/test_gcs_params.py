"""The parameter table: 16-character names, byte-wise values, PX4 names for the services'
parameters."""
from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas.system import ParamDescriptor
from aeroperception.services.gcs.params import ParamTable, decode_value, mavlink_name
from aeroperception.services.mavlink.param_value import encode_value


def test_param_names_fit_16_chars_are_stable_and_unique():
    assert mavlink_name("planner", "max_velocity_mps") == "PLN_MAX_VELOCITY"
    assert mavlink_name("planner", "kp") == "PLN_KP"
    assert mavlink_name("mission", "takeoff_altitude_m").startswith("MIS_TAKEO")
    t = ParamTable(["planner", "mission"], aliases=())
    t.update_service("planner", [ParamDescriptor(name=n, value=1.0, type="float") for n in
                                 ("max_velocity_mps", "max_velocity_mps2", "acceptance_radius_m", "kp")]
                     + [ParamDescriptor(name="mode", value="x", type="str"),
                        ParamDescriptor(name="count", value=3, type="int"),
                        ParamDescriptor(name="enabled", value=True, type="bool")])
    names = [e.mav_name for e in t.entries]
    assert all(len(n) <= 16 for n in names) and len(set(names)) == len(names) == 6   # string not exposed
    idx, e = t.lookup("PLN_KP")
    assert t.lookup(index=idx)[1] is e and t.lookup("NOPE") is None and t.lookup(index=99) is None
    msg = t.value_msg(idx, e)
    assert msg.param_count == 6 and msg.param_index == idx


def test_param_values_bytewise():
    assert decode_value(encode_value(7, M.MAV_PARAM_TYPE_INT32), M.MAV_PARAM_TYPE_INT32, M.MAV_PARAM_TYPE_INT32) == 7
    assert decode_value(encode_value(True, M.MAV_PARAM_TYPE_UINT8), M.MAV_PARAM_TYPE_UINT8, M.MAV_PARAM_TYPE_UINT8) is True
    assert struct.pack("<f", encode_value(-3, M.MAV_PARAM_TYPE_INT32)) == struct.pack("<i", -3)
    assert decode_value(2.5, M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_REAL32) == 2.5
    assert decode_value(5.0, M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_INT32) == 5   # cast-encoded
    # a float32 on the wire reaches the service as the decimal the operator typed
    f32 = struct.unpack("<f", struct.pack("<f", 1.1))[0]
    assert f32 != 1.1 and decode_value(f32, M.MAV_PARAM_TYPE_REAL32, M.MAV_PARAM_TYPE_REAL32) == 1.1
    assert decode_value(struct.unpack("<f", struct.pack("<f", -0.3))[0], M.MAV_PARAM_TYPE_REAL32,
                        M.MAV_PARAM_TYPE_REAL32) == -0.3


def test_px4_names_map_to_the_owning_services_parameters():
    """PX4 names read the services' live values, exist only while an owner answers,
    and a geofence name covers both mission and safety; fixed answers are read-only."""
    from aeroperception.services.gcs.params import ALIAS_SERVICE
    t = ParamTable(["planner", "mission", "gcs"])
    assert {"sim", "safety"} <= set(t.sources)            # read for their aliases, not exposed natively
    names = lambda: {e.mav_name for e in t.entries}       # noqa: E731
    assert names() == {"COM_RC_IN_MODE", "NAV_DLL_ACT"}   # constants only, nobody answered yet
    t.update_service("mission", [ParamDescriptor(name="takeoff_altitude_m", value=3.0, min=0.5, max=120.0)])
    t.update_service("planner", [ParamDescriptor(name="max_velocity_mps", value=2.0, default=2.0, min=0.1, max=15.0),
                                 ParamDescriptor(name="acceptance_radius_m", value=0.5)])
    assert {"MIS_TAKEOFF_ALT", "MPC_XY_VEL_MAX", "NAV_ACC_RAD"} <= names()
    assert "GF_MAX_HOR_DIST" not in names() and "GF_ACTION" not in names() and "RTL_RETURN_ALT" not in names()
    _, e = t.lookup("MPC_XY_VEL_MAX")
    assert (e.service, e.value, e.min, e.max, e.targets) == (ALIAS_SERVICE, 2.0, 0.1, 15.0, (("planner", "max_velocity_mps"),))
    t.set_value("planner", "max_velocity_mps", 3.5)        # a confirmed set: native and alias agree
    assert t.lookup("MPC_XY_VEL_MAX")[1].value == 3.5 and t.find("planner", "max_velocity_mps")[1].value == 3.5

    fence = [ParamDescriptor(name="geofence_radius_m", value=500.0, min=1.0, max=100000.0),
             ParamDescriptor(name="geofence_max_altitude_m", value=120.0, min=1.0, max=10000.0)]
    t.update_service("safety", fence + [ParamDescriptor(name="geofence_action", value=2, type="int")])
    _, gf = t.lookup("GF_MAX_HOR_DIST")
    assert gf.targets == (("safety", "geofence_radius_m"),) and gf.value == 500.0
    t.update_service("mission", [ParamDescriptor(name="takeoff_altitude_m", value=3.0)] + fence)
    assert t.lookup("GF_MAX_HOR_DIST")[1].targets == (("mission", "geofence_radius_m"), ("safety", "geofence_radius_m"))
    _, act = t.lookup("GF_ACTION")
    assert act.ptype == M.MAV_PARAM_TYPE_INT32 and act.value == 2
    t.update_service("sim", [ParamDescriptor(name="RTL_RETURN_ALT", value=60.0)])
    assert t.lookup("RTL_RETURN_ALT")[1].value == 60.0
    _, dll = t.lookup("NAV_DLL_ACT")
    assert dll.value == 1 and dll.readonly and t.lookup("COM_RC_IN_MODE")[1].value == 4
    assert not any(e.service == "sim" for e in t.entries)  # the sim's own names are not exposed
    idx, e = t.lookup("MIS_TAKEOFF_ALT")
    assert t.value_msg(idx, e).param_id == "MIS_TAKEOFF_ALT" and t.lookup(index=idx)[1] is e
