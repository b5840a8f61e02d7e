"""`aero up`'s launch plan (tools/cli/up/launch.py): what a service is given for the options of
`aero up` and for --gps-denied is data in tools/profiles.yaml (`options:`, `gps_denied:`, a
profile's `gps_denied_args:`), applied in the order declared; no service gets another's flags.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest
import yaml

from aeroperception.tools.cli import up as cmd_up

REPO = Path(__file__).resolve().parents[2]
PROFILES_YAML = yaml.safe_load((REPO / "tools" / "profiles.yaml").read_text())
ENDPOINT = "tcp/127.0.0.1:7447"


def up_args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    cmd_up.register(p.add_subparsers())
    return p.parse_args(["up", *argv])


def argv_of(name: str, args: argparse.Namespace, running=("sim", "fmu", "mission", "recorder")) -> list[str]:
    return cmd_up.service_argv(name, args, ENDPOINT, [], list(running))


def test_sim_options_are_handed_to_the_simulator_in_the_declared_order():
    args = up_args("--scenario", "village", "--speed", "4", "--seed", "3", "--sensors", "camera")
    assert argv_of("sim", args)[-8:] == ["--scenario", "village", "--speed", "4.0", "--seed", "3",
                                         "--sensors", "camera"]


def test_recorder_gets_the_scenario_only_and_fmu_the_fcu_url_only():
    args = up_args("--scenario", "village", "--seed", "3", "--fcu-url", "udpin:0.0.0.0:14540")
    assert argv_of("recorder", args)[-2:] == ["--scenario", "village"]
    assert "--seed" not in argv_of("recorder", args)
    fmu = argv_of("fmu", args)
    assert fmu[-2:] == ["--fcu-url", "udpin:0.0.0.0:14540"] and "--scenario" not in fmu


def test_the_mission_file_is_handed_over_as_an_absolute_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert argv_of("mission", up_args("--mission", "m.json"))[-1] == f"--param=mission_file={tmp_path / 'm.json'}"


def test_an_option_not_given_adds_nothing():
    args = up_args()
    for name in ("sim", "recorder", "fmu", "mission"):
        assert argv_of(name, args) == [sys.executable, "-m", f"aeroperception.services.{name}", "--connect", ENDPOINT]


def test_gps_denied_flags_come_from_profiles_yaml():
    want = PROFILES_YAML["gps_denied"]["args"]
    args = up_args("--gps-denied")
    assert argv_of("sim", args)[-len(want["sim"]):] == want["sim"]
    assert argv_of("mission", args)[-len(want["mission"]):] == want["mission"]
    assert "SIM_GPS_DENIED=true" not in argv_of("mission", args)


def test_the_px4_profile_gives_the_follower_sim_no_gps_denied_flags_but_keeps_the_missions():
    profile = cmd_up.load_profiles()["px4"]
    assert profile["gps_denied_args"]["sim"] == []
    assert profile["gps_denied_args"]["mission"] == PROFILES_YAML["gps_denied"]["args"]["mission"]
    assert cmd_up.load_profiles()["sim"]["gps_denied_args"]["sim"] == PROFILES_YAML["gps_denied"]["args"]["sim"]


def test_gps_denied_needs_are_declared_in_profiles_yaml():
    assert cmd_up.gps_denied_needs() == PROFILES_YAML["gps_denied"]["needs"] == ["vio", "perception"]


@pytest.mark.parametrize("section", ["options", "gps_denied"])
def test_every_service_named_in_the_launch_data_is_a_service_folder(section):
    data = PROFILES_YAML[section]
    names = set(data) if section == "options" else set(data["args"]) | set(data["needs"])
    missing = sorted(n for n in names if not (REPO / "services" / n / "__main__.py").is_file())
    assert not missing, f"profiles.yaml {section}: no service folder {missing}"


def test_every_option_named_in_profiles_yaml_is_an_aero_up_option():
    dests = set(vars(up_args()))
    unknown = sorted(o for opts in PROFILES_YAML["options"].values() for o in opts if o not in dests)
    assert not unknown, f"profiles.yaml options: not `aero up` options: {unknown}"
