"""Flight-controller parameter sets (tools/cli/fc_params.py): every value has its reason, `aero up
--profile px4 --gps-denied` boots PX4 with the SIH set, and `aero fc params apply` sets a set over
MAVLink and reads each value back (here against a loopback PX4 stand-in that keeps a parameter
table; tests/integration/test_px4_gps_denied.py applies it to real PX4 SITL)."""
from __future__ import annotations

import socket
import subprocess
import sys
import threading

import pytest
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.tools.cli import up as cmd_up, fc_params, px4_sitl
from aeroperception.tools.common import CliError

from test_px4_sitl import fake_build, up_args


def test_every_parameter_has_a_reason_a_type_and_appears_once():
    for name, params in fc_params.SETS.items():
        names = [p.name for p in params]
        assert len(names) == len(set(names)), name
        for p in params:
            assert len(p.why) > 20 and p.param_type in (fc_params.INT32, fc_params.REAL32), p
    vehicle = {p.name: p.value for p in fc_params.SETS["gps-denied"]}
    assert vehicle["EKF2_GPS_CTRL"] == 0 and vehicle["EKF2_HGT_REF"] == 3
    assert vehicle["EKF2_EV_CTRL"] == 1 | 2 | 4          # hpos + vpos + vel, not yaw (8)
    assert "SIM_GPS_USED" not in vehicle                   # SITL only
    assert {p.name: p.value for p in fc_params.SETS["gps-denied-sih"]}["SIM_GPS_USED"] == 0


def test_int_parameters_travel_bytewise_and_floats_as_themselves():
    for p in fc_params.SETS["gps-denied-sih"]:
        assert fc_params.decode(fc_params.encode(p), p.param_type) == p.value
    ctrl = fc_params.FcParam("EKF2_EV_CTRL", 7, "x")
    assert fc_params.encode(ctrl) != 7.0                   # not the float 7: PX4 reads the int32's bytes
    assert not fc_params.matches(ctrl, 11) and not fc_params.matches(ctrl, None)


def test_gps_denied_px4_boots_with_the_sih_set_and_a_users_own_value_wins(tmp_path, monkeypatch):
    monkeypatch.setattr(px4_sitl, "check_instance", lambda n: None)
    monkeypatch.setenv("PX4_PARAM_EKF2_EVP_NOISE", "0.3")
    build = fake_build(tmp_path)
    args = up_args(profile="px4", px4=build, px4_instance=4)
    args.gps_denied = True
    names = cmd_up.select_services(args)
    cmd_up.validate_args(args, names)        # px4 runs no vio: vision comes from elsewhere, not refused
    plan = cmd_up.plan_px4(args, names)
    env = plan.child(tmp_path, cmd_up.Priority()).extra_env
    assert env["PX4_PARAM_SIM_GPS_USED"] == "0" and env["PX4_PARAM_EKF2_GPS_CTRL"] == "0"
    assert env["PX4_PARAM_EKF2_EV_CTRL"] == "7" and env["PX4_PARAM_EKF2_HGT_REF"] == "3"
    assert env["PX4_PARAM_EKF2_EVP_NOISE"] == "0.3"
    fmu = cmd_up.service_argv("fmu", args, "tcp/127.0.0.1:7447", [], names)
    assert "--sim-time" not in fmu                          # the sim follows PX4: no sim/clock, wall time
    if "sim" in names:                                      # PX4's EKF2 estimates, not the sim's imitation
        assert "SIM_GPS_DENIED=true" not in cmd_up.service_argv("sim", args, "tcp/127.0.0.1:7447", [], names)
    assert f"--param=global_origin={px4_sitl.SIH_ORIGIN}" in fmu         # PX4 gets a global position
    assert "PX4_PARAM_EKF2_EV_CTRL" not in cmd_up.Px4Plan(plan.build, 4).env()


def test_px4_profile_runs_vio_with_imu_propagated_poses_its_contract_accepts():
    """EKF2 fuses vision only < 0.2 s apart and soon after its stamp: with PX4 the VIO also publishes
    poses between frames (services/vio/propagate.py), at a rate its own parameter check accepts."""
    from aeroperception.services.vio import contract as vio_contract

    vio_args = cmd_up.load_profiles()["px4"]["args"]["vio"]
    rates = [float(a.split("=", 2)[2]) for a in vio_args if a.startswith("--param=imu_rate_hz=")]
    spec = next(p for p in vio_contract.PARAMS if p.name == "imu_rate_hz")
    assert rates and 5.0 < rates[0] <= spec.max, vio_args       # > 5 Hz: EKF2's 0.2 s
    assert "vio" not in cmd_up.load_profiles()["sim"]["args"]          # the sim's own FC: one pose per frame


def test_gps_denied_sim_still_needs_the_vio_it_runs():
    args = up_args(profile="sim", only="sim,fmu,planner,mission")
    args.gps_denied = True
    with pytest.raises(CliError, match="--gps-denied needs vio, perception"):
        cmd_up.validate_args(args, cmd_up.select_services(args))


class ParamPeer:
    """A PX4 stand-in on loopback: HEARTBEAT as an autopilot, PARAM_SET/PARAM_REQUEST_READ answered
    with PARAM_VALUE (bytewise ints) from its table; parameters it does not have get no answer."""

    def __init__(self, table: dict[str, tuple[float, int]]):
        self.table = table
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
        self.peer = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _send(self, msg) -> None:
        if self.peer:
            self.sock.sendto(msg.pack(self.mav), self.peer)

    def _run(self) -> None:
        while not self.stop.is_set():
            try:
                data, self.peer = self.sock.recvfrom(4096)
            except OSError:
                continue
            for m in self.mav.parse_buffer(data) or []:
                t = m.get_type()
                if t == "HEARTBEAT":
                    self._send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                                                 0, 0, 0, 3))
                    continue
                if t not in ("PARAM_SET", "PARAM_REQUEST_READ") or m.target_system != 3:
                    continue
                name = str(m.param_id).rstrip("\x00")
                if name not in self.table:
                    continue
                if t == "PARAM_SET":
                    self.table[name] = (m.param_value, m.param_type)
                value, ptype = self.table[name]
                self._send(mavlink.MAVLink_param_value_message(name.encode(), value, ptype, len(self.table), 0))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(1)
        self.sock.close()


def aero(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aeroperception.tools.cli", *argv], capture_output=True, text=True,
                          timeout=60, stdin=subprocess.DEVNULL)


def test_fc_params_apply_sets_and_reads_back_and_names_what_the_fc_lacks():
    table = {p.name: (0.0, p.param_type) for p in fc_params.GPS_DENIED if p.name != "GF_ACTION"}
    peer = ParamPeer(table)
    try:
        r = aero("fc", "params", "apply", "gps-denied", "--fcu-url", f"udpout:127.0.0.1:{peer.port}", "--timeout", "5")
    finally:
        peer.close()
    assert r.returncode == 1, r.stdout + r.stderr
    lines = {line.split()[0]: line.split()[1:] for line in r.stdout.splitlines()[1:-1]}
    assert lines["EKF2_EV_CTRL"] == ["7", "7"] and lines["MC_YAWRATE_MAX"] == ["60", "60"]
    assert lines["GF_ACTION"] == ["1", "(no", "answer)", "MISMATCH"]
    assert r.stdout.splitlines()[-1] == f"{len(table)}/{len(table) + 1} set; not as wanted: GF_ACTION"
    assert fc_params.decode(*table["EKF2_EV_CTRL"]) == 7                  # what the FC now holds


def test_fc_params_errors_are_one_line():
    r = aero("fc", "params", "apply", "gps-denied", "--fcu-url", "nonsense")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "expected udpin:HOST:PORT" in r.stderr
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        silent = s.getsockname()[1]
        r = aero("fc", "params", "apply", "gps-denied", "--fcu-url", f"udpout:127.0.0.1:{silent}", "--timeout", "1")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "no flight controller HEARTBEAT" in r.stderr
    r = aero("fc", "params", "show", "gps-denied")
    assert r.returncode == 0 and "EKF2_EV_CTRL" in r.stdout and "SIM_GPS_USED" not in r.stdout
