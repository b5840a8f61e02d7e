"""tools/bench/vio_replay (the VIO CPU figure of docs/results/perception.md): it records the sim's stereo frames and IMU
as the sim encodes them, replays them through the service's decoding and strategy with a CPU time
per frame, and its estimates track the recorded truth."""
from __future__ import annotations

import json
import pickle

from aeroperception.tools.bench import vio_replay


def test_records_and_replays_the_services_work_per_frame(tmp_path, capsys):
    data_path = tmp_path / "inputs.pkl"
    vio_replay.record(40, str(data_path))
    data = pickle.loads(data_path.read_bytes())
    assert len(data["frames"]) == 40 and len(data["truth"]) == 40 and len(data["imu"]) > 300
    assert vio_replay.main(["run", str(data_path), "--poses", str(tmp_path / "est.json")]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames"] == 35 and 0 < summary["median"] <= summary["p99"]
    assert summary["tracking"] >= 30 and summary["ate_m"] < 0.1, summary
    est = json.loads((tmp_path / "est.json").read_text())
    assert len(est["cpu_ms"]) == 40 and sum(p is not None for p in est["poses"]) >= 30
