"""`aero eval objects --replay FILE`: the objects pipeline run offline over a recording (MCAP, as the
recorder writes it) scores the same table as --live: a 2 s recording made here (camera infos, home,
vehicle states, a textured stereo pair and the detector's box on a person) puts the person where
the scenario says it is, by stereo; a file that is missing, lacks the inputs or names no scenario
is one line saying what to do."""
from __future__ import annotations

import json

import numpy as np
import pytest

from test_objects_projection import BASELINE, FX, T_BODY_CAM, infos, project, textured_pair

from aeroperception.schemas import (
    Detection2D, Detection2DArray, Header, HomePosition, Image, Quaternion, Vector3, VehicleState, encode,
)
from aeroperception.services.objects.projection import PoseSample
from aeroperception.services.recorder import contract as recorder_contract
from aeroperception.services.recorder.logic import McapSink, Recording, SinkConfig
from aeroperception.services.runtime.config import build
from aeroperception.services.runtime.node import encoding_for
from aeroperception.services.runtime.rotations import quat_from_euler
from aeroperception.tools.cli.aero import main as aero
from aeroperception.tools.eval.objects import replay

MS = 1_000_000
T0 = 1_000_000_000
DISPARITY = 4                                   # px at the person's near face
FACE_DEPTH = FX * BASELINE / DISPARITY          # 6.4 m
VEHICLE = np.array([0.0, 0.0, 0.875 - T_BODY_CAM[2]])   # the camera at the person's mid-height, looking east
# The person's centre: a quarter of its footprint (0.45 + 0.5 m) behind the face stereo sees, on the left camera's axis.
PERSON = np.array([T_BODY_CAM[0] + FACE_DEPTH + 0.95 / 4, T_BODY_CAM[1], 0.875])
SCENARIO = f"""name: replay_one_person
description: a person ahead of the vehicle
seed: 1
ground: {{size_m: [60, 60], slope_deg: 0, material: grass}}
start: {{position_m: [0, 0], height_agl_m: 0, yaw_deg: 0}}
objects: []
targets:
  - {{class: person, position_m: [{PERSON[0]:.6f}, {PERSON[1]:.6f}], yaw_deg: 90}}
sensors:
  camera: {{width: 640, height: 480, rate_hz: 20, hfov_deg: 90, stereo: true, baseline_m: 0.08, pitch_down_deg: 0}}
"""


def _offer(rec, key, msg, log_ns):
    assert rec.offer(key, str(encoding_for(type(msg))), encode(msg), log_ns)


def record(tmp_path, metadata=True, detections=True):
    """2 s at 10 detection frames a second: what `aero record --images` keeps of a hover."""
    scenario = tmp_path / "one_person.yaml"
    scenario.write_text(SCENARIO)
    sink = McapSink(build(SinkConfig, recorder_contract.PARAMS, output_dir=tmp_path / "rec"),
                    {"aeroperception": {"scenario": str(scenario)}} if metadata else {})
    rec = Recording(sink, 64 << 20).start()
    left_info, right_info = infos(0.0)
    q = quat_from_euler(0.0, 0.0, 0.0)
    u, v, z = project(PERSON, PoseSample(0, VEHICLE, q))
    u, v, w, h = float(u), float(v), FX * 0.5 / z, FX * 1.75 / z
    box = (int(u - w / 2), int(v - h / 2), int(u + w / 2), int(v + h / 2))
    left, right = textured_pair(DISPARITY, box)
    _offer(rec, "sensors/camera/left/info", left_info, T0)
    _offer(rec, "sensors/camera/right/info", right_info, T0)
    _offer(rec, "fmu/out/home_position", HomePosition(latitude_deg=47.39, longitude_deg=8.54, altitude_amsl_m=488.0), T0)
    for k in range(100):                                        # 50 Hz states
        t = T0 + k * 20 * MS
        _offer(rec, "state/vehicle", VehicleState(header=Header(stamp_ns=t), position_m=Vector3.from_array(VEHICLE),
                                                  orientation=Quaternion.from_array(q)), t)
        if k % 5 or not k:
            continue
        stamp = t - 40 * MS                                     # the image, 40 ms old when its boxes come
        hdr = Header(stamp_ns=stamp, frame_id="camera_left_optical")
        _offer(rec, "sensors/camera/left/image", Image.from_numpy(left, "mono8", hdr), stamp + 5 * MS)
        _offer(rec, "sensors/camera/right/image", Image.from_numpy(right, "mono8", hdr), stamp + 5 * MS)
        if detections:
            _offer(rec, "perception/detections", Detection2DArray(
                header=hdr, image_width=640, image_height=480, detections=[Detection2D(
                    center_x_px=u, center_y_px=v, size_x_px=w, size_y_px=h, class_id=0, class_name="person",
                    score=0.9)]), t)
    rec.close()
    [path] = sink.stats.files
    return str(path), str(scenario)


def test_replay_scores_a_recorded_flight_as_live_does(tmp_path, capsys):
    path, _ = record(tmp_path)
    out = tmp_path / "res.json"
    assert aero(["eval", "objects", "--replay", path, "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "19 detection frames" in printed and "goals: met" in printed and "person" in printed
    res = json.loads(out.read_text())
    p = res["classes"]["person"]
    assert (p["targets"], p["found"], p["missed"], p["duplicates"], p["false_tracks"]) == (1, 1, 0, 0, 0)
    assert p["error_samples"] >= 15 and p["error_p95_m"] < 0.2          # stereo: 6.6 m ahead, where the scenario has it
    assert res["replay"]["placed"] == {"stereo": 19}
    assert res["service"]["frames_processed"] == 19 and res["service"]["frame_cpu_ms_p99"] > 0


def test_replay_takes_objects_parameters_and_refuses_unknown_ones(tmp_path, capsys):
    path, _ = record(tmp_path)
    res = replay(path, overrides={"confirm_hits": "25"})            # 19 frames never confirm a track
    assert res["classes"]["person"]["found"] == 0
    assert aero(["eval", "objects", "--replay", path, "--param", "no_such=1"]) == 2
    assert "--param: unknown parameter 'no_such'" in capsys.readouterr().err


@pytest.mark.parametrize("case, message", [
    ("missing", "no_file.mcap: not a readable MCAP recording"),
    ("no_scenario", "does not name its scenario: give --scenario"),
    ("no_detections", "has no perception/detections: record them"),
])
def test_replay_errors_are_one_line_saying_what_to_do(tmp_path, capsys, case, message):
    if case == "missing":
        path = str(tmp_path / "no_file.mcap")
    else:
        path, _ = record(tmp_path, metadata=case != "no_scenario", detections=case != "no_detections")
    assert aero(["eval", "objects", "--replay", path]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err


def test_live_only_flags_are_refused_with_replay(tmp_path, capsys):
    assert aero(["eval", "objects", "--replay", "x.mcap", "--until-landed"]) == 2
    assert "--until-landed needs --live" in capsys.readouterr().err
    assert aero(["eval", "objects", "--live", "--param", "confirm_hits=2"]) == 2
    assert "--param needs --replay" in capsys.readouterr().err
