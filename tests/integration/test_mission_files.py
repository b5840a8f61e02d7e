"""Mission files, JSON and YAML alike, through the real mission service: `aero up
--mission FILE` loads one at start-up (the mission service's `mission_file` parameter), `aero
mission load` and mission/srv/load take either format, and both are decoded strictly (an
unknown or a missing field is refused, naming it). A bad start-up file is refused in one line
before anything starts.
"""
from __future__ import annotations

import json

from aerotest import aero, free_port, wait_for_message
from aeroperception.schemas import (
    DiagnosticStatus, LoadMissionReply, LoadMissionRequest, MissionStatus,
)
from aeroperception.services.runtime.node import call

YAML_MISSION = """\
# a YAML mission: the same fields as the JSON files in examples/missions
mission_id: yaml_square
takeoff_altitude_m: 4.0
waypoints:
  - {x: 5.0, y: 0.0, z: 4.0}
  - {x: 5.0, y: 5.0, z: 4.0, yaw_deg: 90}
  - x: 0.0
    y: 0.0
    z: 4.0
waypoint_acceptance_radius_m: 0.5
"""
JSON_MISSION = {"mission_id": "json_line", "takeoff_altitude_m": 3.0,
                "waypoints": [{"x": 2.0, "y": 0.0, "z": 3.0}, {"x": 4.0, "y": 0.0, "z": 3.0}]}


def status(st, pred, what: str) -> MissionStatus:
    return wait_for_message(st.session, "mission/status", MissionStatus, pred, 10.0)


def test_aero_up_mission_yaml_at_start_and_both_formats_through_the_service(stack, tmp_path):
    y = tmp_path / "square.yaml"
    y.write_text(YAML_MISSION)
    j = tmp_path / "line.json"
    j.write_text(json.dumps(JSON_MISSION))
    st = stack(["mission"], extra_args=["--mission", str(y)])
    s = status(st, lambda m: m.mission_id == "yaml_square", "the start-up mission")
    assert s.total_waypoints == 3 and s.state == "IDLE", s

    r = st.aero("mission", "load", str(j))
    assert r.returncode == 0 and "json_line loaded, 2 waypoints" in r.stdout, r.stdout + r.stderr
    status(st, lambda m: m.mission_id == "json_line" and m.total_waypoints == 2, "the JSON mission")
    r = st.aero("mission", "load", str(y))       # the defect: "Mission: JSON is malformed"
    assert r.returncode == 0 and "yaml_square loaded, 3 waypoints" in r.stdout, r.stdout + r.stderr
    status(st, lambda m: m.mission_id == "yaml_square" and m.total_waypoints == 3, "the YAML mission")

    # strict in both formats, at the service itself (not only the CLI's local check)
    for text, field in [(YAML_MISSION.replace("takeoff_altitude_m", "takeoff_altitude"), "takeoff_altitude"),
                        ("mission_id: no_waypoints\n", "waypoints"),
                        (json.dumps({**JSON_MISSION, "speed": 3}), "speed"),
                        (json.dumps({"mission_id": "x"}), "waypoints")]:
        rep = call(st.session, "mission/srv/load", LoadMissionRequest(mission_json=text), LoadMissionReply, 5.0)
        assert not rep.success and f"`{field}`" in rep.message, (field, rep.message)
    assert status(st, lambda m: True, "status").mission_id == "yaml_square"   # the refusals changed nothing

    # the parameter set live loads the file too (never accepted and ignored)
    r = st.aero("param", "set", "mission", "mission_file", str(j))
    assert r.returncode == 0, r.stderr
    status(st, lambda m: m.mission_id == "json_line", "mission_file set live")
    # a live set it cannot honour is refused with the reason, and the parameter keeps what runs
    bad = tmp_path / "bad.yaml"
    bad.write_text(YAML_MISSION.replace("mission_id", "mission_name"))
    for name, value, words in [("mission_file", str(bad), "mission_name"),
                               ("geofence_polygon", "not a polygon", "geofence_polygon")]:
        r = st.aero("param", "set", "mission", name, value)
        assert r.returncode == 1 and words in r.stderr, (name, r.stderr)
        assert st.aero("param", "get", "mission", name).stdout.strip() != value
    assert st.aero("param", "get", "mission", "mission_file").stdout.strip() == str(j)
    assert status(st, lambda m: True, "status").mission_id == "json_line"


def test_a_bad_start_up_mission_is_refused_in_one_line_before_anything_starts(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(YAML_MISSION.replace("  - {x: 5.0, y: 0.0, z: 4.0}", "  - {x: 5.0, y: 0.0, z: 4.0, zz: 1}"))
    port = free_port()
    for path, words in [(bad, "unknown field `waypoints[0].zz`"), (tmp_path / "missing.yaml", "cannot read")]:
        r = aero("up", "--only", "mission", "--listen", f"tcp/127.0.0.1:{port}",
                 "--log-dir", str(tmp_path / "logs"), "--mission", str(path), timeout_s=30)
        assert r.returncode == 2, r.stdout + r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0] and str(path) in lines[0], r.stderr
        assert "Traceback" not in r.stderr and not (tmp_path / "logs").exists()


def test_mission_service_with_a_bad_mission_file_runs_and_says_why(stack, tmp_path):
    """Started without aero up's check (e.g. a parameter file): the service keeps running, loads
    nothing and its diagnostics name the file and the field."""
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**JSON_MISSION, "takeoff_alt": 3}))
    st = stack(["mission"], extra_args=["--arg", f"mission:--param=mission_file={bad}"])
    d = wait_for_message(st.session, "diagnostics/mission", DiagnosticStatus,
                         lambda m: "mission_file" in m.message, 15.0)
    assert d.level == DiagnosticStatus.WARN and "unknown field `takeoff_alt`" in d.message, d.message
    assert status(st, lambda m: True, "status").mission_id == ""
