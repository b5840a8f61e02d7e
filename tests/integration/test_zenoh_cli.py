"""The PyPI `zenoh-cli` (`zenoh subscribe/put`) with our codec plugin, against a real router.

The plugin is found through zenoh-cli's own entry-point groups, so these tests run the real
`zenoh` script exactly as a user would."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from aerotest import clean_env, wait_until
from aeroperception.schemas import MissionCommand, Reply, TrajectorySetpoint, Vector3, VehicleState
from aeroperception.services.runtime.session import DEFAULT_CONFIG

ZENOH = Path(sys.executable).parent / "zenoh"
pytestmark = pytest.mark.skipif(not ZENOH.is_file() and not shutil.which("zenoh"),
                                reason="zenoh-cli is not installed (pip install .[test])")


def zenoh_cli(endpoint: str, *args: str) -> list[str]:
    # The project's config (no multicast scouting), in client mode, connected to the test router.
    return [str(ZENOH if ZENOH.is_file() else shutil.which("zenoh")), "--config", str(DEFAULT_CONFIG),
            "--mode", "client", "--connect", endpoint, *args]


def read_lines(proc: subprocess.Popen, out: list[str]) -> threading.Thread:
    t = threading.Thread(target=lambda: [out.append(line) for line in proc.stdout], daemon=True)
    t.start()
    return t


def test_zenoh_subscribe_decodes_our_state(zenoh_router, make_node):
    node = make_node("fmu")
    pub = node.publisher("state/vehicle", VehicleState)
    proc = subprocess.Popen(zenoh_cli(zenoh_router, "subscribe", "-k", "state/**", "--decoder", "aero"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=clean_env())
    lines: list[str] = []
    read_lines(proc, lines)
    try:
        def published_and_seen():
            pub.publish(VehicleState(position_m=Vector3(x=1.5, y=-2.0, z=10.0), armed=True, flight_mode="OFFBOARD"))
            return lines
        wait_until(published_and_seen, timeout_s=10, what="a decoded line from `zenoh subscribe`", interval_s=0.1)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=5)
    shown = json.loads(lines[0])
    assert shown["schema"] == "VehicleState", (lines, err)
    assert shown["data"]["position_m"] == {"x": 1.5, "y": -2.0, "z": 10.0}
    assert shown["data"]["armed"] is True and shown["data"]["flight_mode"] == "OFFBOARD"


def test_zenoh_put_injects_a_typed_setpoint_and_refuses_a_wrong_one(zenoh_router, make_node):
    node = make_node("fmu")
    got: list[TrajectorySetpoint] = []
    node.subscribe("fmu/in/trajectory_setpoint", TrajectorySetpoint, got.append, strict=True)
    time.sleep(0.3)
    ok = subprocess.run(zenoh_cli(zenoh_router, "put", "-k", "fmu/in/trajectory_setpoint", "--encoder", "aero",
                                  "-v", '{"position_valid": true, "position_m": {"x": 1, "y": 2, "z": 3}}'),
                        capture_output=True, text=True, timeout=20, env=clean_env())
    assert ok.returncode == 0, ok.stderr
    wait_until(lambda: got, timeout_s=5, what="the setpoint `zenoh put` sent")
    assert got[0].position_valid and (got[0].position_m.x, got[0].position_m.z) == (1.0, 3.0)
    assert got[0].header.stamp_ns > 0  # stamped like `aero topic pub`

    # Strict: an unknown field (a typo) is refused before anything is sent.
    bad = subprocess.run(zenoh_cli(zenoh_router, "put", "-k", "fmu/in/trajectory_setpoint", "--encoder", "aero",
                                   "-v", '{"position_vaild": true}'),
                         capture_output=True, text=True, timeout=20, env=clean_env())
    assert bad.returncode != 0
    assert "position_vaild" in bad.stderr and "Traceback" not in bad.stderr
    # An explicit schema on an undeclared key works too.
    named = subprocess.run(zenoh_cli(zenoh_router, "put", "-k", "test/anything", "--encoder", "aero",
                                     "-v", 'TrajectorySetpoint {"yaw_valid": true, "yaw_rad": 0.5}'),
                           capture_output=True, text=True, timeout=20, env=clean_env())
    assert named.returncode == 0, named.stderr
    time.sleep(0.5)
    assert len(got) == 1 and node.bad_input.total() == 0


def test_zenoh_get_calls_a_service_with_a_typed_request_and_decodes_the_reply(zenoh_router, make_node):
    node = make_node("mission")
    got: list[MissionCommand] = []

    def handle(cmd: MissionCommand) -> Reply:
        got.append(cmd)
        return Reply(success=True, message=f"{cmd.command} accepted")

    node.serve("mission/srv/command", MissionCommand, Reply, handle)
    r = subprocess.run(zenoh_cli(zenoh_router, "get", "-s", "mission/srv/command", "--encoder", "aero",
                                 "-v", "{command: HOLD}", "--decoder", "aero"),
                       capture_output=True, text=True, timeout=30, env=clean_env())
    assert r.returncode == 0, r.stderr
    shown = json.loads(r.stdout.splitlines()[0])
    assert shown["schema"] == "Reply"
    assert (shown["data"]["success"], shown["data"]["message"]) == (True, "HOLD accepted")
    assert [c.command for c in got] == ["HOLD"]
