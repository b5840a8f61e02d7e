"""`aero doctor`'s checks, each against a real condition made here: a port this test binds on
127.0.0.1, a module made unimportable (sys.modules[name] = None, what find_spec then reports),
a PX4 build dir in tmp_path with and without bin/px4, a real Zenoh router."""
from __future__ import annotations

import re
import socket
import stat
import sys

import pytest

from aeroperception.tools.cli import doctor
from aeroperception.tools.cli import px4_sitl
from aeroperception.tools.cli import up as cmd_up
from aeroperception.tools.common import CliError

LINE = re.compile(r"^(ok  |warn|FAIL)  \S.*$")


@pytest.mark.parametrize("kind, proto", [(socket.SOCK_STREAM, "tcp"), (socket.SOCK_DGRAM, "udp")])
def test_a_port_bound_here_is_reported_in_use_and_free_once_closed(kind, proto):
    s = socket.socket(socket.AF_INET, kind)
    s.bind(("127.0.0.1", 0))
    if kind == socket.SOCK_STREAM:
        s.listen(1)
    port = s.getsockname()[1]
    use = doctor.PortUse(proto, "127.0.0.1", port, "test")
    try:
        busy = doctor.check_port(use)
        assert busy.status == doctor.FAIL and f"{proto} 127.0.0.1:{port}" in busy.what and "in use" in busy.what
        assert f":{port}" in busy.todo
        # a port someone else's peer binds (the ground station's) is only reported
        assert doctor.check_port(doctor.PortUse(proto, "127.0.0.1", port, "gs", bind=False)).status == doctor.OK
    finally:
        s.close()
    assert doctor.check_port(use).status == doctor.OK


def test_a_missing_module_is_a_fail_naming_it_and_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "gtsam", None)     # `import gtsam` now fails; find_spec says None
    c = doctor.check_service("vio", "deploy/install.sh sim,perception,tools")
    assert c.status == doctor.FAIL and c.what == "vio: not installed: gtsam", c
    assert c.todo == "deploy/install.sh sim,perception,tools"
    assert c.line() == "FAIL  vio: not installed: gtsam -> deploy/install.sh sim,perception,tools"
    ok = doctor.check_service("fmu", "unused")
    assert ok.status == doctor.OK and "pymavlink" in ok.what


def fake_px4(root, with_binary: bool):
    (root / "etc" / "init.d-posix").mkdir(parents=True)
    (root / "etc" / "init.d-posix" / "rcS").write_text("#!/bin/sh\n")
    if with_binary:
        (root / "bin").mkdir()
        px4 = root / "bin" / "px4"
        px4.write_text("#!/bin/sh\n")
        px4.chmod(px4.stat().st_mode | stat.S_IXUSR)
    return root


def test_px4_dir_with_and_without_bin_px4(tmp_path, monkeypatch):
    monkeypatch.delenv(px4_sitl.DIR_ENV, raising=False)
    good = fake_px4(tmp_path / "good", with_binary=True)
    bad = fake_px4(tmp_path / "bad", with_binary=False)
    assert doctor.check_px4(str(good), required=True).status == doctor.OK
    assert doctor.check_px4(str(bad), required=False).status == doctor.WARN       # sim: only a warning
    c = doctor.check_px4(str(bad), required=True)                                  # px4 profile: it cannot start
    assert c.status == doctor.FAIL and "bin/px4" in c.what, c
    monkeypatch.setenv(px4_sitl.DIR_ENV, str(good))
    assert doctor.check_px4(None, required=True).status == doctor.OK


def test_px4_bundle_beside_the_repo_is_pointed_at(tmp_path, monkeypatch):
    """../shared/px4 holds the tests' tarball, not a build: the line says how to extract it."""
    monkeypatch.delenv(px4_sitl.DIR_ENV, raising=False)
    (tmp_path / "px4-sitl-sih.tar.gz").write_bytes(b"")
    monkeypatch.setattr(doctor, "shared_px4_dir", lambda: tmp_path)
    c = doctor.check_px4(None, required=False)
    assert c.status == doctor.WARN and "px4-sitl-sih.tar.gz" in c.what
    assert c.todo.startswith("extract it: mkdir -p DIR && tar -xzf") and px4_sitl.DIR_ENV in c.todo
    fake_px4(tmp_path, with_binary=True)
    assert doctor.check_px4(None, required=True).status == doctor.OK


def test_profile_ports_come_from_where_aero_up_takes_them():
    from aeroperception.services.fmu.contract import DEFAULT_FCU_URL
    from aeroperception.services.gcs.contract import DEFAULT_LOCAL_PORT, DEFAULT_REMOTE_PORT
    from aeroperception.services.sim.vehicle.endpoint import PX4_SITL_BIND

    sim = {(u.proto, u.port): u for u in doctor.profile_ports("sim")}
    router = doctor.parse_endpoint(cmd_up.DEFAULT_LISTEN)
    assert (router[0], router[2]) in sim and router[2] == 7447
    assert ("udp", int(DEFAULT_FCU_URL.rsplit(":", 1)[1])) in sim and ("udp", PX4_SITL_BIND[1]) in sim
    assert sim[("udp", DEFAULT_LOCAL_PORT)].bind and not sim[("udp", DEFAULT_REMOTE_PORT)].bind
    px4 = {u.port for u in doctor.profile_ports("px4")}
    assert set(px4_sitl.Ports(0).bound_by_px4) <= px4 and px4_sitl.Ports(0).fmu in px4
    viz = {u.port for u in doctor.profile_ports("viz", "tcp/127.0.0.1:7500")}
    assert {7500, 9090, 9876} <= viz and 7447 not in viz
    assert doctor._flag_params(["--param", "local_port=1", "--param=bind_ip=127.0.0.1", "--follow"]) == {
        "local_port": "1", "bind_ip": "127.0.0.1"}
    with pytest.raises(CliError, match="expected tcp:PORT or udp:PORT"):
        doctor.parse_port("sctp:1")


def test_router_absent_then_present(zenoh_router):
    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    assert "none at" in doctor.check_router(f"tcp/127.0.0.1:{port}").what
    c = doctor.check_router(zenoh_router)
    assert c.status == doctor.OK and "a Zenoh router answers" in c.what, c


def test_clock_checks(monkeypatch, tmp_path):
    good = doctor.check_clock(ntp=(True, "timedatectl"))
    assert [c.status for c in good] == [doctor.OK] * 3, good
    old = doctor.check_clock(now_s=0.0, ntp=(False, "chronyc"))
    assert old[1].status == doctor.WARN and "1970-01-01" in old[1].what
    assert old[2].status == doctor.WARN and "not synchronised" in old[2].what
    monkeypatch.setenv("PATH", str(tmp_path))    # neither timedatectl nor chronyc: unknown, a warning
    assert doctor.ntp_synchronised()[0] is None
    assert doctor.check_clock()[2].status == doctor.WARN


def test_docker_and_gpu_are_never_a_fail(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))
    assert doctor.check_docker().status == doctor.WARN
    assert doctor.gpu_names() == [] and doctor.check_gpu([]).status == doctor.OK


def test_onnx_providers_line():
    pytest.importorskip("onnxruntime")
    c = doctor.check_onnx(gpu=False)
    assert c.status == doctor.OK and "CPU yes" in c.what and "CUDA" in c.what and "TensorRT" in c.what


def test_every_line_has_a_status_and_a_px4_profile_without_px4_fails(monkeypatch, tmp_path):
    monkeypatch.delenv(px4_sitl.DIR_ENV, raising=False)
    monkeypatch.setattr(doctor, "shared_px4_dir", lambda: tmp_path)
    found = doctor.checks("px4", ports=[])
    assert all(LINE.match(c.line()) for c in found), [c.line() for c in found]
    px4 = [c for c in found if c.what.startswith("PX4:")]
    assert len(px4) == 1 and px4[0].status == doctor.FAIL
    assert not any(c.what.startswith("px4:") for c in found)     # PX4 itself has no Python imports to check


def test_a_missing_optional_import_is_a_warning(monkeypatch):
    monkeypatch.setitem(sys.modules, "cv2", None)
    c = doctor.check_service("viz", "deploy/install.sh x")
    assert c.status == doctor.WARN and "optional cv2" in c.what and "raw pixels" in c.what, c
    assert doctor.check_service("vio", "deploy/install.sh x").status == doctor.FAIL    # required there
