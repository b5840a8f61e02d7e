"""Process shell of the simulator: the PX4-like vehicle on MAVLink, the scenario's sensors on
sensors/**, ground truth on sim/truth/** and the clock on sim/clock.

Timing: the vehicle runner owns sim time. Each physics step reports its truth here; the IMU is
sampled at its rate in that callback, and camera / LiDAR frames are *requested* there with the
exact truth of their stamp, then rendered in processes of their own (render.py: Open3D holds
the GIL while it casts rays). A renderer that cannot keep up skips frames and reports the
achieved rate (WARN), never delays the physics.
"""
from __future__ import annotations

import math
import time

import numpy as np

from aeroperception.schemas import (
    CameraInfo, Clock, DiagnosticStatus, Header, Imu, NDArray, Pose, Quaternion, Vector3, VehicleState,
)
from aeroperception.services.runtime import Health, Service, run
from aeroperception.services.runtime.rotations import quat_from_rotmat

from .contract import NAME, OUTPUTS, PARAMS
from .qos import qos_for
from .render import RenderProcess
from .sensors.rig import build_sensors
from .truth import VehicleTruth
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

    NAME = NAME
    PARAMS = PARAMS

    @classmethod
    def add_arguments(cls, parser) -> None:
        parser.add_argument("--scenario", default="open_field", help="open_field, village, slope_forest or a YAML path")
        parser.add_argument("--speed", type=float, default=1.0, help="sim seconds per wall second")
        parser.add_argument("--seed", type=int, default=None, help="seed (default: the scenario's)")
        parser.add_argument("--sensors", default="all", choices=["all", "lidar", "camera", "imu", "none"],
                            help="which scenario sensors to render (lidar: IMU + LiDAR, no cameras; "
                                 "camera: IMU + cameras, no LiDAR (VIO without its CPU); "
                                 "none: vehicle and truth only)")
        parser.add_argument("--target", default="%s:%d" % PX4_SITL_TARGET, help="MAVLink goes to HOST:PORT (fmu)")
        parser.add_argument("--bind", default="%s:%d" % PX4_SITL_BIND, help="MAVLink sent from HOST:PORT")

    def start(self) -> None:
        a = self.args
        try:
            self.scenario = load_scenario(a.scenario)
        except ScenarioError as e:
            raise RuntimeError(str(e)) from None
        seed = a.seed if a.seed is not None else self.scenario.seed
        self.speed = a.speed if a.speed > 0 else 1.0
        # The physics ground is the scenario's (slope_forest's 10 deg slope too), so landing,
        # take-off and the rendered sensors agree on where the ground is.
        self.vehicle = SimVehicle(self.node.params, seed=seed, terrain=self.scenario.ground_height_m)
        self.blackout_until_ns = 0
        self.node.params.on_change(self._on_param)
        self.endpoint = MavlinkEndpoint(target=parse_address(a.target), bind=parse_address(a.bind))
        pub = self.node.publisher
        self.pubs = {k: pub(k, cls, **qos_for(k)) for k, cls in OUTPUTS.items()}
        self.sensors = build_sensors(self.scenario) if a.sensors != "none" else None
        self.workers: list[RenderProcess] = []
        node_kwargs = dict(vehicle=a.vehicle, zenoh_config=a.zenoh_config, connect=a.connect, log_level=a.log_level)
        self.next_ns: dict[str, int] = {}
        self.periods_ns: dict[str, int] = {"truth": int(1e9 / self.params.truth_rate_hz)}
        if self.sensors is not None:
            self.periods_ns["imu"] = int(1e9 / self.scenario.sensors.imu.rate_hz)
            if a.sensors in ("all", "camera") and self.sensors.stereo is not None:
                self.periods_ns["camera"] = int(1e9 / self.sensors.stereo.infos()[0].rate_hz)
                self.workers.append(RenderProcess("camera", a.scenario, node_kwargs))
                for info in self.sensors.stereo.infos():
                    side = "left" if "left" in info.frame_id else "right"
                    key = f"sensors/camera/{side}/info"
                    self.node.serve(key, None, CameraInfo, lambda _r, i=info: camera_info_msg(i, self.stamp(self.runner.now_ns())))
                self.node.every(1.0, self._publish_infos, name="camera_info")
            if a.sensors in ("all", "lidar") and self.sensors.lidar is not None:
                self.periods_ns["lidar"] = int(1e9 / self.sensors.lidar.info().rate_hz)
                self.workers.append(RenderProcess("lidar", a.scenario, node_kwargs))
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

    def stamp(self, sim_ns: int) -> int:
        """Stamps on Zenoh: sim time anchored at the wall clock by the runner (at 1x they agree
        with services on wall time; at other speeds services follow sim/clock)."""
        return self.runner.epoch_ns + sim_ns

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
            self.pubs["sim/clock"].publish(Clock(header=Header(stamp_ns=stamp), speed_factor=self.speed))
            self.pubs["sim/truth/state"].publish(VehicleState(
                header=Header(stamp_ns=stamp, frame_id="map"), position_m=Vector3.from_array(t.position_enu_m),
                velocity_mps=Vector3.from_array(t.velocity_enu_mps), acceleration_mps2=Vector3.from_array(t.accel_enu_mps2),
                orientation=Quaternion.from_array(t.q_enu_flu), angular_velocity_radps=Vector3.from_array(t.angular_velocity_flu_radps),
                estimator_name="truth", confidence=1.0, armed=self.vehicle.commander.armed,
                flight_mode=self.vehicle.commander.mode, connected=True))
        if "imu" in self.periods_ns and self._due("imu", now):
            s = self.sensors.imu.sample(t)
            self.pubs["sensors/imu"].publish(Imu(header=Header(stamp_ns=stamp, frame_id="base_link"),
                                                 angular_velocity_radps=Vector3.from_array(s.angular_velocity_flu_radps),
                                                 linear_acceleration_mps2=Vector3.from_array(s.linear_acceleration_flu_mps2)))
        for w in self.workers:
            if self._due(w.name, now):
                w.request(t, stamp, blackout=w.name == "camera" and now < self.blackout_until_ns)

    def _on_param(self, name: str, value) -> None:
        """SIM_CAM_BLACKOUT = N: the cameras see black for N s of sim time from now (a fault)."""
        if name == "SIM_CAM_BLACKOUT" and hasattr(self, "runner"):
            self.blackout_until_ns = self.runner.now_ns() + int(float(value) * 1e9)
            self.log.info("camera_blackout", seconds=value)

    # ------------------------------------------------------------ renderers (own threads)

    def _publish_infos(self) -> None:
        for info in self.sensors.stereo.infos():
            side = "left" if "left" in info.frame_id else "right"
            self.pubs[f"sensors/camera/{side}/info"].publish(camera_info_msg(info, self.stamp(self.runner.now_ns())))

    # ------------------------------------------------------------ health

    def health(self) -> Health:
        d = self.runner.diagnostics()
        values = {k: d[k] for k in ("sim_time_s", "realtime_factor", "mode", "armed", "landed_state", "failsafe",
                                    "battery_remaining", "overruns", "reboots", "rebooting", "time_boot_ms") if k in d}
        values.update({k: v for k, v in d.items()
                       if k.startswith(("rx", "tx", "vision", "setpoint", "bad", "commander_", "gps_denied",
                                                        "position_valid", "estimate_", "ev_"))})
        values["camera_blackout"] = self.runner.now_ns() < self.blackout_until_ns
        level, msgs = DiagnosticStatus.OK, []
        for w in self.workers:
            rated = 1e9 / self.periods_ns[w.name]
            hz = w.achieved_hz(self.speed)
            values[f"{w.name}_rate_hz"] = round(hz, 1)
            values[f"{w.name}_skipped"] = w.skipped
            values[f"{w.name}_frames"] = w.rendered
            if w.render_ms:
                values[f"{w.name}_render_p50_ms"] = round(float(np.median(w.render_ms)), 1)
            if w.rendered > 5 and hz < 0.9 * rated:
                level = DiagnosticStatus.WARN
                msgs.append(f"{w.name} {hz:.1f}/{rated:.0f} Hz")
            values[f"{w.name}_errors"] = w.errors
            if w.errors and time.monotonic() - w.error_wall < 5.0:
                level = DiagnosticStatus.WARN
                msgs.append(f"{w.name} render failed x{w.errors} ({w.error[:80]})")
        if self.runner.overruns:
            msgs.append(f"physics behind real time ({self.runner.overruns} re-anchors)")
        return Health(level, f"{self.scenario.name} x{self.speed:g} {d['mode']}" + (f"; {', '.join(msgs)}" if msgs else ""),
                      values)


def main(argv=None) -> int:
    return run(SimService, argv)
