"""`aero up --profile vehicle --sensors-file FILE`: a real vehicle's perception from its own
sensors. A flight controller that is not our simulator (the simulated PX4 standalone, MAVLink
only), a stereo camera that is two folders of real EuRoC images with its Kalibr calibration, and a
Velodyne that is a real HDL-32E capture replayed over loopback UDP (`aero play pcap --loop`): every
service the file brings comes up healthy, and the costmap marks what the capture saw."""
from __future__ import annotations

import socket
import subprocess

import numpy as np
import pytest
import yaml
from scipy.spatial import cKDTree

from aeroperception.schemas import DiagnosticStatus, OccupancyGrid, VehicleState
from aeroperception.services.lib.lidar.pcap import read_udp
from aeroperception.services.lib.lidar.velodyne import VelodyneDecoder
from aeroperception.services.runtime.data import shared_data_dir
from aeroperception.services.runtime.rotations import quat_to_rotmat
from aeroperception.tools.harness.stack import Stack
from aerotest import aero_argv, clean_env, euroc_camchain, free_port, poll_until, standalone_fc, wait_for_message

DATA = shared_data_dir()
MAV = DATA / "euroc" / "V1_01_easy_start" / "mav0" if DATA else None
HDL32 = DATA / "lidar_pcap" / "velodyne" / "hdl32_example.pcap" if DATA else None
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(MAV is None or not MAV.is_dir(), reason="../shared/data absent")]
SERVICES = ["fmu", "planner", "mission", "diagnostics", "camera", "vio", "detector", "objects", "lidar_driver", "lidar", "perception"]
LIDAR_Z_M = 0.3


def sensors_file(folder, lidar_port: int):
    euroc_camchain(MAV, folder / "camchain.yaml")
    path = folder / "sensors.yaml"
    path.write_text(yaml.safe_dump({
        "camera": {"driver": "camera", "params": {
            "source": str(MAV / "cam0" / "data"), "source_right": str(MAV / "cam1" / "data"), "layout": "stereo",
            "calibration_path": "camchain.yaml", "loop": True}},
        "lidar": {"driver": "lidar_driver",
                  "params": {"device_ip": "127.0.0.1", "bind_address": "127.0.0.1", "port": lidar_port},
                  "mount": {"z_m": LIDAR_Z_M}},
        "imu": "fc"}))
    return path


def capture_points() -> np.ndarray:
    dec = VelodyneDecoder()
    return np.concatenate([dec.decode(d.payload).xyz_m for d in read_udp(HDL32) if d.dst[1] == 2368])


def test_a_vehicle_with_a_sensors_file_perceives_with_every_service_healthy(tmp_path):
    fcu_port, lidar_port = free_port(), free_port(socket.SOCK_DGRAM)
    path = sensors_file(tmp_path, lidar_port)
    player = None
    with standalone_fc(fcu_port, tmp_path / "fc.log"):
        st = Stack(tmp_path / "stack", SERVICES, profile="vehicle",
                   extra_args=["--fcu-url", f"udpin:127.0.0.1:{fcu_port}", "--sensors-file", str(path)])
        try:
            with open(tmp_path / "play.log", "wb") as log:
                player = subprocess.Popen(aero_argv() + ["play", "pcap", str(HDL32), "--port", f"2368={lidar_port}", "--loop"],
                                          stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                          env=clean_env())
            perceivers = SERVICES[SERVICES.index("camera"):]
            last: dict[str, DiagnosticStatus] = {}

            def all_ok() -> bool:
                last.update({s: st.latest_diag(s, 1.0) for s in perceivers})
                return all(d.values and d.level == DiagnosticStatus.OK for d in last.values())

            if not poll_until(all_ok, 90, 0.5):
                raise AssertionError("not every sensor and perception service OK within 90 s: "
                                     + "; ".join(f"{s}: {d.level} {d.message}" for s, d in last.items()))
            # on the ground the costmap only clears (every return grazes the ground): take off
            st.wait_flight_ready(30)
            r = st.aero("mission", "command", "TAKEOFF", timeout_s=20)
            assert r.returncode == 0, r.stdout + r.stderr
            state = wait_for_message(st.session, "state/vehicle", VehicleState,
                                     lambda m: m.landed_state == VehicleState.LANDED_STATE_IN_AIR and m.position_m.z > 1.5, timeout_s=30)
            grid = wait_for_message(st.session, "perception/costmap", OccupancyGrid,
                                    lambda g: int((g.data.to_numpy() == OccupancyGrid.OCCUPIED).sum()) > 0, timeout_s=20)
            state = wait_for_message(st.session, "state/vehicle", VehicleState, lambda m: True, timeout_s=5)
            lidar = st.latest_diag("lidar")
        finally:
            if player is not None and player.poll() is None:
                player.terminate()
                player.wait(10)
            st.stop()
    # every lethal cell is where the capture has a return (the replayed scan, placed with the
    # FC's pose and the declared mount), within a cell's diagonal
    cells = np.argwhere(grid.data.to_numpy() == OccupancyGrid.OCCUPIED)
    centres = np.stack([grid.origin.position.x + (cells[:, 1] + 0.5) * grid.resolution_m,
                        grid.origin.position.y + (cells[:, 0] + 0.5) * grid.resolution_m], axis=1)
    r_wb = quat_to_rotmat(state.orientation.to_array())
    world = (r_wb @ capture_points().T).T + state.position_m.to_array() + r_wb @ np.array([0.0, 0.0, LIDAR_Z_M])
    dist, _ = cKDTree(world[:, :2]).query(centres)
    print(f"costmap: {len(cells)} lethal cells; farthest from a capture return {dist.max():.3f} m")
    assert len(cells) >= 30 and dist.max() < grid.resolution_m * 1.5, (len(cells), dist.max())
    # the real sweeps carry per-point times: each is deskewed with the FC's poses (hovering: ~no motion)
    assert int(lidar.values["deskewed"]) > 0, lidar.values
