"""Perception coordinator logic (services/perception/logic.py): requirement PERC-1's enum mapping, the
VIO-only gate, timeouts and the on-change trigger."""
import pytest

from aeroperception.schemas import DiagnosticStatus, PerceptionHealth, VioHealth
from aeroperception.services.perception.logic import Coordinator, parse_sources

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


def test_a_source_the_stack_does_not_run_is_not_configured_not_broken():
    """`aero up --sensors camera`: no LiDAR service. Its status is NOT_CONFIGURED (never DEGRADED or
    UNKNOWN for ever), and a stack without VIO (--sensors lidar) has nothing to gate on."""
    c = Coordinator({"vio": 3.0, "detector": 3.0, "lidar": 3.0}, parse_sources("vio,detector"))
    c.on_vio(VioHealth(state=VioHealth.TRACKING), 0.0)
    c.on_detector(DiagnosticStatus(level=DiagnosticStatus.OK), 0.0)
    m = c.verdict(2.0, 1)
    assert (m.vio_status, m.detector_status, m.lidar_status) == (PH.HEALTHY, PH.HEALTHY, PH.NOT_CONFIGURED)
    assert m.overall_healthy and "lidar NOT_CONFIGURED" in m.message and "(" not in m.message
    lidar_only = Coordinator({"vio": 3.0, "detector": 3.0, "lidar": 3.0}, parse_sources("lidar"))
    lidar_only.on_lidar(DiagnosticStatus(level=DiagnosticStatus.OK), 0.0)
    m = lidar_only.verdict(0.5, 1)
    assert (m.vio_status, m.detector_status, m.lidar_status) == (PH.NOT_CONFIGURED, PH.NOT_CONFIGURED, PH.HEALTHY)
    assert m.overall_healthy


def test_unknown_sources_are_refused_naming_them():
    with pytest.raises(ValueError, match="unknown radar; known: vio, detector, lidar"):
        parse_sources("vio,radar")
    assert parse_sources("") == frozenset()


def test_the_config_comes_from_the_parameters_and_a_bad_source_changes_nothing():
    from aeroperception.services.perception import contract
    from aeroperception.services.perception.logic import CoordinatorConfig
    from aeroperception.services.runtime.config import build

    c = Coordinator.from_config(build(CoordinatorConfig, contract.PARAMS))
    assert c.sources == frozenset(("vio", "detector", "lidar")) and c.timeouts_s == {"vio": 3.0, "detector": 3.0, "lidar": 3.0}
    c.configure(build(CoordinatorConfig, contract.PARAMS, sources="vio", lidar_timeout_s=5.0))
    assert c.sources == frozenset(("vio",)) and c.timeouts_s["lidar"] == 5.0
    with pytest.raises(ValueError, match="unknown radar"):
        c.configure(build(CoordinatorConfig, contract.PARAMS, sources="radar", vio_timeout_s=9.0))
    assert c.sources == frozenset(("vio",)) and c.timeouts_s["vio"] == 3.0
