"""`aero up --profile ardupilot`: the ArduCopter SITL launcher's checks (tools/cli/ardupilot_sitl.py) and
how aero up plans it, without running ArduPilot (tests/integration/test_ardupilot.py flies it)."""
from __future__ import annotations

import tarfile

import pytest

from aeroperception.tools.cli import ardupilot_sitl, up as cmd_up
from aeroperception.tools.common import CliError
from test_px4_sitl import up_args


def fake_bundle(root, binary: bool = True, params: bool = True):
    d = root / ardupilot_sitl.BUNDLE
    (d / "bin").mkdir(parents=True)
    (d / "default_params").mkdir()
    if binary:
        (d / "bin" / "arducopter").write_text("#!/bin/sh\n")
        (d / "bin" / "arducopter").chmod(0o755)
    if params:
        (d / "default_params" / "copter.parm").write_text("")
    return d


def test_the_folder_its_parent_or_a_waf_checkout_are_found(tmp_path, monkeypatch):
    monkeypatch.delenv(ardupilot_sitl.DIR_ENV, raising=False)
    d = fake_bundle(tmp_path / "a")
    assert ardupilot_sitl.sitl(str(d)) == (d / "bin" / "arducopter", d / "default_params" / "copter.parm")
    assert ardupilot_sitl.sitl(str(tmp_path / "a"))[0] == d / "bin" / "arducopter"
    co = tmp_path / "ardupilot"
    (co / "build" / "sitl" / "bin").mkdir(parents=True)
    (co / "Tools" / "autotest" / "default_params").mkdir(parents=True)
    (co / "build" / "sitl" / "bin" / "arducopter").write_text("")
    (co / "build" / "sitl" / "bin" / "arducopter").chmod(0o755)
    (co / "Tools" / "autotest" / "default_params" / "copter.parm").write_text("")
    assert ardupilot_sitl.sitl(str(co))[0] == co / "build" / "sitl" / "bin" / "arducopter"
    monkeypatch.setenv(ardupilot_sitl.DIR_ENV, str(d))
    assert ardupilot_sitl.sitl(None)[0] == d / "bin" / "arducopter"


def test_a_wrong_dir_is_refused_in_one_line(tmp_path, monkeypatch):
    monkeypatch.delenv(ardupilot_sitl.DIR_ENV, raising=False)
    with pytest.raises(CliError, match=r"needs ArduCopter SITL: --ardupilot DIR or AERO_ARDUPILOT_DIR"):
        ardupilot_sitl.sitl(None)
    with pytest.raises(CliError, match="no such directory or .tar.gz"):
        ardupilot_sitl.sitl(str(tmp_path / "nope"))
    for kw in ({"binary": False}, {"params": False}):
        root = tmp_path / str(kw)
        fake_bundle(root, **kw)
        with pytest.raises(CliError, match="no executable bin/arducopter with default_params/copter.parm") as e:
            ardupilot_sitl.sitl(str(root))
        assert "\n" not in str(e.value)


def test_a_tarball_is_unpacked_once_into_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(ardupilot_sitl.CACHE_ENV, str(tmp_path / "cache"))
    fake_bundle(tmp_path / "src")
    tgz = tmp_path / "ardupilot-sitl-copter.tar.gz"
    with tarfile.open(tgz, "w:gz") as tf:
        tf.add(tmp_path / "src" / ardupilot_sitl.BUNDLE, arcname=ardupilot_sitl.BUNDLE)
    binary, _ = ardupilot_sitl.sitl(str(tgz))
    assert binary.is_file() and (tmp_path / "cache" / "ardupilot") in binary.parents
    binary.with_name("marker").write_text("kept")
    assert ardupilot_sitl.sitl(str(tgz))[0] == binary and binary.with_name("marker").is_file()   # not again
    assert [p.name for p in (tmp_path / "cache" / "ardupilot").iterdir()] == [binary.parents[2].name]


def test_argv_sends_serial0_to_fmu_over_loopback_udp_as_instance_n(tmp_path):
    argv = ardupilot_sitl.argv(tmp_path / "arducopter", tmp_path / "copter.parm", 3)
    assert argv[argv.index("-I") + 1] == "3"
    assert argv[argv.index("--serial0") + 1] == "udpclient:127.0.0.1:14543"
    assert ardupilot_sitl.fcu_url(3) == "udpin:127.0.0.1:14543"
    assert ardupilot_sitl.tcp_ports(3) == (5790, 5792, 5793)


def test_plan_points_fmu_at_it_and_refuses_what_does_not_fit(tmp_path, monkeypatch):
    monkeypatch.delenv(ardupilot_sitl.DIR_ENV, raising=False)
    monkeypatch.setattr(ardupilot_sitl, "busy_ports", lambda n: [])
    d = fake_bundle(tmp_path)
    names = cmd_up.load_profiles()["ardupilot"]["services"]
    assert "ardupilot" in names and "sim" not in names and "fmu" in names
    args = up_args(profile="ardupilot", ardupilot=d, ardupilot_instance=4)
    plan = cmd_up.plan_fc(args, names)
    assert plan.name == "ardupilot" and plan.instance == 4 and args.fcu_url == "udpin:127.0.0.1:14544"
    with pytest.raises(CliError, match="--fcu-url: fmu talks to the ArduPilot"):
        cmd_up.plan_fc(up_args(profile="ardupilot", ardupilot=d, fcu_url="udpin:127.0.0.1:14540"), names)
    with pytest.raises(CliError, match="--ardupilot: profile vehicle starts no ArduPilot"):
        cmd_up.plan_fc(up_args(profile="vehicle", ardupilot=d), cmd_up.load_profiles()["vehicle"]["services"])
    monkeypatch.setattr(ardupilot_sitl, "busy_ports", lambda n: [5800] if n == 4 else [])
    with pytest.raises(CliError, match=r"ArduPilot instance 4: port 5800 already in use .* use --ardupilot-instance 0"):
        cmd_up.plan_fc(up_args(profile="ardupilot", ardupilot=d, ardupilot_instance=4), names)
