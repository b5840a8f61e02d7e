"""`aero up --profile vehicle` against a flight controller that is not our sim service: the
simulated PX4 run standalone (MAVLink only, no Zenoh), as a real PX4 SITL would be. fmu alone
must give the stack its state and, with no simulator, the IMU (HIGHRES_IMU -> sensors/imu); the
recorder keeps the flight within its disk budget."""
from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from aeroperception.schemas import DiagnosticStatus, Imu, VehicleState
from aeroperception.services.recorder.files import info, is_indexed
from aeroperception.services.recorder import contract as recorder_contract
from aeroperception.services.recorder.logic import SinkConfig, split_files
from aeroperception.services.runtime.config import build
from aeroperception.tools.cli.up import load_profiles
from aerotest import free_port, sample_stream, standalone_fc, wait_for_message


def test_vehicle_profile_fmu_bridges_a_standalone_px4_and_republishes_its_imu(stack, tmp_path):
    fcu_port = free_port()
    with standalone_fc(fcu_port, tmp_path / "fc.log"):
        st = stack(["fmu"], profile="vehicle", extra_args=["--fcu-url", f"udpin:127.0.0.1:{fcu_port}"])
        state = wait_for_message(st.session, "state/vehicle", VehicleState, lambda m: m.connected, timeout_s=15)
        assert state.flight_mode and abs(state.position_m.z) < 0.5

        imu, rate_hz = sample_stream(st.session, "sensors/imu", Imu, 100, 2.0)
        stamps = [m.header.stamp_ns for m in imu]
        accel_z = [m.linear_acceleration_mps2.z for m in imu]
        assert rate_hz > 50, f"sensors/imu at {rate_hz:.1f} Hz (FC streams HIGHRES_IMU at 100 Hz)"
        assert np.all(np.diff(stamps) > 0), "IMU stamps not strictly increasing"
        # FLU body frame, specific force: a vehicle at rest on the ground reads about +g on z.
        assert abs(float(np.median(accel_z)) - 9.81) < 0.5, np.median(accel_z)


def dir_bytes(path: Path) -> int:
    total = 0
    for f in path.glob("*.mcap"):
        try:
            total += f.stat().st_size
        except FileNotFoundError:   # rotated out between the listing and the stat
            pass
    return total


def profile_params(flags: list[str]) -> dict[str, int]:
    return {k: int(v) for k, _, v in (flags[i + 1].partition("=") for i in range(0, len(flags), 2)
                                      if flags[i] == "--param")}


def test_vehicle_profile_records_the_flight_within_its_disk_budget(stack, tmp_path):
    """A real vehicle records its essentials (it ran no recorder), with a disk budget: the
    profile's own budget is sane, and a real recording with a small budget rotates its oldest
    files out while the directory stays under the budget the whole time."""
    vehicle = load_profiles()["vehicle"]
    assert "recorder" in vehicle["services"]
    own = profile_params(vehicle["args"]["recorder"])
    build(SinkConfig, recorder_contract.PARAMS, output_dir=Path("."), max_bag_size=own["max_bag_size"],
          max_total_size=own["max_total_size"]).check()
    assert own["max_total_size"] >= 8 * own["max_bag_size"]

    out = tmp_path / "recordings"
    split, chunk = 1 << 16, 1 << 14
    budget = 4 * split + chunk
    fcu_port = free_port()
    with standalone_fc(fcu_port, tmp_path / "fc.log"):
        st = stack(["fmu", "recorder"], profile="vehicle", extra_args=[
            "--fcu-url", f"udpin:127.0.0.1:{fcu_port}", "--arg", f"recorder:--param=output_dir={out}",
            "--arg", f"recorder:--param=max_bag_size={split}", "--arg", f"recorder:--param=chunk_size={chunk}",
            "--arg", f"recorder:--param=max_total_size={budget}", "--arg", "recorder:--param=compression=none",
            "--arg", "recorder:--param=keys=sensors/imu"])   # + the FC's IMU: ~60 kB/s, a new file every ~1 s
        peak, done = [0], threading.Event()

        def watch_disk() -> None:        # the directory's size every 50 ms while recording
            while not done.wait(0.05):
                peak[0] = max(peak[0], dir_bytes(out))

        watcher = threading.Thread(target=watch_disk, daemon=True)
        watcher.start()
        t0 = time.monotonic()
        try:
            wait_for_message(st.session, "diagnostics/recorder", DiagnosticStatus,
                             lambda d: int(d.values.get("rotated_out_files", 0)) >= 3, timeout_s=60)
        finally:
            done.set()
            watcher.join(2)
        rotate_s = time.monotonic() - t0
        st.stop()
    kept = split_files(out, "aero")
    assert peak[0] <= budget, f"directory peaked at {peak[0]} B over the {budget} B budget"
    assert sum(f.stat().st_size for f in kept) <= budget and len(kept) >= 2, rotate_s
    # what is left is the newest files, complete, each with the flight's state, back to back
    files = [info(f) for f in kept]
    assert all(is_indexed(f) for f in kept)
    # the stop cuts the newest file at any moment (it opens on the rotation the wait ends on), so
    # state/vehicle (50 Hz) is required in it only once it spans 0.1 s
    for fi in files:
        topics = {c.topic for c in fi.channels if c.count}
        want = {"state/vehicle", "sensors/imu"} if fi is not files[-1] or fi.duration_s >= 0.1 else {"sensors/imu"}
        assert topics >= want, (fi.path, topics, fi.duration_s)
    gaps = [b.start_ns - a.end_ns for a, b in zip(files, files[1:])]
    assert all(0 <= g < 0.2e9 for g in gaps), gaps
