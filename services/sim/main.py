"""Process shell of the simulator: the PX4-like vehicle on MAVLink, the scenario's sensors on
sensors/**, ground truth on sim/truth/** and the clock on sim/clock. With --follow, no vehicle of
its own: the sensors and sim/truth/** follow an external FC's ground truth (follow.py).

Timing: the vehicle runner owns sim time. Each physics step reports its truth here; the IMU is
sampled at its rate in that callback, and camera / LiDAR frames are *requested* there with the
exact truth of their stamp, then rendered in processes of their own (render.py says why). A
renderer that cannot keep up skips frames and reports the achieved rate (WARN), never delays the
physics.
"""
from __future__ import annotations

import math
import time

import numpy as np

from aeroperception.schemas import (
    CameraInfo, Clock, DiagnosticStatus, Header, Imu, NDArray, Pose, Quaternion, Vector3, VehicleState,
)
from aeroperception.services.runtime import Health, ParamError, Service, run
from aeroperception.services.runtime.rotations import quat_from_rotmat

from . import contract
from .contract import FOLLOW_OUTPUTS, NAME, OUTPUTS, PARAMS, RENDERED, SENSOR_CHOICES
from .follow import Follower, ImuLag
from .render import RenderProcess
from .sensors.rig import build_sensors
from .truth import VehicleTruth
from .vehicle import PARAMS as VEHICLE_PARAMS
from .vehicle import PX4_SITL_BIND, PX4_SITL_TARGET, MavlinkEndpoint, SimVehicle, SimVehicleRunner, parse_address
from .world.scenario import ScenarioError, load_scenario


def camera_info_msg(info, stamp_ns: int) -> CameraInfo:
    r = np.array(info.r_body_camera).reshape(3, 3)
    return CameraInfo(header=Header(stamp_ns=stamp_ns, frame_id=info.frame_id), width=info.width,
                      height=info.height, distortion_model=info.distortion_model,
                      K=NDArray.from_numpy(np.array(info.k, float).reshape(3, 3)),
                      D=NDArray.from_numpy(np.array(info.d, float)),
                      P=NDArray.from_numpy(np.array(info.p, float).reshape(3, 4)),
                      T_body_camera=Pose(position=Vector3.from_array(info.t_body_camera_m), orientation=Quaternion.from_array(quat_from_rotmat(r))))


class SimService(Service):
    """Built-in simulator: PX4-like vehicle over MAVLink + scenario sensors + ground truth."""

    OUTAGE_HOLD_S = 5.0         # following: a ground-truth outage stays WARN this long after it ended

    NAME = NAME
    PARAMS = PARAMS

    @classmethod
    def add_arguments(cls, parser) -> None:
        parser.add_argument("--scenario", default="open_field", help="open_field, village, slope_forest or a YAML path")
        parser.add_argument("--speed", type=float, default=1.0, help="sim seconds per wall second")
        parser.add_argument("--seed", type=int, default=None, help="seed (default: the scenario's)")
        parser.add_argument("--sensors", default="all", choices=SENSOR_CHOICES,
                            help="which scenario sensors to render (lidar: IMU + LiDAR, no cameras; "
                                 "camera: IMU + cameras, no LiDAR (VIO without its CPU); "
                                 "none: vehicle and truth only)")
        parser.add_argument("--target", default="%s:%d" % PX4_SITL_TARGET, help="MAVLink goes to HOST:PORT (fmu)")
        parser.add_argument("--bind", default="%s:%d" % PX4_SITL_BIND, help="MAVLink sent from HOST:PORT")
        parser.add_argument("--follow", action="store_true",
                            help="no vehicle of its own: render the sensors from an external FC's ground truth "
                                 "(fmu/out/vehicle_ground_truth; PX4 SITL), the IMU being the FC's")

    def start(self) -> None:
        a = self.args
        try:
            self.scenario = load_scenario(a.scenario)
        except ScenarioError as e:
            raise RuntimeError(str(e)) from None
        seed = a.seed if a.seed is not None else self.scenario.seed
        self.speed = a.speed if a.speed > 0 else 1.0
        self.follower = None
        if a.follow:
            self._check_follow_args()
            self.follower, self.imu_lag = Follower(self.scenario.ground_height_m), ImuLag()
            self.truth_stamp_ns = 0
        else:
            # The physics ground is the scenario's (slope_forest's 10 deg slope too), so landing,
            # take-off and the rendered sensors agree on where the ground is.
            self.vehicle = SimVehicle(self.node.params, seed=seed, terrain=self.scenario.ground_height_m)
            self.endpoint = MavlinkEndpoint(target=parse_address(a.target), bind=parse_address(a.bind))
        self.blackout_until_ns = 0
        self.node.params.on_change(self._on_param)
        self.sensors = build_sensors(self.scenario) if a.sensors != "none" else None
        self.cameras = self.sensors.cameras() if self.sensors is not None and a.sensors in ("all", "camera") else {}
        self.workers: list[RenderProcess] = []
        node_kwargs = dict(vehicle=a.vehicle, zenoh_config=a.zenoh_config, connect=a.connect, log_level=a.log_level)
        self.next_ns: dict[str, int] = {}
        self.periods_ns: dict[str, int] = {"truth": int(1e9 / self.params.truth_rate_hz)}
        if self.sensors is not None and not a.follow:     # following: the IMU is the FC's (fmu)
            self.periods_ns["imu"] = int(1e9 / self.scenario.sensors.imu.rate_hz)
        if self.sensors is not None:
            if self.cameras:
                self.periods_ns["camera"] = int(1e9 / max(cam.rate_hz for cam in self.cameras.values()))
                self.workers.append(RenderProcess("camera", a.scenario, node_kwargs))
                self.node.every(1.0, self._publish_infos, name="camera_info")
            if a.sensors in ("all", "lidar") and self.sensors.lidar is not None:
                self.periods_ns["lidar"] = int(1e9 / self.sensors.lidar.info().rate_hz)
                self.workers.append(RenderProcess("lidar", a.scenario, node_kwargs))
        # The shell's part of the contract (the render processes publish RENDERED); following, no
        # sim/clock nor IMU of its own (FOLLOW_OUTPUTS), and the FC's truth and IMU in.
        handlers = {f"on_sensors_camera_{name}_info": lambda _r, i=cam.info(): camera_info_msg(i, self.now_stamp())
                    for name, cam in self.cameras.items()}
        if a.follow:
            handlers.update(on_fmu_out_vehicle_ground_truth=self._on_ground_truth,
                            on_fmu_out_sensor_combined=lambda m: self.imu_lag.add_imu(
                                m.header.stamp_ns, m.angular_velocity_radps.to_array()))
        rendered = {k for keys in RENDERED.values() for k in keys}
        self.io = self.node.bind(contract, handlers, inputs=contract.INPUTS if a.follow else (),
                                 outputs=[k for k in (FOLLOW_OUTPUTS if a.follow else OUTPUTS) if k not in rendered],
                                 services=[f"sensors/camera/{name}/info" for name in self.cameras])
        if a.follow:
            self.log.info("sim_following", scenario=self.scenario.name, sensors=a.sensors,
                          truth="fmu/out/vehicle_ground_truth")
            return
        # Physics steps at a multiple of the IMU rate (>= 250 Hz) so IMU samples are evenly spaced
        # (200 Hz from 250 Hz physics would alternate 4 / 8 ms gaps).
        imu_hz = self.scenario.sensors.imu.rate_hz
        physics_hz = imu_hz * math.ceil(250.0 / imu_hz) if "imu" in self.periods_ns else 250.0
        self.runner = SimVehicleRunner(self.vehicle, self.endpoint, speed=self.speed, physics_rate_hz=physics_hz,
                                       on_truth=self._on_truth)
        # Vision stamps -> sim time for the GPS-denied fusion: the runner owns the epoch.
        self.vehicle.estimator.epoch_ns = lambda: self.runner.epoch_ns
        self.runner.start()
        self.log.info("sim_started", scenario=self.scenario.name, seed=seed, speed=self.speed,
                      mavlink_target=a.target, sensors=a.sensors)

    def _check_follow_args(self) -> None:
        """Following, the vehicle, its clock and its MAVLink are the FC's: refuse what would be ignored."""
        a = self.args
        if a.speed != 1.0:
            raise RuntimeError(f"--follow: --speed {a.speed:g} cannot apply (the FC's clock is real time)")
        if a.seed is not None:
            raise RuntimeError(f"--follow: --seed {a.seed} cannot apply (wind and sensor noise are the FC's)")
        changed = [p.name for p in VEHICLE_PARAMS if p.name != "SIM_CAM_BLACKOUT"
                   and getattr(self.params, p.name) != p.default]
        if changed:
            raise RuntimeError(f"--follow: {', '.join(changed)} set, but the vehicle is the FC's (no SIM_* but "
                               "SIM_CAM_BLACKOUT applies)")

    def stamp(self, sim_ns: int) -> int:
        """Stamps on Zenoh: sim time anchored at the wall clock by the runner (at 1x they agree
        with services on wall time; at other speeds services follow sim/clock)."""
        return self.runner.epoch_ns + sim_ns

    def now_stamp(self) -> int:
        """The newest stamp: of the simulation, or following, of the FC's ground truth."""
        return self.truth_stamp_ns if self.follower else self.stamp(self.runner.now_ns())

    def stop(self) -> None:
        if hasattr(self, "runner"):   # start() may have failed (bad --scenario) before it existed
            self.runner.stop()
        for w in getattr(self, "workers", []):
            w.stop()

    # ------------------------------------------------------------ physics-step callback

    def _due(self, what: str, now_ns: int) -> bool:
        nxt = self.next_ns.get(what, 0)
        if now_ns < nxt:
            return False
        self.next_ns[what] = max(nxt + self.periods_ns[what], now_ns)
        return True

    def _on_truth(self, t: VehicleTruth) -> None:
        now = t.stamp_ns
        stamp = self.stamp(now)
        if self._due("truth", now):
            self.io["sim/clock"].publish(Clock(header=Header(stamp_ns=stamp), speed_factor=self.speed))
            self.io["sim/truth/state"].publish(VehicleState(
                header=Header(stamp_ns=stamp, frame_id="map"), position_m=Vector3.from_array(t.position_enu_m),
                velocity_mps=Vector3.from_array(t.velocity_enu_mps), acceleration_mps2=Vector3.from_array(t.accel_enu_mps2),
                orientation=Quaternion.from_array(t.q_enu_flu), angular_velocity_radps=Vector3.from_array(t.angular_velocity_flu_radps),
                estimator_name="truth", confidence=1.0, armed=self.vehicle.commander.armed,
                flight_mode=self.vehicle.commander.mode, connected=True))
        if "imu" in self.periods_ns and self._due("imu", now):
            s = self.sensors.imu.sample(t)
            self.io["sensors/imu"].publish(Imu(header=Header(stamp_ns=stamp, frame_id="base_link"),
                                                 angular_velocity_radps=Vector3.from_array(s.angular_velocity_flu_radps),
                                                 linear_acceleration_mps2=Vector3.from_array(s.linear_acceleration_flu_mps2)))
        for w in self.workers:
            if self._due(w.name, now):
                w.request(t, stamp, blackout=w.name == "camera" and now < self.blackout_until_ns)

    # ------------------------------------------------------------ follow mode (Zenoh callback)

    def _on_ground_truth(self, m: VehicleState) -> None:
        """Each FC ground-truth sample: sim/truth/state at truth_rate_hz and the frames due, all
        with the sample's stamp (sensors/imu's clock); no sim/clock (the FC's clock is real time)."""
        rejected = self.follower.rejected
        t = self.follower.truth(m)
        if t is None:
            if self.follower.rejected != rejected:
                self.node.report_bad_input("fmu/out/vehicle_ground_truth", "non-finite ground truth")
            return
        now = self.truth_stamp_ns = t.stamp_ns
        self.imu_lag.add_truth(now, t.angular_velocity_flu_radps)
        if self._due("truth", now):
            self.io["sim/truth/state"].publish(VehicleState(
                header=Header(stamp_ns=now, frame_id="map"), position_m=Vector3.from_array(t.position_enu_m),
                velocity_mps=Vector3.from_array(t.velocity_enu_mps), acceleration_mps2=Vector3.from_array(t.accel_enu_mps2),
                orientation=Quaternion.from_array(t.q_enu_flu), angular_velocity_radps=Vector3.from_array(t.angular_velocity_flu_radps),
                estimator_name="truth", confidence=1.0, armed=m.armed, flight_mode=m.flight_mode,
                landed_state=m.landed_state, connected=True))
        for w in self.workers:
            if self._due(w.name, now):
                w.request(t, now, blackout=w.name == "camera" and now < self.blackout_until_ns)

    def _on_param(self, name: str, value) -> None:
        """SIM_CAM_BLACKOUT = N: the cameras see black for N s of sim time from now (a fault).
        Following, the other SIM_* (the built-in vehicle's) are refused: the vehicle is the FC's."""
        if self.follower is not None and name != "SIM_CAM_BLACKOUT" and name.startswith("SIM_"):
            raise ParamError(f"{name}: the simulator follows an external FC (--follow); its vehicle parameters do not apply")
        if name == "SIM_CAM_BLACKOUT" and (hasattr(self, "runner") or self.follower is not None):
            start = self.truth_stamp_ns if self.follower is not None else self.runner.now_ns()
            self.blackout_until_ns = start + int(float(value) * 1e9)
            self.log.info("camera_blackout", seconds=value)

    # ------------------------------------------------------------ renderers (own threads)

    def _publish_infos(self) -> None:
        for name, cam in self.cameras.items():
            self.io[f"sensors/camera/{name}/info"].publish(camera_info_msg(cam.info(), self.now_stamp()))

    # ------------------------------------------------------------ health

    def health(self) -> Health:
        if self.follower is not None:
            return self._follow_health()
        d = self.runner.diagnostics()
        values = {k: d[k] for k in ("sim_time_s", "realtime_factor", "mode", "armed", "landed_state", "failsafe",
                                    "battery_remaining", "overruns", "reboots", "rebooting", "time_boot_ms") if k in d}
        values.update({k: v for k, v in d.items()
                       if k.startswith(("rx", "tx", "vision", "setpoint", "bad", "commander_", "gps_denied",
                                                        "position_valid", "estimate_", "ev_"))})
        values["camera_blackout"] = self.runner.now_ns() < self.blackout_until_ns
        level, msgs = self._worker_health(values)
        if self.runner.overruns:
            msgs.append(f"physics behind real time ({self.runner.overruns} re-anchors)")
        return Health(level, f"{self.scenario.name} x{self.speed:g} {d['mode']}" + (f"; {', '.join(msgs)}" if msgs else ""),
                      values)

    def _follow_health(self) -> Health:
        f = self.follower
        age_s = (self.node.now_ns() - self.truth_stamp_ns) / 1e9 if self.truth_stamp_ns else None
        lag = self.imu_lag.lag_ms()
        values = {"following": "fmu/out/vehicle_ground_truth", "truth_samples": f.samples, "truth_rejected": f.rejected,
                  "truth_out_of_order": f.out_of_order, "truth_outages": f.outages,
                  "truth_age_ms": round(age_s * 1e3, 1) if age_s is not None else None,
                  "ground_shift_m": round(f.z_shift_m, 3) if f.z_shift_m is not None else None,
                  "below_ground": f.below_ground, "below_ground_max_m": round(f.below_ground_max_m, 3),
                  "camera_blackout": self.truth_stamp_ns < self.blackout_until_ns}
        if lag is not None:                 # the median of the recent measurements (needs rotation to see)
            values["truth_imu_lag_ms"] = round(lag, 2)
        level, msgs = self._worker_health(values)
        if age_s is None or age_s > f.outage_ns / 1e9:
            level = DiagnosticStatus.WARN
            msgs.insert(0, "no ground truth from the FC" if age_s is None else f"ground truth {age_s:.1f} s old")
        elif f.last_outage and self.node.now_ns() - f.last_outage[1] < self.OUTAGE_HOLD_S * 1e9:
            level = DiagnosticStatus.WARN       # held a while: a short outage falls between two diagnostics
            msgs.insert(0, f"no ground truth for {f.last_outage[0]:.1f} s (back; {f.outages} outages)")
        elif f.z_shift_m is None:
            msgs.append("ground not seen yet (the FC never reported landed and disarmed): unshifted")
        return Health(level, f"{self.scenario.name} following the FC" + (f"; {', '.join(msgs)}" if msgs else ""), values)

    def _worker_health(self, values: dict) -> tuple[int, list[str]]:
        """The renderers' rates, skips and errors into `values`; (level, complaints)."""
        level, msgs = DiagnosticStatus.OK, []
        for w in self.workers:
            rated = 1e9 / self.periods_ns[w.name]
            hz = w.achieved_hz(self.speed)
            values[f"{w.name}_rate_hz"] = round(hz, 1)
            values[f"{w.name}_skipped"] = w.skipped
            values[f"{w.name}_frames"] = w.rendered
            values[f"{w.name}_unwatched"] = w.unwatched
            values[f"{w.name}_watched"] = w.watched     # False: nobody subscribes, nothing rendered
            if w.render_ms:
                values[f"{w.name}_render_p50_ms"] = round(float(np.median(w.render_ms)), 1)
            if w.watched and w.rendered > 5 and hz < 0.9 * rated:
                level = DiagnosticStatus.WARN
                msgs.append(f"{w.name} {hz:.1f}/{rated:.0f} Hz")
            values[f"{w.name}_errors"] = w.errors
            if w.errors and time.monotonic() - w.error_wall < 5.0:
                level = DiagnosticStatus.WARN
                msgs.append(f"{w.name} render failed x{w.errors} ({w.error[:80]})")
        return level, msgs


def main(argv=None) -> int:
    return run(SimService, argv)
