"""What may cross a link to another host (tests/integration/test_multihost.py): no publisher waits
for a slow subscriber (congestion control BLOCK stalled the vehicle's router behind a saturated
ground link), and `aero router --thin-link IFACE` downsamples the bulk streams on that interface.
"""
from __future__ import annotations

import json
import re
import socket
from pathlib import Path

import pytest
import zenoh

from aeroperception.services.sim.qos import BULK_STREAMS, SMALL_STREAMS, qos_for
from aeroperception.tools.cli.router import thin_link_downsampling
from aeroperception.tools.common import CliError

SERVICES = Path(__file__).resolve().parents[2] / "services"


@pytest.mark.parametrize("key", SMALL_STREAMS + BULK_STREAMS)
def test_sim_streams_never_block(key):
    qos = qos_for(key)
    assert qos["congestion_control"] == zenoh.CongestionControl.DROP
    assert qos["priority"] == (zenoh.Priority.DATA_HIGH if key in SMALL_STREAMS else zenoh.Priority.DATA_LOW)


def test_no_service_publishes_with_block():
    offenders = [f"{p.relative_to(SERVICES)}:{n}" for p in SERVICES.rglob("*.py")
                 for n, line in enumerate(p.read_text().splitlines(), 1)
                 if re.search(r"CongestionControl\.BLOCK", line) and not line.lstrip().startswith("#")]
    assert not offenders, f"congestion control BLOCK lets a slow remote subscriber stall the router: {offenders}"


def test_thin_link_rules_cover_every_bulk_stream_with_or_without_vehicle_prefix():
    lo = socket.if_nameindex()[0][1]
    (item,) = thin_link_downsampling([lo], 0.5)
    assert item["interfaces"] == [lo] and item["flows"] == ["egress"] and item["messages"] == ["put"]
    assert {r["key_expr"] for r in item["rules"]} == {f"**/{k}" for k in BULK_STREAMS}
    assert {r["freq"] for r in item["rules"]} == {0.5}
    conf = zenoh.Config()
    conf.insert_json5("downsampling", json.dumps([item]))   # zenoh accepts it


def test_thin_link_none_is_no_rule_and_bad_input_is_one_line():
    assert thin_link_downsampling([], 1.0) == []
    with pytest.raises(CliError, match="no network interface 'nosuch0'"):
        thin_link_downsampling(["nosuch0"], 1.0)
    with pytest.raises(CliError, match="must be > 0"):
        thin_link_downsampling(["lo"], 0.0)


# ---------------------------------------------------------------- profiles (tools/profiles.yaml)

def test_ros2_profile_is_sim_plus_the_bridge_and_opt_in():
    from aeroperception.tools.cli.up import load_profiles

    profiles = load_profiles()
    assert profiles["ros2"]["services"] == [*profiles["sim"]["services"], "ros2bridge"]
    assert profiles["ros2"]["args"] == profiles["sim"]["args"]
    assert not any("ros2bridge" in p["services"] for name, p in profiles.items() if name != "ros2")


def test_optional_service_without_its_extra_is_one_line(monkeypatch):
    import importlib.util
    import subprocess
    import sys

    from aeroperception.tools.cli import up as cmd_up

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda m, *a: None if m == "rosbags" else real(m, *a))
    with pytest.raises(CliError, match=r"profile ros2: not installed: rosbags \(ros2bridge\)\. Install with: "
                                       r"\S*install\.sh sim,perception,tools,ros2"):
        cmd_up.check_installed("ros2", ["sim", "ros2bridge"])
    cmd_up.check_installed("ros2", ["sim", "fmu"])
    # The service itself, started without rosbags: one line on stderr, exit 2, no traceback.
    block = ("import sys, runpy; sys.modules['rosbags'] = None; "
             "runpy.run_module('aeroperception.services.ros2bridge', run_name='__main__')")
    r = subprocess.run([sys.executable, "-c", block], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == [
        "ros2bridge: needs the optional extra 'ros2' (rosbags): pip install 'aeroperception[ros2]'"]
