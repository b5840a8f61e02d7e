"""Simulator ground truth through the flight controller, and the FC's clock on this host.

A simulated FC (PX4 SITL: SIH, Gazebo) knows the vehicle's true state and streams it as
HIL_STATE_QUATERNION when asked (SET_MESSAGE_INTERVAL; a real FC has no ground truth and sends
nothing). fmu republishes it in ENU/FLU about the FC's local origin (GPS_GLOBAL_ORIGIN, the frame
of the FC's own LOCAL_POSITION_NED), so the simulator can render the scenario's sensors from the
pose the FC's physics flies, and eval tools can judge against it.

Time: the FC's IMU (HIGHRES_IMU) carries the FC's boot time; the ground truth carries none
(time_usec 0 from PX4). `FcClock` maps FC time onto this host's clock by the least transport
delay seen lately, so IMU samples are stamped when the FC sampled them, without the link's and
the scheduler's jitter; a ground-truth sample is stamped as the newest FC-timed sample plus the
time between their arrivals (PX4 sends it ~4 ms after the IMU). Images rendered at a truth pose
thus carry stamps on the same clock as sensors/imu.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from aeroperception.schemas import Header, Quaternion, Vector3, VehicleState
from aeroperception.services.lib.geo import MapProjection
from aeroperception.services.mavlink import frames


class FcClock:
    """FC boot time -> this host's clock: a line (offset and rate) through the least transport
    delays (receive time - FC time) of the last `window_s`, one per `bucket_s`, refitted as each
    bucket closes. A line, not a constant: PX4 SITL's clock is the simulation's and runs slower
    than the host's under load (1.1 % measured with SIH on a loaded 2-core machine), so a constant
    offset would step the IMU's stamps. An FC clock going back by more than `reboot_s` (a reboot)
    starts over."""

    def __init__(self, window_s: float = 5.0, bucket_s: float = 0.25, extrapolate_s: float = 0.02, reboot_s: float = 1.0):
        self.bucket_ns, self.extrapolate_ns, self.reboot_ns = int(bucket_s * 1e9), int(extrapolate_s * 1e9), int(reboot_s * 1e9)
        self.buckets: deque[list[int]] = deque(maxlen=max(3, round(window_s / bucket_s)))   # [index, fc_ns, least delay]
        self.line: tuple[int, float, float] | None = None    # (fc_ref_ns, delay at fc_ref, delay slope)
        self.last_fc_ns: int | None = None
        self.last_rx_ns = 0
        self.last_excess_ns = 0     # the newest FC-timed sample's delay above the line
        self.resets = 0

    def offset_ns(self, fc_ns: int) -> int | None:
        """Host time - FC time of a sample the FC took at `fc_ns`, as received with the least delay."""
        if self.line is None:
            return min(b[2] for b in self.buckets) if self.buckets else None
        ref, delay, slope = self.line
        return int(delay + slope * (fc_ns - ref))

    def stamp(self, fc_us: int, rx_ns: int) -> int:
        """The host-clock stamp of a sample the FC took at boot time `fc_us`, received at `rx_ns`."""
        fc_ns = int(fc_us) * 1000
        if self.last_fc_ns is not None and fc_ns < self.last_fc_ns - self.reboot_ns:
            self.buckets.clear()
            self.line = None
            self.resets += 1
        self.last_fc_ns = fc_ns
        delay = rx_ns - fc_ns
        index = fc_ns // self.bucket_ns
        if self.buckets and self.buckets[-1][0] == index:
            self.buckets[-1][2] = min(self.buckets[-1][2], delay)
        else:
            if len(self.buckets) >= 3:
                self._fit()
            self.buckets.append([index, fc_ns, delay])
        offset = self.offset_ns(fc_ns)
        self.last_rx_ns, self.last_excess_ns = rx_ns, delay - offset
        return fc_ns + offset

    def _fit(self) -> None:
        """The line through the closed buckets' least delays, lowered onto the lowest of them."""
        b = np.array([(f, d) for _i, f, d in self.buckets], dtype=float)
        ref = b[-1, 0]
        slope, delay = np.polyfit(b[:, 0] - ref, b[:, 1], 1)
        delay -= max(0.0, float(np.max(delay + slope * (b[:, 0] - ref) - b[:, 1])))
        self.line = (int(ref), float(delay), float(slope))

    def stamp_untimed(self, rx_ns: int) -> int:
        """The stamp of a sample without FC time (ground truth) received at `rx_ns`: the newest
        FC-timed sample's stamp plus the time between their arrivals (so it waited as long in the
        link); its receive time when none came within `extrapolate_s`."""
        if self.buckets and 0 <= rx_ns - self.last_rx_ns <= self.extrapolate_ns:
            return rx_ns - self.last_excess_ns
        return rx_ns


def ground_truth_from_mavlink(m, origin, stamp_ns: int, **status) -> VehicleState | None:
    """HIL_STATE_QUATERNION (lat/lon degE7, alt mm AMSL, NED velocity cm/s, attitude NED/FRD, body
    rates FRD) -> VehicleState in ENU/FLU about `origin` = (lat_deg, lon_deg, alt_m), the FC's local
    origin. None when there is no origin yet or the sample is unusable (zero quaternion, position
    0/0 as sent before the simulator runs). Acceleration is not carried: PX4 fills xacc..zacc with
    whole m/s^2, useless as mG. `status`: armed, flight_mode, landed_state from the FC's telemetry."""
    if origin is None or (m.lat == 0 and m.lon == 0):
        return None
    q = np.array(m.attitude_quaternion, dtype=float)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
        return None
    lat0, lon0, alt0 = origin
    north, east = MapProjection(lat0, lon0).project(m.lat * 1e-7, m.lon * 1e-7)
    position = np.array([east, north, m.alt * 1e-3 - alt0])
    q_enu_flu = frames.q_ned_frd_to_enu_flu(q / np.linalg.norm(q))
    if q_enu_flu[0] < 0:    # same rotation; w >= 0 as everywhere else on Zenoh
        q_enu_flu = -q_enu_flu
    roll, pitch, yaw = frames.euler_from_q(q_enu_flu)
    return VehicleState(
        header=Header(stamp_ns=stamp_ns, frame_id="map"), position_m=Vector3.from_array(position),
        velocity_mps=Vector3.from_array(frames.ned_to_enu(np.array([m.vx, m.vy, m.vz], float) / 100.0)),
        orientation=Quaternion.from_array(q_enu_flu),
        angular_velocity_radps=Vector3.from_array(frames.frd_to_flu(np.array([m.rollspeed, m.pitchspeed, m.yawspeed]))),
        roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, estimator_name="ground_truth", confidence=1.0,
        connected=True, **status)


def origin_from_mavlink(m) -> tuple[float, float, float] | None:
    """GPS_GLOBAL_ORIGIN -> (lat_deg, lon_deg, alt_m AMSL); None when out of range or unset (0/0)."""
    lat, lon = m.latitude * 1e-7, m.longitude * 1e-7
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0) or (m.latitude == 0 and m.longitude == 0):
        return None
    return lat, lon, m.altitude * 1e-3
