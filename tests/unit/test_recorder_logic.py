"""The recorder's logic without Zenoh: presets, the MCAP sink (plain readers, splits, flush
interval, disk errors), recover, replay timing and the Foxglove export."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from aeroperception.schemas import (
    DiagnosticArray, DiagnosticStatus, Header, Image, MissionStatus, NDArray, OccupancyGrid, Odometry, PointCloud,
    VehicleState, Vector3, encode, schema_id,
)
from aeroperception.services.recorder import contract
from aeroperception.services.recorder.files import info, is_indexed, recover, scan
from aeroperception.services.recorder.logic import (
    KeyFilter, McapSink, Recording, Sample, SinkConfig, rotation_victims, select_keys, split_files,
)
from aeroperception.services.recorder.replay import CLOCK_KEY, Recorded, Replayer
from aeroperception.services.runtime import ParamError, ParamSet
from aeroperception.services.runtime.config import build
from aeroperception.services.runtime.node import encoding_for


def sink_config(output_dir: Path, **kw) -> SinkConfig:
    """The defaults of the recorder's parameters, writing to output_dir (and `kw` set)."""
    return build(SinkConfig, contract.PARAMS, output_dir=output_dir, **kw)


def sample(msg, key: str, t_ns: int) -> Sample:
    return Sample(key, str(encoding_for(type(msg))), encode(msg), t_ns)


def state(i: int) -> VehicleState:
    return VehicleState(header=Header(stamp_ns=i, frame_id="map"), position_m=Vector3(x=i * 0.1, y=0.0, z=2.0),
                        flight_mode="OFFBOARD")


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_essentials_preset_is_seed_list_mapped_and_images_only_when_asked():
    keys = select_keys("essentials")
    assert "state/vehicle" in keys and "diagnostics/agg" in keys and "fmu/out/battery_status" in keys
    assert not any("image" in k for k in keys)
    assert select_keys("essentials", ["sensors/imu", "state/vehicle"], record_images=True)[-2:] == \
        ["sensors/imu", "sensors/camera/*/image"]
    f = KeyFilter(select_keys("all"), record_images=False)
    assert f.accept(0, "sensors/imu") and not f.accept(0, "sensors/camera/left/image")
    f = KeyFilter(["state/vehicle", "**"], record_images=False)   # a key under two expressions: once
    assert f.accept(0, "state/vehicle") and not f.accept(1, "state/vehicle")
    with pytest.raises(ValueError, match="presets"):
        select_keys("everything")


def test_recording_decodes_with_plain_mcap_reader_and_plain_msgpack(tmp_path):
    sink = McapSink(sink_config(tmp_path), {"aeroperception": {"scenario": "open_field"}})
    rec = Recording(sink, 1 << 20).start()
    for i in range(50):
        assert rec.offer("state/vehicle", str(encoding_for(VehicleState)), encode(state(i)), 1_000_000_000 + i * 20_000_000)
    rec.add_metadata("params/planner", {"kp": "0.8"})
    rec.close()
    [path] = sink.stats.files
    with open(path, "rb") as f:
        reader = make_reader(f)
        got = [(s, c, m) for s, c, m in reader.iter_messages()]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert len(got) == 50
    s, c, m = got[7]
    assert c.topic == "state/vehicle" and c.message_encoding == "msgpack"
    assert s.name == "VehicleState@1" and s.encoding == "jsonschema"
    assert json.loads(s.data)["$defs"]["VehicleState"]["properties"]["flight_mode"]["type"] == "string"
    assert c.metadata["zenoh_encoding"] == "application/msgpack;VehicleState@1"
    plain = msgpack.unpackb(m.data)
    assert plain["position_m"]["x"] == pytest.approx(0.7) and plain["flight_mode"] == "OFFBOARD"
    assert m.log_time == 1_000_000_000 + 7 * 20_000_000
    assert meta["aeroperception"]["scenario"] == "open_field" and meta["params/planner"] == {"kp": "0.8"}


def test_splits_past_max_bag_size_each_file_complete(tmp_path):
    cfg = sink_config(tmp_path, max_bag_size=1 << 16, chunk_size=1 << 14, compression="none")
    clock = FakeClock()
    sink = McapSink(cfg, {"aeroperception": {"preset": "x"}}, clock=clock)
    payload = bytes(range(256)) * 4
    n = 400
    for i in range(n):
        clock.t = i * 0.01
        sink.write([Sample("blob", "application/octet-stream", payload, i)])
    sink.close()
    files = sink.stats.files
    assert len(files) >= 4
    total = 0
    for p in files:
        assert is_indexed(p)
        fi = info(p)
        total += fi.messages
        assert fi.metadata["aeroperception"] == {"preset": "x"}          # each split stands alone
        assert (tmp_path / p).stat().st_size <= cfg.max_bag_size + 4096   # + the summary
    assert total == n


def dir_bytes(path) -> int:
    return sum(f.stat().st_size for f in path.glob("*.mcap"))


def test_rotation_deletes_the_oldest_first_until_the_new_split_fits(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    assert rotation_victims([(a, 40), (b, 40), (c, 40)], max_total_size=150, reserve=50) == [a]
    assert rotation_victims([(a, 40), (b, 40), (c, 40)], max_total_size=170, reserve=50) == []
    assert rotation_victims([(a, 40), (b, 40)], max_total_size=30, reserve=50) == [a, b]   # cannot fit: all


def test_split_files_are_ours_only_oldest_first_by_start_then_split_number(tmp_path):
    names = ["aero_20260101T000000Z_10.mcap", "aero_20260101T000000Z_2.mcap", "aero_20251231T230000Z_0.mcap",
             "aero_notes.mcap", "other_20250101T000000Z_0.mcap", "aero_20260101T000000Z_3.mcap.bak"]
    for n in names:
        (tmp_path / n).write_bytes(b"x")
    assert [p.name for p in split_files(tmp_path, "aero")] == \
        ["aero_20251231T230000Z_0.mcap", "aero_20260101T000000Z_2.mcap", "aero_20260101T000000Z_10.mcap"]


def test_a_budget_below_two_splits_is_refused():
    with pytest.raises(ValueError, match="max_total_size"):
        sink_config(Path("."), max_bag_size=1 << 16, chunk_size=1 << 14, max_total_size=1 << 17).check()
    sink_config(Path("."), max_bag_size=1 << 16, chunk_size=1 << 14, max_total_size=(1 << 17) + (1 << 14)).check()


def test_rotation_keeps_the_directory_within_budget_while_recording(tmp_path):
    """Older flights go first, then this flight's oldest splits; a foreign file and another
    recorder's live file are never touched; every file left is complete."""
    budget = 5 * (1 << 16)
    old_flight = tmp_path / "aero_20200101T000000Z_0.mcap"
    old_flight.write_bytes(b"\x00" * (1 << 16))                # cut short (no closing magic), long ago
    os.utime(old_flight, (1e9, 1e9))
    foreign = tmp_path / "aero_notes.mcap"
    foreign.write_bytes(b"\x00" * 1000)
    live = tmp_path / "aero_20200101T000001Z_0.mcap"            # another recorder's file being written
    live.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 5000)
    cfg = sink_config(tmp_path, max_bag_size=1 << 16, chunk_size=1 << 14, compression="none", max_total_size=budget)
    cfg.check()
    clock = FakeClock()
    sink = McapSink(cfg, clock=clock)
    payload = bytes(range(256)) * 4
    n, peak = 1500, 0
    for i in range(n):
        clock.t = i * 0.01
        sink.write([Sample("blob", "application/octet-stream", payload, i)])
        peak = max(peak, dir_bytes(tmp_path))
    sink.close()
    assert peak <= budget and dir_bytes(tmp_path) <= budget
    written = sink.stats.files
    assert len(written) >= 15 and not old_flight.exists() and sink.stats.deleted[0] == str(old_flight)
    assert foreign.exists() and live.exists()
    kept = [p for p in written if Path(p).exists()]
    assert kept == written[-len(kept):] and len(kept) >= 2                # the newest splits are kept
    assert sink.stats.deleted[1:] == written[:len(written) - len(kept)]   # this flight's oldest went first
    assert all(is_indexed(p) for p in kept)
    assert sum(info(p).messages for p in kept) < n                        # (rotation really dropped data)


def test_recorder_parameters_are_read_at_start_so_a_live_set_is_refused():
    params = ParamSet.from_declarations(contract.PARAMS)
    params.update({"max_total_size": 1 << 33})                     # start-up values: taken
    with pytest.raises(ParamError, match="read at start only"):
        params.apply("max_total_size", 1 << 34)                   # live: refused, not ignored
    assert params.max_total_size == 1 << 33


def test_chunks_reach_disk_every_flush_interval_and_recover_indexes_a_cut_file(tmp_path):
    """What a kill -9 leaves: the file as written so far, never finished."""
    clock = FakeClock()
    sink = McapSink(sink_config(tmp_path, flush_interval_s=0.5), clock=clock)
    for i in range(300):                       # 3 s at 100 Hz
        clock.t = i * 0.01
        sink.write([sample(state(i), "state/vehicle", i * 10_000_000)])
    cut = tmp_path / "cut.mcap"
    shutil.copy(sink.path, cut)                # not closed: no summary, no index
    assert not is_indexed(cut)
    res = recover(cut, tmp_path / "fixed.mcap")
    assert is_indexed(tmp_path / "fixed.mcap")
    assert res.messages >= 300 - 0.5 * 100 - 1  # all but at most the last flush interval
    assert info(tmp_path / "fixed.mcap").channels[0].count == res.messages
    # A cut in the middle of a chunk: everything before it is kept.
    data = cut.read_bytes()
    (tmp_path / "half.mcap").write_bytes(data[: len(data) - 500])
    res2 = recover(tmp_path / "half.mcap", tmp_path / "half_fixed.mcap")
    assert 0 < res2.messages <= res.messages and res2.truncated


FSIZE_SCRIPT = textwrap.dedent("""
    import resource, sys
    from pathlib import Path
    from aeroperception.services.recorder import contract
    from aeroperception.services.recorder.logic import McapSink, Sample, SinkConfig
    from aeroperception.services.runtime.config import build
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
    sink = McapSink(build(SinkConfig, contract.PARAMS, output_dir=Path(sys.argv[1]), flush_interval_s=0.05,
                          compression="none"))
    import time
    for i in range(2000):
        sink.write([Sample("blob", "application/octet-stream", bytes(1000), i)])
        if i % 50 == 0:
            sink.flush()
    sink.close()
    print(sink.error)
    print(sink.path)
""")


def test_file_size_limit_is_an_error_with_reason_and_the_file_stays_readable(tmp_path):
    out = subprocess.run([sys.executable, "-c", FSIZE_SCRIPT, str(tmp_path)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    error, path = out.stdout.strip().splitlines()
    assert "File too large" in error
    sc = scan(path)                            # whole chunks only: the partial one was cut off
    assert not sc.truncated or "EndOfFile" in sc.truncated
    res = recover(path, tmp_path / "fixed.mcap")
    assert res.messages > 100


def test_unwritable_directory_is_an_error_not_an_exception(tmp_path):
    (tmp_path / "file").write_text("x")
    sink = McapSink(sink_config(tmp_path / "file" / "sub"))
    sink.write([sample(state(1), "state/vehicle", 1)])
    sink.close()
    assert sink.failed and "Not a directory" in sink.error


def test_buffer_is_bounded_and_counts_drops(tmp_path):
    rec = Recording(McapSink(sink_config(tmp_path)), max_buffer_bytes=10_000)  # writer not started
    ok = [rec.offer("k", "application/octet-stream", bytes(1000), i + 1) for i in range(25)]
    assert sum(ok) == 10 and rec.dropped == 15 and rec.buffer.bytes == 10_000


def test_sample_before_the_sim_clock_started_is_counted_not_recorded(tmp_path):
    """On sim time the node's clock reads 0 until sim/clock is heard: such a sample would put the
    file's start in 1970 and make a replay wait that long for the next message."""
    rec = Recording(McapSink(sink_config(tmp_path)), max_buffer_bytes=10_000)
    assert not rec.offer("diagnostics/agg", "application/octet-stream", b"x", 0)
    assert rec.offer("diagnostics/agg", "application/octet-stream", b"x", 1_800_000_000_000_000_000)
    assert rec.before_clock == 1 and rec.dropped == 0 and len(rec.buffer.take_all(0)) == 1


def test_replay_keeps_recorded_timing_and_drives_sim_clock():
    clock = FakeClock()
    out = []

    def sleep(dt):
        clock.t += dt

    r = Replayer(lambda k, p, e: out.append((clock.t, k, p, e)), rate=2.0, now=clock, sleep=sleep, spin_s=0.0)
    msgs = [Recorded("state/vehicle", "application/msgpack;VehicleState@1", bytes([i]), 5_000_000_000 + i * 100_000_000)
            for i in range(11)]
    r.run(msgs)
    data = [(t, p) for t, k, p, e in out if k == "state/vehicle"]
    assert [p for _, p in data] == [bytes([i]) for i in range(11)]
    for i, (t, _) in enumerate(data):
        assert t == pytest.approx(i * 0.05, abs=0.002)          # 100 ms apart at rate 2
    ticks = [(t, p) for t, k, p, e in out if k == CLOCK_KEY]
    assert len(ticks) >= 45
    stamp = msgpack.unpackb(ticks[-1][1])["header"]["stamp_ns"]
    assert stamp == pytest.approx(5_000_000_000 + ticks[-1][0] * 2 * 1e9, abs=2e7)


def test_foxglove_export_validates_against_foxglove_schemas(tmp_path):
    jsonschema = pytest.importorskip("jsonschema")
    pytest.importorskip("foxglove_schemas_protobuf")
    from aeroperception.services.recorder.foxglove import export, foxglove_json_schema

    h = Header(stamp_ns=1_700_000_000_123_456_789, frame_id="map")
    grid = OccupancyGrid(header=h, resolution_m=0.5, width=4, height=3, data=NDArray.from_numpy(np.zeros((3, 4), "int8")))
    msgs = [
        ("state/vehicle", state(5)),
        ("state/visual_odometry", Odometry(header=Header(stamp_ns=2, frame_id="odom"))),
        ("sensors/camera/left/image", Image.from_numpy(np.zeros((4, 6, 3), "uint8"), header=h)),
        ("perception/obstacles", PointCloud.from_numpy(np.ones((5, 3)), intensity=np.ones(5), header=h)),
        ("perception/costmap", grid),
        ("diagnostics/agg", DiagnosticArray(header=h, status=[DiagnosticStatus(name="fmu", level=2, message="link lost")])),
        ("mission/status", MissionStatus(header=h, state="EXECUTING")),
    ]
    sink = McapSink(sink_config(tmp_path))
    sink.write([sample(m, k, 10 + i) for i, (k, m) in enumerate(msgs)])
    sink.close()
    out = tmp_path / "fox.mcap"
    counts = export(sink.path, str(out))
    assert counts["state/vehicle/tf"] == 1 and len(counts) == len(msgs) + 1
    seen = {}
    with open(out, "rb") as f:
        for s, c, m in make_reader(f).iter_messages():
            assert c.message_encoding == "json" and s.encoding == "jsonschema"
            obj = json.loads(m.data)
            jsonschema.validate(obj, json.loads(s.data))
            if s.name.startswith("foxglove."):
                assert json.loads(s.data) == foxglove_json_schema(s.name.removeprefix("foxglove."))
            seen[c.topic] = (s.name, obj)
    assert seen["state/vehicle"][0] == "foxglove.PoseInFrame"
    assert seen["state/vehicle/tf"][0] == "foxglove.FrameTransform"
    assert seen["sensors/camera/left/image"][0] == "foxglove.RawImage"
    assert seen["perception/obstacles"][0] == "foxglove.PointCloud"
    assert seen["perception/obstacles"][1]["point_stride"] == 16
    assert seen["perception/costmap"][0] == "foxglove.Grid"
    assert seen["diagnostics/agg"] == ("foxglove.Log", seen["diagnostics/agg"][1])
    assert seen["diagnostics/agg"][1]["level"] == 4 and seen["diagnostics/agg"][1]["name"] == "fmu"
    assert seen["mission/status"][0] == schema_id(MissionStatus)
    assert seen["state/vehicle"][1]["timestamp"] == {"sec": 0, "nsec": 5}


def test_cli_errors_are_one_line_with_what_to_do(tmp_path, capsys):
    from aeroperception.tools.cli import main

    assert main(["mcap", "info", str(tmp_path / "none.mcap")]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    assert main(["mcap", "recover", str(tmp_path / "junk.mcap")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    clock = FakeClock()
    sink = McapSink(sink_config(tmp_path, flush_interval_s=0.1), clock=clock)
    for i in range(20):
        clock.t = i * 0.05
        sink.write([sample(state(i), "state/vehicle", i)])
    cut = tmp_path / "cut.mcap"
    shutil.copy(sink.path, cut)
    assert main(["replay", str(cut)]) == 2
    err = capsys.readouterr().err
    assert "aero mcap recover" in err and len(err.strip().splitlines()) == 1
    assert main(["mcap", "recover", str(cut)]) == 0
    assert main(["mcap", "info", str(tmp_path / "cut.recovered.mcap")]) == 0
    out = capsys.readouterr().out
    assert "state/vehicle" in out and "VehicleState@1" in out
