"""viz adapters: one of our messages in, Rerun archetypes out (ENU kept as is, quaternions
reordered to x, y, z, w); the registry covers the contract; sampling and frame gating; a
.rrd written by the sink reads back with Rerun's own reader."""
from __future__ import annotations

import math

import numpy as np
import pytest
import rerun as rr

from aerotest import free_port
from aeroperception.schemas import (
    BatteryState, Detection2D, Detection2DArray, DiagnosticStatus, GetMissionReply, Header, Image,
    MissionStatus, NDArray, OccupancyGrid, Odometry, PointCloud, Pose, PoseStamped, Quaternion,
    TrackedObject, TrackedObjectArray, TrajectorySetpoint, Vector3, VehicleState, VioHealth, WaypointReached,
)
from aeroperception.services.runtime.config import build
from aeroperception.services.viz import adapters as A
from aeroperception.services.viz import contract
from aeroperception.services.viz.main import FrameGate, Sampler
from aeroperception.services.viz.rrd import entity_spans
from aeroperception.services.viz.config import VizConfig
from aeroperception.services.viz.viewer import Outputs, ViewerConfigError, ViewerSink


def arrow(archetype, field: str):
    return getattr(archetype, field).as_arrow_array().to_pylist()


def by_path(logs) -> dict:
    out = {}
    for entry in logs:
        out.setdefault(entry.path, []).extend(entry.archetypes)
    return out


def one(logs, path: str, kind):
    found = [a for a in by_path(logs).get(path, []) if isinstance(a, kind)]
    assert len(found) == 1, f"{path}: expected one {kind.__name__}, got {by_path(logs).get(path)}"
    return found[0]


YAW90 = Quaternion(w=math.cos(math.pi / 4), x=0.0, y=0.0, z=math.sin(math.pi / 4))


def state(x=1.0, y=2.0, z=3.0, stamp_ns=1_000_000_000, **kw) -> VehicleState:
    return VehicleState(header=Header(stamp_ns=stamp_ns, frame_id="map"), position_m=Vector3(x=x, y=y, z=z),
                        velocity_mps=Vector3(x=3.0, y=4.0, z=0.0), orientation=YAW90, **kw)


def outputs(**over) -> Outputs:
    return build(Outputs, contract.PARAMS, **over)


# ---------------------------------------------------------------- pose, trajectory, VIO


def test_vehicle_pose_translation_on_root_attitude_on_body_in_enu():
    logs = A.VehicleAdapter()(state())
    t = one(logs, "world/vehicle", rr.Transform3D)
    assert arrow(t, "translation") == [[1.0, 2.0, 3.0]]           # ENU, untouched
    body = one(logs, "world/vehicle/body", rr.Transform3D)
    x, y, z, w = arrow(body, "quaternion")[0]
    assert (x, y) == (0.0, 0.0) and z == pytest.approx(math.sin(math.pi / 4)) and w == pytest.approx(math.cos(math.pi / 4))
    assert arrow(one(logs, "series/altitude_m/vehicle", rr.Scalars), "scalars") == [3.0]
    assert arrow(one(logs, "series/speed_mps/vehicle", rr.Scalars), "scalars") == [5.0]
    assert arrow(one(logs, "world/trajectory/vehicle", rr.LineStrips3D), "strips") == [[[1.0, 2.0, 3.0]]]


def test_trail_decimates_by_distance_resends_by_period_and_is_bounded():
    trail = A.Trail("world/trajectory/x", (0, 0, 0), period_s=0.5, max_points=3, min_step_m=0.1)
    assert trail(0, Vector3(x=0.0))                        # first point: sent
    assert trail(100_000_000, Vector3(x=1.0)) == []        # within the period: kept, not sent
    trail(200_000_000, Vector3(x=1.01))                    # closer than min_step: not kept
    trail(300_000_000, Vector3(x=2.0))
    sent = trail(600_000_000, Vector3(x=3.0))
    strip = arrow(sent[0].archetypes[0], "strips")[0]
    assert [p[0] for p in strip] == [1.0, 2.0, 3.0]        # bounded to the newest 3
    assert trail(700_000_000, Vector3(x=float("nan"))) == []


def test_truth_pose_and_track_beside_the_estimate():
    logs = A.TruthAdapter()(state(x=5.0))
    t = one(logs, "world/truth/vehicle", rr.Transform3D)
    assert arrow(t, "translation") == [[5.0, 2.0, 3.0]]
    assert "world/trajectory/truth" in by_path(logs) and "series/altitude_m/truth" in by_path(logs)


def test_covariance_ellipsoid_axes_reconstruct_the_covariance():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(3, 3))
    cov = a @ a.T + 0.1 * np.eye(3)
    half, q = A.covariance_ellipsoid(cov, n_sigma=2.0)
    from aeroperception.services.runtime.rotations import quat_to_rotmat
    r = quat_to_rotmat(q)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ np.diag((half / 2.0) ** 2) @ r.T, cov, atol=1e-9)
    assert A.covariance_ellipsoid(np.full((3, 3), np.nan)) is None


def test_vio_pose_with_covariance_ellipsoid_at_the_estimate():
    cov = np.diag([0.04, 0.01, 0.09, 0.001, 0.001, 0.001])
    msg = Odometry(header=Header(stamp_ns=5, frame_id="odom"),
                   pose=Pose(position=Vector3(x=1.0, y=-1.0, z=2.0), orientation=YAW90),
                   pose_covariance=NDArray.from_numpy(cov))
    logs = A.VioAdapter()(msg)
    assert arrow(one(logs, "world/vio", rr.Transform3D), "translation") == [[1.0, -1.0, 2.0]]
    ell = one(logs, "world/vio_covariance", rr.Ellipsoids3D)
    assert arrow(ell, "centers") == [[1.0, -1.0, 2.0]]
    assert sorted(arrow(ell, "half_sizes")[0]) == pytest.approx([0.2, 0.4, 0.6])   # 2 sigma
    no_cov = A.VioAdapter()(Odometry(header=Header(stamp_ns=5)))
    assert "world/vio_covariance" not in by_path(no_cov)


def test_vio_health_text_only_on_state_change():
    ad = A.VioHealthAdapter()
    first = ad(VioHealth(state=1, tracked_features=120))
    assert arrow(one(first, "logs/vio", rr.TextLog), "text") == ["VIO TRACKING: "]
    assert "logs/vio" not in by_path(ad(VioHealth(state=1, tracked_features=110)))
    lost = ad(VioHealth(state=3, message="no features"))
    assert arrow(one(lost, "logs/vio", rr.TextLog), "level") == ["ERROR"]


# ---------------------------------------------------------------- cameras and boxes


def test_image_jpeg_decodes_to_the_same_picture_size_and_raw_when_quality_is_zero():
    cv2 = pytest.importorskip("cv2")
    px = np.zeros((48, 64, 3), np.uint8)
    px[:, :32] = (255, 0, 0)                                 # left half red (RGB)
    msg = Image.from_numpy(px, "rgb8", Header(stamp_ns=1, frame_id="camera_left_optical"))
    enc = one(A.ImageAdapter("left", 90)(msg), "camera/left/image", rr.EncodedImage)
    assert arrow(enc, "media_type") == ["image/jpeg"]
    blob = bytes(arrow(enc, "blob")[0])
    bgr = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_COLOR)
    assert bgr.shape == (48, 64, 3) and bgr[10, 5, 2] > 200 and bgr[10, 5, 0] < 50   # still red
    raw = one(A.ImageAdapter("right", 0)(msg), "camera/right/image", rr.Image)
    assert raw is not None
    mono = A.image_archetype(Image.from_numpy(np.zeros((4, 6), np.uint8), "mono8"), 0)
    assert isinstance(mono, rr.Image)


def test_detections_become_labelled_boxes_on_the_camera_of_their_frame():
    msg = Detection2DArray(header=Header(stamp_ns=7, frame_id="camera_right_optical"), detections=[
        Detection2D(center_x_px=100, center_y_px=50, size_x_px=20, size_y_px=10, class_id=2, class_name="car", score=0.9)])
    boxes = one(A.BoxesAdapter("detections", (0, 0, 0))(msg), "camera/right/image/detections", rr.Boxes2D)
    assert arrow(boxes, "centers") == [[100.0, 50.0]] and arrow(boxes, "half_sizes") == [[10.0, 5.0]]
    assert arrow(boxes, "labels") == ["car 0.90"] and arrow(boxes, "class_ids") == [2]
    empty = A.BoxesAdapter("truth_boxes", (0, 0, 0))(Detection2DArray(header=Header(frame_id="camera_left_optical")))
    one(empty, "camera/left/image/truth_boxes", rr.Clear)


def test_tracks_are_labelled_points_with_their_history_and_tentative_ones_grey():
    ad = A.ObjectsAdapter(max_points=3, forget_after=2)

    def frame(*tracks):
        return TrackedObjectArray(header=Header(stamp_ns=1, frame_id="map"), objects=[
            TrackedObject(track_id=tid, class_name=name, class_id=cid, confirmed=conf, best_score=score,
                          position_m=Vector3(x=x, y=0.0, z=0.5)) for tid, name, cid, conf, score, x in tracks])

    for x in (1.0, 2.0, 3.0, 4.0):
        logs = ad(frame((7, "person", 0, True, 0.91, x), (8, "car", 2, False, 0.40, 10.0)))
    tracks = one(logs, "world/objects/tracks", rr.Points3D)
    assert arrow(tracks, "labels") == ["person #7 0.91", "car #8 0.40"]
    assert arrow(tracks, "positions") == [[4.0, 0.0, 0.5], [10.0, 0.0, 0.5]]
    colors = arrow(tracks, "colors")
    assert colors[0] != colors[1]                        # the tentative car is drawn apart
    history = one(logs, "world/objects/history", rr.LineStrips3D)
    assert arrow(history, "strips") == [[[2.0, 0.0, 0.5], [3.0, 0.0, 0.5], [4.0, 0.0, 0.5]]]   # bounded, confirmed only
    for _ in range(3):                                   # the person is gone: cleared, then forgotten
        logs = ad(frame())
    one(logs, "world/objects/tracks", rr.Clear)
    assert 7 not in ad.history


# ---------------------------------------------------------------- LiDAR and costmap


def test_clouds_in_the_world_frame_only():
    pts = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    conv = A.cloud_adapter("obstacles", (1, 2, 3), 0.1)
    p = one(conv(PointCloud.from_numpy(pts, header=Header(frame_id="map"))), "world/perception/obstacles", rr.Points3D)
    assert arrow(p, "positions") == pts.tolist()
    assert conv(PointCloud.from_numpy(pts, header=Header(frame_id="lidar_level"))) == []


def test_costmap_grid_on_the_ground_at_its_origin_unknown_as_255():
    grid = np.array([[0, 50, 100], [-1, 0, 0]], np.int8)
    msg = OccupancyGrid(header=Header(frame_id="map"), resolution_m=0.5, width=3, height=2,
                        origin=Pose(position=Vector3(x=-10.0, y=4.0, z=0.0)), data=NDArray.from_numpy(grid))
    g = one(A.costmap(msg), "world/perception/costmap", rr.GridMap)
    assert arrow(g, "cell_size") == [0.5]
    assert arrow(g, "translation")[0][:2] == [-10.0, 4.0]
    assert bytes(arrow(g, "data")[0]) == bytes([0, 50, 100, 255, 0, 0])


# ---------------------------------------------------------------- mission, planner, health


def test_mission_state_changes_as_text_not_every_status():
    ad = A.MissionStatusAdapter()
    first = ad(MissionStatus(state="TAKEOFF", mission_id="m1", distance_to_goal_m=2.0))
    assert arrow(one(first, "logs/mission", rr.TextLog), "text") == ["TAKEOFF [m1]"]
    assert "logs/mission" not in by_path(ad(MissionStatus(state="TAKEOFF", mission_id="m1")))
    ex = ad(MissionStatus(state="EXECUTING", mission_id="m1", active_waypoint=0, total_waypoints=4))
    assert arrow(one(ex, "logs/mission", rr.TextLog), "text") == ["EXECUTING waypoint 1/4 [m1]"]


def test_active_goal_point_and_hold_clears_it():
    g = PoseStamped(header=Header(frame_id="map"), pose=Pose(position=Vector3(x=10.0, y=0.0, z=5.0)))
    assert arrow(one(A.active_goal(g), "world/mission/active_goal", rr.Points3D), "positions") == [[10.0, 0.0, 5.0]]
    one(A.active_goal(PoseStamped(header=Header(frame_id="hold"))), "world/mission/active_goal", rr.Clear)


def test_mission_waypoints_from_the_loaded_mission():
    reply = GetMissionReply(success=True, mission_id="m", num_waypoints=2, mission_json=(
        '{"mission_id": "m", "waypoints": [{"x": 0, "y": 0, "z": 5}, {"x": 10, "y": 0, "z": 5}]}'))
    pts = one(A.mission_waypoints(reply), "world/mission/waypoints", rr.Points3D)
    assert arrow(pts, "positions") == [[0.0, 0.0, 5.0], [10.0, 0.0, 5.0]] and arrow(pts, "labels") == ["1", "2"]
    one(A.mission_waypoints(GetMissionReply(success=False)), "world/mission/waypoints", rr.Clear)


def test_waypoint_reached_markers_accumulate():
    ad = A.WaypointReachedAdapter()
    ad(WaypointReached(index=0, position_m=Vector3(x=1.0)))
    pts = one(ad(WaypointReached(index=1, position_m=Vector3(x=2.0))), "world/mission/reached", rr.Points3D)
    assert arrow(pts, "positions") == [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]


def test_setpoint_velocity_is_an_enu_arrow_on_the_vehicle():
    sp = TrajectorySetpoint(velocity_valid=True, velocity_mps=Vector3(x=1.0, y=-2.0, z=0.5))
    a = one(A.setpoint(sp), "world/vehicle/setpoint", rr.Arrows3D)
    assert arrow(a, "vectors") == [[1.0, -2.0, 0.5]] and arrow(a, "origins") == [[0.0, 0.0, 0.0]]


def test_battery_series():
    logs = A.battery(BatteryState(voltage_v=15.2, remaining_fraction=0.5))
    assert arrow(one(logs, "series/battery_voltage_v", rr.Scalars), "scalars") == [pytest.approx(15.2)]
    assert arrow(one(logs, "series/battery_pct/remaining", rr.Scalars), "scalars") == [50.0]


def test_diagnostics_loop_timing_series_and_text_on_level_change():
    ad = A.DiagnosticsAdapter()
    msg = DiagnosticStatus(name="planner", level=0, message="tracking goal", values={
        "loop[setpoint].work_p99_ms": "0.4", "loop[setpoint].ticks": "100", "total_ms_p99": "12.5", "loop[x].work_p99_ms": "n/a"})
    logs = ad(msg)
    assert arrow(one(logs, "series/loop_work_p99_ms/planner.setpoint", rr.Scalars), "scalars") == [pytest.approx(0.4)]
    assert "series/stage_ms_p99/planner.total" in by_path(logs)
    assert arrow(one(logs, "logs/diagnostics/planner", rr.TextLog), "text") == ["planner: tracking goal"]
    assert "logs/diagnostics/planner" not in by_path(ad(msg))
    assert "logs/diagnostics/planner" not in by_path(ad(DiagnosticStatus(name="planner", level=0, message="holding")))
    warn = ad(DiagnosticStatus(name="planner", level=1, message="holding"))
    assert arrow(one(warn, "logs/diagnostics/planner", rr.TextLog), "level") == ["WARN"]


# ---------------------------------------------------------------- registry, sampling, sink


def test_registry_covers_the_contract_and_names_real_rate_parameters():
    ads = A.build_adapters(build(VizConfig, contract.PARAMS))
    assert {a.key: a.schema for a in ads} == contract.INPUTS
    names = {q.name for q in contract.PARAMS}
    for a in ads:
        assert a.rate_param is None or (a.rate_param in names and a.rate_param in VizConfig.__dataclass_fields__), a.key
        assert a.follows is None or a.follows in contract.INPUTS
    assert {a.key for a in ads if a.truth} == {"sim/truth/state", "sim/truth/boxes"}


def test_sampler_keeps_at_most_the_rate_and_zero_means_off():
    s = Sampler()
    admitted = sum(s.admit("k", 5.0, t * 0.01) for t in range(100))     # 100 Hz for 1 s
    assert admitted == 5
    assert not s.admit("other", 0.0, 0.0)


def test_frame_gate_admits_overlays_of_shown_frames_only():
    g = FrameGate(keep=2)
    g.note("left", 1)
    g.note("left", 2)
    g.note("left", 3)
    assert g.admits("left", 3) and not g.admits("left", 1) and not g.admits("right", 3)


def test_no_output_is_refused_at_start():
    with pytest.raises(ViewerConfigError, match="no output"):
        outputs(web_port=0).check()
    with pytest.raises(ViewerConfigError, match="rerun\\+http"):
        outputs(web_port=0, viewer_url="tcp/1.2.3.4:7447").check()


def test_sink_saves_an_rrd_that_reads_back_with_entities_over_the_stamps(tmp_path):
    path = tmp_path / "v.rrd"
    sink = ViewerSink(outputs(web_port=0, save_path=str(path)))
    sink.write(1, A.static_scene())
    ad = A.VehicleAdapter(trail_period_s=0.1)
    t0 = 1_800_000_000_000_000_000
    for i in range(20):
        m = state(x=0.1 * i, stamp_ns=t0 + i * 50_000_000)
        sink.write(m.header.stamp_ns, ad(m))
    sink.close()
    spans = entity_spans(str(path))
    v = spans["/world/vehicle"]
    assert v.rows == 20 and (v.first_ns, v.last_ns) == (t0, t0 + 19 * 50_000_000)
    assert spans["/world/vehicle/body/model"].first_ns is None          # static body model
    assert spans["/world/trajectory/vehicle"].rows >= 9


def test_spawned_viewer_is_asked_for_with_the_sinks_own_recording(monkeypatch, tmp_path):
    """rr.spawn without recording= looks for a global recording, finds none (the sink has its own
    stream) and silently spawns nothing: `aero viz` showed no viewer."""
    calls = []
    monkeypatch.setattr(rr, "spawn", lambda **kw: calls.append(kw))
    monkeypatch.setattr(rr, "GrpcSink", lambda url: rr.FileSink(str(tmp_path / "stand-in.rrd")))  # no viewer here
    sink = ViewerSink(outputs(web_port=0, spawn=True, grpc_port=free_port()))
    try:
        assert len(calls) == 1 and calls[0]["recording"] is sink.rec and calls[0]["connect"] is False
    finally:
        sink.close(timeout_s=0.1)


# ---------------------------------------------------------------- `aero viz` flags


def viz_args(*argv: str):
    import argparse

    from aeroperception.tools.cli import viz as cmd_viz

    parser = argparse.ArgumentParser()
    cmd_viz.register(parser.add_subparsers())
    return cmd_viz.viz_argv(parser.parse_args(["viz", *argv]))


def test_aero_viz_flags_become_viz_parameters():
    argv = viz_args("--web", "9090", "--save", "f.rrd", "--no-truth", "--connect", "tcp/10.0.0.2:7447")
    params = [argv[i + 1] for i, a in enumerate(argv) if a == "--param"]
    assert params == ["web_port=9090", "save_path=f.rrd", "show_truth=false"]
    assert argv[argv.index("--connect") + 1] == "tcp/10.0.0.2:7447"      # --connect stays the Zenoh router
    viewer = viz_args("--viewer", "rerun+http://laptop:9876/proxy")
    assert "viewer_url=rerun+http://laptop:9876/proxy" in viewer and "spawn=true" not in viewer


def test_aero_viz_without_outputs_spawns_the_native_viewer_or_says_what_to_do(monkeypatch):
    from aeroperception.tools.cli import viz as cmd_viz
    from aeroperception.tools.common import CliError

    monkeypatch.setattr(cmd_viz.shutil, "which", lambda name: "/usr/bin/rerun")
    assert "spawn=true" in viz_args()
    monkeypatch.setattr(cmd_viz.shutil, "which", lambda name: None)
    with pytest.raises(CliError, match="--web PORT"):
        viz_args()
    with pytest.raises(CliError, match="--viewer URL"):
        viz_args("--connect", "rerun+http://laptop:9876/proxy")
