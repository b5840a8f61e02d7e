"""`aero up --profile vehicle` against a flight controller that is not our sim service: the
simulated PX4 run standalone (MAVLink only, no Zenoh), as a real PX4 SITL would be. fmu alone
must give the stack its state and, with no simulator, the IMU (HIGHRES_IMU -> sensors/imu)."""
from __future__ import annotations


import numpy as np

from aeroperception.schemas import Imu, VehicleState
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
