"""`aero up --profile px4`: the PX4 SITL launcher's checks (tools/cli/px4_sitl.py) and how aero up plans
and stops it, without running PX4 (tests/integration/test_px4.py flies it)."""
from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from aeroperception.services.runtime.supervision import terminate
from aeroperception.tools.cli import up as cmd_up, px4_sitl
from aeroperception.tools.common import CliError


def fake_build(tmp_path, px4: bool = True, rcs: bool = True):
    (tmp_path / "bin").mkdir(parents=True)
    (tmp_path / "etc" / "init.d-posix").mkdir(parents=True)
    if px4:
        (tmp_path / "bin" / "px4").write_text("#!/bin/sh\n")
        (tmp_path / "bin" / "px4").chmod(0o755)
    if rcs:
        (tmp_path / "etc" / "init.d-posix" / "rcS").write_text("")
    return tmp_path


def up_args(**kw) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    cmd_up.register(p.add_subparsers())
    return p.parse_args(["up", *[x for k, v in kw.items() for x in (f"--{k.replace('_', '-')}", str(v))]])


def test_px4_build_dir_is_checked_and_refused_in_one_line(tmp_path, monkeypatch):
    monkeypatch.delenv(px4_sitl.DIR_ENV, raising=False)
    with pytest.raises(CliError, match=r"needs a PX4 build: --px4 DIR or AERO_PX4_DIR"):
        px4_sitl.build_dir(None)
    with pytest.raises(CliError, match="no such directory"):
        px4_sitl.build_dir(str(tmp_path / "nope"))
    with pytest.raises(CliError, match="no executable bin/px4"):
        px4_sitl.build_dir(str(fake_build(tmp_path / "a", px4=False)))
    with pytest.raises(CliError, match="no etc/init.d-posix/rcS"):
        px4_sitl.build_dir(str(fake_build(tmp_path / "b", rcs=False)))
    good = fake_build(tmp_path / "c")
    assert px4_sitl.build_dir(str(good)) == good.resolve()
    monkeypatch.setenv(px4_sitl.DIR_ENV, str(good))
    assert px4_sitl.build_dir(None) == good.resolve()


def test_a_running_px4_instance_is_refused_naming_its_pid_and_a_free_one(tmp_path, monkeypatch):
    lock = tmp_path / "px4_lock-3"
    monkeypatch.setattr(px4_sitl, "lock_path", lambda n: lock if n == 3 else tmp_path / f"free-{n}")
    monkeypatch.setattr(px4_sitl, "busy_ports", lambda n: [])
    assert px4_sitl.lock_holder(3) is None                    # no file
    lock.write_text("")
    assert px4_sitl.lock_holder(3) is None                    # a file nobody holds (PX4 killed -9)
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time\n"     # what PX4 does
                               f"fd = os.open({str(lock)!r}, os.O_RDWR)\nfcntl.lockf(fd, fcntl.LOCK_EX)\n"
                               "print('locked', flush=True)\ntime.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert px4_sitl.lock_holder(3) == holder.pid
        with pytest.raises(CliError, match=rf"PX4 instance 3 is already running \(pid {holder.pid} holds "
                                           r".*px4_lock-3\): stop it, or .* --px4-instance 0"):
            px4_sitl.check_instance(3)
    finally:
        holder.kill()
        holder.wait(5)
    px4_sitl.check_instance(3)


def test_an_instance_whose_ports_are_taken_is_refused():
    n = px4_sitl.free_instance(1)
    assert n is not None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", px4_sitl.Ports(n).fmu))      # e.g. another stack's fmu
        with pytest.raises(CliError, match=rf"PX4 instance {n}: UDP port {14540 + n} already in use"):
            px4_sitl.check_instance(n)
    with pytest.raises(CliError, match=r"--px4-instance 10: expected 0..9"):
        px4_sitl.check_instance(10)


def test_px4_profile_points_fmu_at_its_instance_and_refuses_what_it_would_ignore(tmp_path, monkeypatch):
    monkeypatch.setattr(px4_sitl, "check_instance", lambda n: None)
    build = fake_build(tmp_path)
    args = up_args(profile="px4", px4=build, px4_instance=4)
    names = cmd_up.select_services(args)
    assert {"px4", "fmu", "planner", "mission", "sim", "vio", "lidar", "detector"} <= set(names)
    plan = cmd_up.plan_px4(args, names)
    assert (plan.build, plan.instance) == (build.resolve(), 4)
    assert cmd_up.service_argv("fmu", args, "tcp/127.0.0.1:7447")[-2:] == ["--fcu-url", "udpin:127.0.0.1:14544"]

    with pytest.raises(CliError, match=r"--fcu-url: fmu talks to the PX4 this profile starts"):
        cmd_up.plan_px4(up_args(profile="px4", px4=build, fcu_url="udpin:127.0.0.1:14540"), names)
    # the simulator renders the sensors following PX4's physics: its own clock and noise do not apply
    assert "--follow" in cmd_up.service_argv("sim", args, "tcp/127.0.0.1:7447", cmd_up.load_profiles()["px4"]["args"]["sim"])
    kept, left_out = cmd_up.fed_services(names, "lidar")       # --sensors narrows it as the sim profile
    assert {"sim", "lidar", "px4"} <= set(kept) and {"vio", "detector", "objects"} <= set(left_out)
    assert cmd_up.service_argv("sim", up_args(profile="px4", px4=build, sensors="lidar"), "tcp/127.0.0.1:7447")[-2:] == \
        ["--sensors", "lidar"]
    for flag, value in (("speed", 2.0), ("seed", 7)):
        with pytest.raises(CliError, match=rf"--{flag}: PX4 SITL flies the vehicle in real time"):
            cmd_up.validate_args(up_args(profile="px4", px4=build, **{flag: value}), names)
    for flag, value in (("px4", build), ("px4_instance", 1)):
        args = up_args(profile="vehicle", **{flag: value})
        with pytest.raises(CliError, match=r"profile vehicle starts no PX4 \(use --profile px4\)"):
            cmd_up.plan_px4(args, cmd_up.select_services(args))


def test_px4_child_boots_sih_with_the_offboard_parameters_and_stops_on_sigint(tmp_path, monkeypatch):
    monkeypatch.setenv("PX4_PARAM_NAV_DLL_ACT", "2")           # a user's own value wins
    plan = cmd_up.Px4Plan(fake_build(tmp_path / "build"), 2)
    c = plan.child(tmp_path, cmd_up.Priority())
    assert c.stop_signal == signal.SIGINT and c.booted == px4_sitl.BOOTED
    assert c.extra_env["PX4_SYS_AUTOSTART"] == "10040" and c.extra_env["PX4_SIMULATOR"] == "sihsim"
    assert c.extra_env["PX4_PARAM_COM_RC_IN_MODE"] == "4" and c.extra_env["PX4_PARAM_NAV_DLL_ACT"] == "2"
    px4 = c.argv.index(str(plan.build / "bin" / "px4"))
    workdir = c.argv[px4 + c.argv[px4:].index("-w") + 1]
    assert c.argv[px4:] == [str(plan.build / "bin" / "px4"), "-d", "-i", "2", "-w", workdir, str(plan.build / "etc")]
    assert os.path.dirname(workdir) == str(tmp_path) and not os.listdir(workdir)   # fresh and empty
    assert plan.child(tmp_path, cmd_up.Priority()).argv != c.argv                  # a new one each run


def test_sih_boots_with_ekf2s_imu_noise_matched_with_gps_only():
    """SIH's IMU is noisier than EKF2's defaults (EKF2's velocity then wandered 0.25-0.39 m/s RMS off the
    truth): matched at boot when flying on GPS; the GPS-denied (vision) set leaves them as measured."""
    gps = px4_sitl.boot_env({})
    assert gps["PX4_PARAM_EKF2_ACC_NOISE"] == "1.0" and gps["PX4_PARAM_EKF2_GYR_NOISE"] == "0.1"
    assert gps["PX4_PARAM_COM_RC_IN_MODE"] == "4"
    denied = px4_sitl.boot_env({}, gps_denied=True)
    assert "PX4_PARAM_EKF2_ACC_NOISE" not in denied and denied["PX4_PARAM_EKF2_GPS_CTRL"] == "0"
    assert px4_sitl.boot_env({"PX4_PARAM_EKF2_ACC_NOISE": "0.35"})["PX4_PARAM_EKF2_ACC_NOISE"] == "0.35"  # a user's wins


def test_terminate_asks_with_the_first_signal_then_sigterm_then_sigkill():
    def child(code: str) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, "-c", "import signal, sys, time\n" + code + "\nprint('ready', flush=True)\n"
                              "time.sleep(60)"], stdout=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "ready"
        return p

    on_int = child("signal.signal(signal.SIGINT, lambda *a: sys.exit(7))")
    deaf_to_int = child("signal.signal(signal.SIGINT, signal.SIG_IGN)")
    deaf = child("signal.signal(signal.SIGINT, signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN)")
    t0 = time.monotonic()
    terminate([on_int, deaf_to_int, deaf], timeout_s=1.0, kill_wait_s=1.0, first_signal=lambda p: signal.SIGINT)
    assert on_int.returncode == 7                       # stopped cleanly on SIGINT
    assert deaf_to_int.returncode == -signal.SIGTERM    # then SIGTERM
    assert deaf.returncode == -signal.SIGKILL           # then SIGKILL
    assert time.monotonic() - t0 < 4.0
