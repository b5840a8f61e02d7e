"""Process shell of fmu: a pymavlink link thread, the offboard stream, the fmu/srv/* queryables."""
from __future__ import annotations

import math
import threading
import time
from typing import Any, Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.schemas import (
    ArmReply, ArmRequest, DiagnosticStatus, EmergencyStopReply, EmergencyStopRequest, Image, Odometry, SetModeReply,
    SetModeRequest, TrajectorySetpoint, TrajectoryStatus,
)
from aeroperception.services.runtime import Health, Service, run

from . import ardupilot, contract
from .config import FmuConfig
from .fc_commands import FcCommands
from .link import open_fcu_link
from .logic import IGNORE_POS, IGNORE_VEL, Telemetry, highres_imu_to_imu, odometry_fields, setpoint_target
from .navigation import estimator_status_from_mavlink, gps_from_mavlink
from .offboard import BRAKE, FOLLOW, OffboardArbiter, StreamWarmth
from .setup import Command, LinkSetup, Setup
from .timing import StreamTiming
from .truth import FcClock, ground_truth_from_mavlink, origin_from_mavlink

FORCE_MAGIC = 21196  # COMPONENT_ARM_DISARM param2: force (PX4 and ArduPilot)


class FmuService(Service):
    """MAVLink bridge to the flight controller (PX4, ArduPilot or the built-in sim)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = FmuConfig

    @classmethod
    def add_arguments(cls, parser) -> None:
        parser.add_argument("--fcu-url", default=contract.DEFAULT_FCU_URL,
                            help="pymavlink URL of the flight controller: udpin:127.0.0.1:14540 (PX4 SITL, "
                                 "the built-in sim), udpin:0.0.0.0:14540, serial /dev/ttyACM0,921600, tcp:HOST:5760")

    def bind_selection(self) -> dict[str, Any]:
        """Without publish_imu (real hardware) no sensors/imu, nor the camera stamps checked against it."""
        if self.cfg.publish_imu:
            return {}
        return dict(inputs=[k for k in contract.INPUTS if k not in contract.PUBLISH_IMU_ONLY],
                    outputs=[k for k in contract.OUTPUTS if k not in contract.PUBLISH_IMU_ONLY])

    def start(self) -> None:
        c = self.cfg
        self.tm = Telemetry()
        self.counters = {"rx": 0, "bad_packets": 0, "fc_console_bytes": 0, "setpoints_sent": 0, "holds_sent": 0, "brakes_sent": 0,
                         "vio_injected": 0, "vio_stale_dropped": 0,
                         "commands_retried": 0, "global_origin_sent": 0, "ground_truth": 0, "ground_truth_no_origin": 0, "ground_truth_bad": 0}
        self.commands = FcCommands(self._send_command, self.link_fresh, self.args.fcu_url, self.counters)
        self.send_lock = threading.Lock()
        self.arbiter = OffboardArbiter(c.offboard)
        self.last_target_sent_s = 0.0
        self.stream_warmth = StreamWarmth()
        self.guided_takeoff = ardupilot.GuidedTakeoff()   # ArduPilot: NAV_TAKEOFF before set-points
        self.prearm_ok = False      # SYS_STATUS: the FC's pre-arm checks pass (ArduPilot reports it)
        self.ekf_uses_gps = False   # ArduPilot said "EKF3 IMU0 is using GPS" (since fmu started)
        self.state_published_s = -math.inf  # last state/vehicle from FC data (new session after a gap)
        self.setup = LinkSetup(c.reboot_gap_s, c.ground_truth_rate_hz, c.home_request_period_s)
        self.fc_clock = FcClock()            # HIGHRES_IMU and ground-truth stamps
        self.origin: tuple[float, float, float] | None = None   # the FC's local origin (GPS_GLOBAL_ORIGIN)
        self.timing = StreamTiming()
        # udpin: bound exclusively and locked to the FC (a taken port fails start-up in one line)
        self.conn = open_fcu_link(self.args.fcu_url, c.source_system, c.source_component, c.fcu_peer, c.fcu_relock_s)
        # Stop following the planner at once when it goes away (or says it is in ERROR: on_planner_status),
        # rather than after setpoint_timeout_s of silence (or never, if it kept sending stale motion).
        self.node.on_liveliness("planner", lambda _name, alive: self._planner_health(alive, "planner not alive"))
        self.stale_published_s = 0.0       # last connected=False on state/vehicle (link stale)
        self.stream_loop = self.node.every(1.0 / c.offboard_rate_hz, self._offboard_tick, name="offboard")
        self.node.every(1.0, self._heartbeat_tick, name="heartbeat")
        self.node.every(1.0 / contract.STATUS_RATE_HZ, self._status_tick, name="status")
        self.node.every(1.0, self._home_tick, name="home")
        self.handlers = self._mavlink_handlers()
        self.reader = threading.Thread(target=self._read_loop, name="fmu-mavlink", daemon=True)
        self.reader.start()
        self.log.info("fcu_link", url=self.args.fcu_url)

    def on_config(self, cfg: FmuConfig) -> None:
        self.arbiter.cfg = cfg.offboard
        self.setup.reboots.gap_s = cfg.reboot_gap_s
        self.setup.home_request_period_s = cfg.home_request_period_s
        if cfg.offboard_rate_hz != self.cfg.offboard_rate_hz:
            self.stream_loop.set_rate(cfg.offboard_rate_hz)

    def stop(self) -> None:
        self.node.stop_event.set()
        if hasattr(self, "reader"):   # start() may have failed before (e.g. the FC port was taken)
            self.reader.join(1.0)
        if hasattr(self, "conn"):
            self.conn.close()

    # ------------------------------------------------------------ MAVLink in

    def _read_loop(self) -> None:
        while not self.node.stop_event.is_set():
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError) as e:  # socket hiccup: report, keep going
                self.log.throttled("warn", "link", "mavlink_read_error", error=str(e))
                time.sleep(0.05)
                continue
            events = getattr(self.conn, "events", None)
            while events:  # link lock / rejected sources, logged from the link's own thread
                event, fields = events.pop(0)
                self.log.warn(event, **fields)
            if m is None:
                continue
            self.node.run_callback("mavlink", self._on_mavlink, m)

    def _on_mavlink(self, m) -> None:
        t = m.get_type()
        if t == "BAD_DATA" and ardupilot.console_text(bytes(m.data), self.tm.autopilot.is_px4,
                                                      self.tm.last_heartbeat_s > 0):
            self.counters["fc_console_bytes"] += len(m.data)
            return
        if t == "BAD_DATA":
            self.counters["bad_packets"] += 1
            self.node.report_bad_input("mavlink", f"bad MAVLink data ({len(m.data)} bytes)")
            return
        if m.get_srcComponent() != mavlink.MAV_COMP_ID_AUTOPILOT1 and t != "COMMAND_ACK":
            return  # other components (cameras, gimbals, GCS) on the same link
        self.counters["rx"] += 1
        self.tm.last_rx_s = time.monotonic()
        handler = self.handlers.get(t)
        if handler is not None:
            handler(m, self.node.now_ns())

    def _mavlink_handlers(self) -> dict[str, Callable[[Any, int], None]]:
        """{MAVLink message type: handler(msg, receive stamp ns)}: what fmu reads from the FC.
        Adding a message = one entry here and its handler."""
        tm, io = self.tm, self.io
        return {
            "HEARTBEAT": self._on_heartbeat,
            "LOCAL_POSITION_NED": self._on_local_position,
            "ATTITUDE_QUATERNION": self._on_attitude,
            "EXTENDED_SYS_STATE": lambda m, _s: tm.on_extended_sys_state(m),
            "SYS_STATUS": self._on_sys_status,
            "BATTERY_STATUS": lambda m, s: io["fmu/out/battery_status"].publish(tm.on_battery_status(m, s)),
            "HIGHRES_IMU": self._on_highres_imu,
            "HIL_STATE_QUATERNION": self._on_ground_truth,
            "GPS_GLOBAL_ORIGIN": lambda m, _s: self._on_origin(m),
            "GPS_RAW_INT": lambda m, s: io["fmu/out/vehicle_gps_position"].publish(gps_from_mavlink(m, s)),
            "ESTIMATOR_STATUS": lambda m, s: io["fmu/out/estimator_status"].publish(
                estimator_status_from_mavlink(m, s)),
            "HOME_POSITION": self._on_home_position,   # our request's answer; PX4 also sends it when home changes
            "COMMAND_ACK": lambda m, _s: self.commands.on_ack(m),
            "STATUSTEXT": self._on_statustext,
            "TIMESYNC": self._on_timesync,
        }

    def _on_sys_status(self, m, _stamp: int) -> None:
        self.tm.on_sys_status(m)
        ok = ardupilot.prearm_ok(m)
        if ok != self.prearm_ok:
            self.log.info("fc_prearm", ok=ok)
        self.prearm_ok = ok

    def _on_heartbeat(self, m, stamp: int) -> None:
        if m.type == mavlink.MAV_TYPE_GCS:
            return
        self.tm.system_id = m.get_srcSystem()
        self.tm.on_heartbeat(m)
        self._publish_status(stamp, periodic=False)
        self._set_up(self.setup.on_heartbeat(time.monotonic(), self.tm.home is not None))

    def _on_local_position(self, m, stamp: int) -> None:
        local = self.tm.on_local_position(m, stamp)
        # connected once the FC has identified itself (heartbeat: mode, armed); hot path first
        self.io["state/vehicle"].publish(self.tm.vehicle_state(stamp, connected=self.tm.last_heartbeat_s > 0))
        now = time.monotonic()
        new_session = now - self.state_published_s > self.cfg.link_timeout_s
        self.state_published_s = now
        self.arbiter.on_state(stamp, new_session=new_session)
        if new_session:
            self.log.info("state_session", stamp_ns=stamp, following=False)
        self.io["fmu/out/vehicle_local_position"].publish(local)
        self._check_boot_time(m.time_boot_ms)

    def _on_attitude(self, m, stamp: int) -> None:
        self.io["fmu/out/vehicle_attitude"].publish(self.tm.on_attitude_quaternion(m, stamp))
        self._check_boot_time(m.time_boot_ms)

    def _on_highres_imu(self, m, stamp: int) -> None:
        imu = highres_imu_to_imu(m, self.fc_clock.stamp(m.time_usec, stamp))
        self.io["fmu/out/sensor_combined"].publish(imu)
        if "sensors/imu" in self.io:
            self.io["sensors/imu"].publish(imu)
            self.timing.on_imu(imu.header.stamp_ns)

    def _on_statustext(self, m, _stamp: int) -> None:
        """The FC says why it refused a command (PX4: "Arming denied: ...")."""
        self.commands.on_statustext(m.severity, str(m.text))
        self.log.info("fc_statustext", severity=m.severity, text=str(m.text))
        self.ekf_uses_gps = self.ekf_uses_gps or ardupilot.ekf_uses_gps(str(m.text))

    def _on_timesync(self, m, _stamp: int) -> None:
        """PX4 asks the companion (tc1 == 0): answered in the clock ODOMETRY is stamped in (the
        node's), so PX4 maps each vision pose's stamp into its own time."""
        if m.tc1 == 0:
            self._send(lambda mav: mav.timesync_send(self.node.now_ns(), m.ts1))

    def _on_ground_truth(self, m, rx_ns: int) -> None:
        """A simulated FC's ground truth -> fmu/out/vehicle_ground_truth (ENU about the FC's local
        origin, asked for until the FC has one), stamped on the IMU's clock."""
        truth = ground_truth_from_mavlink(m, self.origin, self.fc_clock.stamp_untimed(rx_ns), armed=self.tm.armed,
                                          flight_mode=self.tm.flight_mode, landed_state=self.tm.landed_state)
        if truth is None:
            self.counters["ground_truth_no_origin" if self.origin is None else "ground_truth_bad"] += 1
            if self.origin is None:
                self._send_commands(self.setup.origin_missing(time.monotonic()))
            return
        self.io["fmu/out/vehicle_ground_truth"].publish(truth)
        self.counters["ground_truth"] += 1

    def _on_origin(self, m) -> None:
        origin = origin_from_mavlink(m)
        if origin is not None and origin != self.origin:
            self.log.info("fc_local_origin", latitude_deg=origin[0], longitude_deg=origin[1], altitude_amsl_m=origin[2],
                          first=self.origin is None)
            self.origin = origin

    def _check_boot_time(self, time_boot_ms: int) -> None:
        self._set_up(self.setup.on_boot_time(time_boot_ms, time.monotonic(), self.tm.home is not None))

    def _set_up(self, setup: Setup) -> None:
        """Send what the link set-up asks (setup.py): stream rates and home, again after a reboot."""
        if setup.rebooted:
            self.log.warn("fc_reboot_detected", reason=setup.rebooted, action="re-requesting stream rates and home")
        self._send_commands(setup.commands)

    def _on_home_position(self, m, stamp: int) -> None:
        old = self.tm.home
        home = self.tm.on_home_position(m, stamp)
        if home is None:
            self.log.throttled("warn", "home", "home_position_invalid", latitude=m.latitude, longitude=m.longitude)
            return
        if old is None or (old.latitude_deg, old.longitude_deg, old.altitude_amsl_m, old.position_m) != \
                (home.latitude_deg, home.longitude_deg, home.altitude_amsl_m, home.position_m):
            self.log.info("home_position", latitude_deg=home.latitude_deg, longitude_deg=home.longitude_deg,
                          altitude_amsl_m=home.altitude_amsl_m,
                          position_m=[round(v, 3) for v in home.position_m.to_array().tolist()],
                          first=old is None)
        self.io["fmu/out/home_position"].publish(home)

    def _home_tick(self) -> None:
        """Latched home: republish at 1 Hz; until the FC sent one, ask again every home_request_period_s."""
        if self.tm.home is not None:
            self.io["fmu/out/home_position"].publish(self.tm.home)
        elif self.setup.streams_requested and self.link_fresh():
            if self.state_published_s > 0:     # PX4 sends LOCAL_POSITION_NED once it has a local position
                self._send_global_origin()
            self._send_commands(self.setup.home_due(time.monotonic()))

    def _send_global_origin(self) -> None:
        """GPS-denied: the FC's local origin as a global position, once the FC has a local position
        (its EKF2 resets position when it takes one) and until it reports a home (it then has a
        global position)."""
        if self.cfg.global_origin is not None:
            lat, lon, alt = self.cfg.global_origin
            self._send(lambda mav: mav.set_gps_global_origin_send(self.tm.system_id, round(lat * 1e7), round(lon * 1e7),
                                                                  round(alt * 1e3), self.node.now_ns() // 1000))
            self.counters["global_origin_sent"] += 1

    # ------------------------------------------------------------ MAVLink out

    def _send(self, fn) -> None:
        with self.send_lock:
            try:
                fn(self.conn.mav)
            except OSError as e:
                self.log.throttled("warn", "send", "mavlink_send_error", error=str(e))

    def _send_commands(self, commands: list[Command]) -> None:
        for c in commands:
            self._send_command(c.command, c.params7())

    def _send_command(self, command: int, params7: list[float]) -> None:
        self._send(lambda mav: mav.command_long_send(self.tm.system_id, 1, command, 0, *params7))

    def link_fresh(self) -> bool:
        return time.monotonic() - self.tm.last_rx_s < self.cfg.link_timeout_s

    def _planner_health(self, ok: bool, why: str) -> None:
        if self.arbiter.on_planner_health(ok, why):
            if ok:
                self.log.info("planner_back")
            else:
                self.log.warn("planner_lost_holding", reason=why)

    # ------------------------------------------------------------ inputs (contract.INPUTS)

    def on_planner_status(self, st: TrajectoryStatus) -> None:
        self._planner_health(st.status != TrajectoryStatus.STATUS_ERROR, "planner reports ERROR")

    def on_fmu_in_trajectory_setpoint(self, sp: TrajectorySetpoint) -> None:
        a = self.arbiter
        was = a.phase
        rejected, stale = a.counters["setpoints_rejected"], a.counters["setpoints_stale"]
        out = a.on_setpoint(sp, time.monotonic())
        if a.counters["setpoints_rejected"] != rejected:
            self.log.throttled("warn", "sp_rejected", "setpoint_rejected_holding", reason=a.last_rejection,
                               count=a.counters["setpoints_rejected"])
        elif a.counters["setpoints_stale"] != stale:
            self.log.throttled("warn", "sp_stale", "setpoint_stale_not_forwarded", reason=a.last_rejection,
                               count=a.counters["setpoints_stale"])
        if out is None:
            return
        if was != FOLLOW:
            self.log.info("planner_following", after=a.cfg.resume_count)
        self._send_target(setpoint_target(out))  # forward at once: the hot path
        self.counters["setpoints_sent"] += 1

    def _send_target(self, f: dict) -> None:
        if not self.tm.autopilot.is_px4 and not self._ardupilot_target(f):
            return
        if not self.tm.autopilot.is_px4:
            f = ardupilot.adapt_target(f)
        boot_ms = int(time.monotonic() * 1e3) & 0xFFFFFFFF
        self._send(lambda mav: mav.set_position_target_local_ned_send(
            boot_ms, self.tm.system_id, 1, f["coordinate_frame"], f["type_mask"], f["x"], f["y"], f["z"],
            f["vx"], f["vy"], f["vz"], f["afx"], f["afy"], f["afz"], f["yaw"], f["yaw_rate"]))
        self.last_target_sent_s = time.monotonic()
        self.stream_warmth.sent(self.last_target_sent_s)

    def _ardupilot_target(self, f: dict) -> bool:
        """ArduPilot only (services/fmu/ardupilot.py): False when NAV_TAKEOFF goes instead of `f`."""
        sp_up = None if f["type_mask"] & IGNORE_POS else -f["z"]
        sp_up_mps = None if f["type_mask"] & IGNORE_VEL else -f["vz"]
        forward, takeoff = self.guided_takeoff.command(time.monotonic(), self.tm.armed, self.tm.flight_mode,
                                                       self.tm.landed_state, float(self.tm.position_m[2]), sp_up,
                                                       sp_up_mps)
        if takeoff is not None:
            self.log.info("ardupilot_guided_takeoff", altitude_m=takeoff[6], setpoint_up_m=sp_up,
                          setpoint_up_mps=sp_up_mps)
            self._send_commands([Command(mavlink.MAV_CMD_NAV_TAKEOFF, takeoff)])
        return forward

    def _offboard_tick(self) -> None:
        """Keep the stream at offboard_rate_hz: the planner's setpoint while it is fresh, else
        brake and hold (OffboardArbiter); never its last motion."""
        now = time.monotonic()
        if not self.link_fresh():
            # Stale: say so on state/vehicle within one tick of link_timeout_s (then once a
            # second) rather than going quiet — consumers detect the loss in <= 0.5 s.
            if now - self.stale_published_s >= 1.0:
                self.stale_published_s = now
                self.io["state/vehicle"].publish(self.tm.vehicle_state(self.node.now_ns(), connected=False))
            return
        self.stale_published_s = 0.0
        if not self.tm.have_position:
            return
        a = self.arbiter
        was = a.phase
        phase, sp = a.tick(now, self.tm.position_m, self.tm.velocity_mps, self.tm.yaw_rad)
        if phase != was:  # FOLLOW -> BRAKE (planner lost) -> HOLD (stopped here)
            (self.log.warn if phase == BRAKE else self.log.info)(
                "offboard_" + phase, reason=a.reason, position_m=self.tm.position_m.round(2).tolist(),
                speed_mps=round(float(np.linalg.norm(self.tm.velocity_mps)), 2))
        if phase == FOLLOW:
            if now - self.last_target_sent_s > 1.25 * self.stream_loop.period_s:
                self._send_target(setpoint_target(sp))
                self.counters["setpoints_sent"] += 1
            return
        self._send_target(setpoint_target(sp))
        self.counters["brakes_sent" if phase == BRAKE else "holds_sent"] += 1

    def _status_tick(self) -> None:
        """fmu/out/vehicle_status at its contract rate from the latest telemetry (the FC's
        heartbeat is only 1 Hz); silent until the FC identified itself and while the link is stale."""
        if self.tm.last_heartbeat_s > 0 and self.link_fresh():
            self._publish_status(self.node.now_ns(), periodic=True)

    def _publish_status(self, stamp_ns: int, periodic: bool) -> None:
        st = self.tm.status_to_publish(stamp_ns, periodic)
        if st is not None:
            self.io["fmu/out/vehicle_status"].publish(st)

    def _heartbeat_tick(self) -> None:
        self._send(lambda mav: mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                                  mavlink.MAV_STATE_ACTIVE))

    def on_state_visual_odometry(self, odom: Odometry) -> None:
        age_s = (self.node.now_ns() - odom.header.stamp_ns) / 1e9
        if age_s > self.cfg.vio_timeout_s:
            self.counters["vio_stale_dropped"] += 1
            self.log.throttled("warn", "vio", "vio_stale_not_injected", age_s=round(age_s, 3))
            return
        f = odometry_fields(odom, odom.header.stamp_ns // 1000)
        self._send(lambda mav: mav.odometry_send(**f))
        self.timing.on_vio_sent(age_s)
        self.counters["vio_injected"] += 1

    def on_sensors_camera_left_image(self, img: Image) -> None:
        """Only with publish_imu: camera frames should fall inside the IMU stream (timing.py)."""
        dt_ms = self.timing.on_image(img.header.stamp_ns)
        self.log.throttled("info", "cam_imu", "camera_imu_alignment", period_s=5.0, dt_ms=round(dt_ms, 3),
                           imu_samples=len(self.timing.imu_stamps_ns))

    # ------------------------------------------------------------ queryables

    def on_fmu_arm(self, req: ArmRequest) -> ArmReply:
        ok, msg = self.commands.run(mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
                                [1.0 if req.arm else 0.0, FORCE_MAGIC if req.force else 0.0],
                                lambda: self.tm.armed == req.arm, self.cfg.command_timeout_s)
        self.log.info("arm", arm=req.arm, force=req.force, success=ok, message=msg)
        return ArmReply(success=ok, message=msg, armed=self.tm.armed)

    def on_fmu_set_mode(self, req: SetModeRequest) -> SetModeReply:
        mode = req.mode.upper()
        try:
            base, main_mode, sub_mode = self.tm.autopilot.set_mode_params(mode)
        except KeyError:
            return SetModeReply(success=False, current_mode=self.tm.flight_mode,
                                message=f"unknown mode {req.mode!r} for {self.tm.autopilot.name}; "
                                        f"known: {', '.join(self.tm.autopilot.mode_names())}")
        timeout_s = self.cfg.command_timeout_s
        offboard = mode == "OFFBOARD"
        if offboard:  # the FC refuses OFFBOARD until our stream has run a while (StreamWarmth)
            timeout_s -= self._wait_stream_warm(min(self.cfg.offboard_warmup_s, timeout_s / 2))
        # Always ask the FC: the mode we last heard (1 Hz heartbeat) may be stale, e.g. right after
        # a failsafe switched OFFBOARD to HOLD; the FC acks a request for its current mode at once.
        ok, msg = self.commands.run(mavlink.MAV_CMD_DO_SET_MODE, [base, main_mode, sub_mode],
                                lambda: self.tm.flight_mode == mode, timeout_s, retry_rejected=offboard)
        self.log.info("set_mode", mode=mode, success=ok, message=msg)
        return SetModeReply(success=ok, message=msg, current_mode=self.tm.flight_mode)

    def _wait_stream_warm(self, warm_s: float) -> float:
        """Block until the setpoint stream has run `warm_s` (bounded by that); the time waited."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < warm_s and self.stream_warmth.age_s(time.monotonic()) < warm_s:
            time.sleep(0.02)
        waited = time.monotonic() - t0
        if waited > 0.05:
            self.log.info("offboard_waited_for_stream", waited_s=round(waited, 2))
        return waited

    def on_fmu_emergency_stop(self, req: EmergencyStopRequest) -> EmergencyStopReply:
        if not req.confirm:
            return EmergencyStopReply(success=False, message="refused: set confirm=true to terminate the flight")
        self.log.error("emergency_stop", reason=req.reason)
        ok, msg = self.commands.run(mavlink.MAV_CMD_DO_FLIGHTTERMINATION, [1.0], lambda: not self.tm.armed,
                                self.cfg.command_timeout_s)
        return EmergencyStopReply(success=ok, message=msg)

    # ------------------------------------------------------------ health

    def health(self) -> Health:
        values = dict(self.counters, **self.setup.counters, **self.timing.values(), mode=self.tm.flight_mode, armed=self.tm.armed, autopilot=self.tm.autopilot.name,
                      prearm_ok=self.prearm_ok, ardupilot_takeoffs_sent=self.guided_takeoff.sent,
                      ready_to_arm=ardupilot.ready_to_arm(self.tm.autopilot.is_px4, self.prearm_ok, self.ekf_uses_gps),
                      **self.arbiter.counters, planner=self.arbiter.label(), offboard=self.arbiter.phase,
                      hold_reason=self.arbiter.reason,
                      **getattr(self.conn, "counters", {}),
                      fcu_peer="%s:%d" % self.conn.peer if getattr(self.conn, "peer", None) else "",
                      home=(f"{self.tm.home.latitude_deg:.7f},{self.tm.home.longitude_deg:.7f},"
                            f"{self.tm.home.altitude_amsl_m:.2f}" if self.tm.home is not None else "unknown"))
        if not self.link_fresh():
            age = time.monotonic() - self.tm.last_rx_s if self.tm.last_rx_s else math.inf
            return Health(DiagnosticStatus.ERROR, f"flight controller link stale ({age:.1f} s) on {self.args.fcu_url}", values)
        return Health(DiagnosticStatus.OK, f"{self.tm.autopilot.name} {self.tm.flight_mode} "
                                           f"{'armed' if self.tm.armed else 'disarmed'}", values)


def main(argv=None) -> int:
    return run(FmuService, argv)
