"""Perception coordinator logic (services/perception/logic.py): seed 000's enum mapping, the
VIO-only gate, timeouts and the on-change trigger."""
from aeroperception.schemas import DiagnosticStatus, PerceptionHealth, VioHealth
from aeroperception.services.perception.logic import Coordinator

PH = PerceptionHealth


def coord() -> Coordinator:
    return Coordinator({"vio": 3.0, "detector": 3.0, "lidar": 3.0})


def test_nothing_heard_is_unknown_and_unhealthy():
    m = coord().verdict(0.0, 1)
    assert (m.vio_status, m.detector_status, m.lidar_status, m.overall_healthy) == (PH.UNKNOWN,) * 3 + (False,)
    assert "vio UNKNOWN" in m.message


def test_vio_state_mapping_and_only_vio_gates():
    c = coord()
    c.on_detector(DiagnosticStatus(level=DiagnosticStatus.ERROR, message="model load failed"), 0.0)
    c.on_lidar(DiagnosticStatus(level=DiagnosticStatus.WARN, message="slow"), 0.0)
    expect = {VioHealth.INIT: PH.INITIALIZING, VioHealth.TRACKING: PH.HEALTHY,
              VioHealth.DEGRADED: PH.DEGRADED, VioHealth.LOST: PH.FAILED}
    for state, status in expect.items():
        c.on_vio(VioHealth(state=state, message="x"), 0.0)
        m = c.verdict(0.1, 1)
        assert m.vio_status == status
        assert m.overall_healthy == (state == VioHealth.TRACKING)
        assert m.detector_status == PH.FAILED and m.lidar_status == PH.DEGRADED
    assert "model load failed" in m.message


def test_silent_vio_times_out_to_unknown():
    c = coord()
    c.on_vio(VioHealth(state=VioHealth.TRACKING), 0.0)
    assert c.verdict(2.9, 1).overall_healthy
    m = c.verdict(3.1, 1)
    assert m.vio_status == PH.UNKNOWN and not m.overall_healthy and "silent" in m.message


def test_stale_diagnostics_are_unknown_and_changes_are_detected_once():
    c = coord()
    c.on_lidar(DiagnosticStatus(level=DiagnosticStatus.STALE), 0.0)
    m = c.verdict(0.0, 1)
    assert m.lidar_status == PH.UNKNOWN
    assert c.changed(m) and not c.changed(c.verdict(0.1, 1))
    c.on_vio(VioHealth(state=VioHealth.TRACKING), 0.2)
    assert c.changed(c.verdict(0.2, 1))
