"""The parameter protocol against the stack: a set goes to every owning service and the value in
force is echoed to every ground station; unknown, read-only and refused sets are explained."""
from __future__ import annotations

from gcs_support import HOME, FakeStack, Log, from_gcs
from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import ParamList, ParamSetReply
from aeroperception.schemas.system import ParamDescriptor
from aeroperception.services.gcs.mission_progress import Progress
from aeroperception.services.gcs.ops import StackOps
from aeroperception.services.gcs.param_protocol import ParamProtocol
from aeroperception.services.gcs.params import ParamTable
from aeroperception.services.gcs.telemetry import TelemetryState
from aeroperception.services.runtime import CallError

FENCE = [ParamDescriptor(name="geofence_radius_m", value=500.0, min=1.0, max=100000.0)]


class Rig:
    def __init__(self):
        self.stack, self.sent, self.notes, self.ignored = FakeStack(), [], [], []
        self.table = ParamTable(["planner", "mission", "gcs"])
        self.own = {"telemetry_period_s": 0.9}
        ops = StackOps(self.stack, 1.0, self.table, TelemetryState(HOME), Progress(), Log())
        self.proto = ParamProtocol(
            self.table, ops, "gcs",
            lambda: ParamList(params=[ParamDescriptor(name=n, value=v) for n, v in self.own.items()]),
            self.set_own, lambda m, broadcast=False: self.sent.append((m, broadcast)),
            lambda text, peer, severity: self.notes.append((text, peer)), self.ignored.append, Log())

    def set_own(self, name, value):
        self.own[name] = value
        return ParamSetReply(success=True, name=name, value=value)

    def refresh(self):
        """gcs's own parameters at once; the others answer their @params calls."""
        self.proto.refresh()
        replies = {"planner": [ParamDescriptor(name="max_velocity_mps", value=2.0, min=0.1, max=15.0)],
                   "mission": [ParamDescriptor(name="takeoff_altitude_m", value=3.0)] + FENCE,
                   "safety": FENCE}
        for key, _ in list(self.stack.calls):
            svc = key.split("/")[1]
            self.stack.answer(ParamList(params=replies[svc]) if svc in replies else CallError("no " + svc))
        self.stack.calls.clear()

    def param_set(self, name: str, value: float):
        self.sent.clear()
        self.proto.on_set(from_gcs(M.MAVLink_param_set_message(1, 1, name.encode(), value, M.MAV_PARAM_TYPE_REAL32)),
                          0.0)

    def types(self):
        return [(m.get_type(), broadcast) for m, broadcast in self.sent]


def test_refresh_reads_every_source_and_keeps_what_a_silent_service_had():
    rig = Rig()
    rig.refresh()
    assert rig.table.lookup("MPC_XY_VEL_MAX")[1].value == 2.0 and rig.table.lookup("GCS_TELEM_PERIOD") is not None
    assert rig.table.lookup("GF_MAX_HOR_DIST")[1].targets == (("mission", "geofence_radius_m"),
                                                              ("safety", "geofence_radius_m"))
    rig.proto.refresh()
    while rig.stack.replies:
        rig.stack.answer(CallError("timeout"))                       # everybody gone quiet
    assert rig.table.lookup("MPC_XY_VEL_MAX")[1].value == 2.0
    rig.sent.clear()
    rig.proto.on_request_list(from_gcs(M.MAVLink_param_request_list_message(1, 1)), 0.0)
    assert len(rig.sent) == len(rig.table) and {t for t, _ in rig.types()} == {"PARAM_VALUE"}


def test_a_set_goes_to_every_owner_and_the_value_in_force_is_echoed_to_everyone():
    rig = Rig()
    rig.refresh()
    rig.param_set("MPC_XY_VEL_MAX", 3.0)
    assert rig.stack.asked() == [("config/planner/@set", "max_velocity_mps")] and rig.sent == []
    rig.stack.answer(ParamSetReply(success=True, name="max_velocity_mps", value=3.0))
    (pv, broadcast), = rig.sent
    assert pv.param_id == "MPC_XY_VEL_MAX" and pv.param_value == 3.0 and broadcast

    rig.stack.calls.clear()
    rig.param_set("GF_MAX_HOR_DIST", 800.0)                          # mission and safety share it
    assert rig.stack.asked() == [("config/mission/@set", "geofence_radius_m"),
                                 ("config/safety/@set", "geofence_radius_m")]
    rig.stack.answer(ParamSetReply(success=True, value=800.0))
    assert rig.sent == []                                            # echoed once both answered
    rig.stack.answer(CallError("timeout calling config/safety/@set"))
    assert rig.notes[-1][0] == "GF_MAX_HOR_DIST: safety refused 800.0: timeout calling config/safety/@set"
    assert rig.types() == [("PARAM_VALUE", True)] and rig.sent[0][0].param_value == 800.0

    rig.param_set("GCS_TELEM_PERIOD", 0.5)                         # gcs's own: no call
    assert rig.own["telemetry_period_s"] == 0.5 and rig.types() == [("PARAM_VALUE", True)]


def test_unknown_and_read_only_names_are_answered_as_px4_does():
    rig = Rig()
    rig.refresh()
    rig.param_set("NOPE", 1.0)
    assert rig.notes[-1] == ("[pm] unknown param: NOPE", (255, 190)) and rig.types() == [("PARAM_ERROR", False)]
    assert rig.sent[0][0].error == M.MAV_PARAM_ERROR_DOES_NOT_EXIST and rig.ignored == ["unknown_param"]
    rig.param_set("NAV_DLL_ACT", 0.0)
    assert rig.notes[-1][0].startswith("NAV_DLL_ACT is read-only")
    assert rig.types() == [("PARAM_ERROR", False), ("PARAM_VALUE", False)] and rig.stack.calls == []
    rig.sent.clear()
    rig.proto.on_request_read(from_gcs(M.MAVLink_param_request_read_message(1, 1, b"", 99)), 0.0)
    assert rig.notes[-1][0] == "[pm] unknown param ID: 99" and rig.types() == [("PARAM_ERROR", False)]
    rig.sent.clear()
    rig.proto.on_request_read(from_gcs(M.MAVLink_param_request_read_message(1, 1, b"NOPE", -1)), 0.0)
    assert rig.types() == [("PARAM_ERROR", False)] and rig.ignored.count("unknown_param") == 3
