"""Process shell: the UDP MAVLink link on one side, the stack (Zenoh) on the other.

Threads: the UDP receive thread hands every parsed message to `_on_mav` under node.lock; a 20 Hz
timer sends due telemetry and drives the mission/command timers; calls into the stack are
asynchronous (node.call_async), their replies come back under node.lock. So the logic objects
(MissionProtocol, CommandHandler, ParamTable, TelemetryState, Progress) are only touched under one lock.

Identity (contract.IDENTITY_*): as the vehicle itself (sim profile: PX4-like autopilot, sys 1 comp
1), or as the flight controller's onboard computer (vehicle profile: comp 191 of the FC's system,
heartbeat only, parameters and commands addressed to comp 191), so a ground station that also
hears the FC's own link sees one vehicle.
"""
from __future__ import annotations

import math
import os
import time

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import (
    ArmReply, ArmRequest, BatteryState, DiagnosticStatus, Empty, EstimatorStatus, GcsLink, GetMissionReply, GoalReply,
    GoToPositionGoal, GpsPosition, HomePosition, Joystick, LoadMissionReply, LoadMissionRequest, MissionCommand, MissionStatus,
    ObjectEvent, ParamList, ParamSet, ParamSetReply, Reply, SafetyStatus, SchemaError, SetModeReply, SetModeRequest, TakeoffGoal,
    TrackedObjectArray, Vector3, VehicleState, VehicleStatus, WaypointReached, parse_mission,
)
from aeroperception.services.mavlink import ftp
from aeroperception.services.runtime import CallError, Health, Service, run

from . import contract
from .commands import CommandHandler, mode_from_custom_mode
from .home import SOURCE_PARAM, Home, HomeTracker, home_from_msg, origin_shift_m
from .link import UdpLink, load_signing_key, parse_signing_key
from .messages import statustext
from .mission_items import MissionConversionError, convert_items, mission_to_items
from .mission_progress import Progress
from .mission_protocol import MissionProtocol
from .mission_speed import SPEED_DEFAULT, SpeedSchedule, waypoint_speeds
from .params import ParamTable, decode_param_id, decode_value
from .presence import GroundStationFilter, LinkVerdict, ListeningClock
from .objects_relay import ObjectsRelay, event_text
from .safety_relay import SafetyRelay
from .telemetry import Scheduler, TelemetryState

SPEED_SERVICE, SPEED_PARAM = "planner", "max_velocity_mps"   # DO_CHANGE_SPEED sets this


class GcsService(Service):
    """MAVLink endpoint for ground stations: presents the stack as one PX4 autopilot (seed 001)."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS

    @classmethod
    def add_arguments(cls, parser) -> None:
        g = parser.add_argument_group("gcs")
        g.add_argument("--local-port", type=int, default=None, help="UDP port to bind (default 14551)")
        g.add_argument("--remote-port", type=int, default=None, help="ground station port (default 14550)")
        g.add_argument("--gcs-ip", default=None, help="ground station address until it talks (default 127.0.0.1)")
        g.add_argument("--bind-ip", default=None, help="address to bind (default 0.0.0.0)")
        g.add_argument("--signing-key-file", default=None, metavar="FILE",
                       help="MAVLink 2 signing: sign everything, refuse unsigned packets; FILE holds the 32-byte "
                            f"key as 64 hex digits or raw bytes (or set {contract.SIGNING_KEY_ENV}=<hex>)")
        g.add_argument("--signing-link-id", type=int, default=None, help="MAVLink 2 signing link id (default 0)")

    def _signing_key(self) -> tuple[bytes | None, str]:
        """The signing key and where it came from (never the key itself in any message)."""
        path = self.params.signing_key_file
        if path:
            key, shared = load_signing_key(path)
            if shared:
                self.log.warn("signing_key_file_permissions", file=path,
                              hint="readable by other users; chmod 600")
            return key, f"file {path}"
        env = os.environ.get(contract.SIGNING_KEY_ENV, "")
        if env:
            try:
                return parse_signing_key(env), f"env {contract.SIGNING_KEY_ENV}"
            except ValueError as e:
                raise ValueError(f"{contract.SIGNING_KEY_ENV}: {e}") from None
        return None, ""

    def start(self) -> None:
        p = self.params
        for flag, name in (("local_port", "local_port"), ("remote_port", "remote_port"),
                           ("gcs_ip", "gcs_ip"), ("bind_ip", "bind_ip"), ("signing_key_file", "signing_key_file"),
                           ("signing_link_id", "signing_link_id")):
            v = getattr(self.args, flag, None)
            if v is not None:
                p.set(name, v)
        node = self.node
        # Until fmu reports the flight controller's home, the parameters' (home = local origin).
        self.home = Home(p.home_lat_deg, p.home_lon_deg, p.home_alt_m)
        key, key_source = self._signing_key()
        self.companion = p.identity == contract.IDENTITY_COMPANION
        component_id = contract.COMPANION_COMPONENT_ID if self.companion else p.component_id
        # Ground-station presence (presence.py): heartbeat ages in listening time, only ground
        # stations count, no verdict before a full timeout.
        self.clock = ListeningClock()
        self.clock.tick()
        self.link = UdpLink(p.bind_ip, p.local_port, p.gcs_ip, p.remote_port, p.system_id, component_id,
                            timeout_s=p.gcs_timeout_s, signing_key=key, signing_link_id=p.signing_link_id,
                            clock=self.clock, is_ground_station=GroundStationFilter.from_param(p.gcs_system_ids))
        del key
        self.verdict = LinkVerdict(p.gcs_timeout_s, self.clock())
        self.tel = TelemetryState(self.home, companion=self.companion)
        self.sched = Scheduler(p.telemetry_period_s, self.tel.build)
        if self.companion:   # the flight controller sends the vehicle's telemetry itself
            self.sched.periods = {M.MAVLINK_MSG_ID_HEARTBEAT: 1.0}
        self.safety = SafetyRelay()
        self.objects = ObjectsRelay()
        self.table = ParamTable(p.param_services.split(","))
        self.missions = MissionProtocol(self.link.send, self._load, p.mission_item_timeout_s,
                                        p.mission_retries, p.max_mission_items, log=self.log.warn,
                                        notify=self._notify)
        self.cmds = CommandHandler(self.link.send, self, self.home, position_enu=self._position,
                                   request_message=self._request_message,
                                   set_interval=self.sched.set_interval, set_current=self._set_current,
                                   notify=self._notify)
        self.homes = HomeTracker(self.home, busy=self._upload_under_way, apply=self._apply_home)
        self.progress = Progress()       # MISSION_ITEM_REACHED / MISSION_CURRENT for our mission
        self._last_progress: tuple[int, int] = (0, 0)
        self._held_reason: str | None = None  # the mission's last HOLDING reason told to ground stations
        self.tel.progress = self.progress
        self.speeds = SpeedSchedule()    # the loaded mission's DO_CHANGE_SPEED items, per waypoint
        # (mission_id, waypoints) of the mission our items describe; one loaded some other way
        # (aero mission load/fly) is fetched from mission/srv/get so a download shows it.
        self.synced: tuple[str, int] | None = None
        self.fetching = False
        self.fetch_failed_s = -math.inf
        self.loads = 0
        self.notices = 0                      # STATUSTEXTs sent (chunk ids)
        self.gcs_last_hb: float | None = None     # ListeningClock time of the last ground station heartbeat
        self.gcs_sysid = 0
        self.gcs_alive: set[tuple[str, int]] = set()
        self.ignored: dict[str, int] = {}
        self.pub_link = node.publisher("gcs/link", GcsLink)
        self.pub_joy = node.publisher("gcs/joystick", Joystick)
        node.subscribe("state/vehicle", VehicleState, self._on_vehicle)
        node.subscribe("fmu/out/battery_status", BatteryState, lambda m: setattr(self.tel, "battery", m))
        node.subscribe("fmu/out/home_position", HomePosition, self._on_home_position)
        node.subscribe("fmu/out/vehicle_gps_position", GpsPosition, self._on_gps)
        node.subscribe("fmu/out/estimator_status", EstimatorStatus, self._on_estimator_status)
        node.subscribe("mission/status", MissionStatus, self._on_mission_status)
        node.subscribe("mission/waypoint_reached", WaypointReached, self._on_reached)
        node.subscribe("safety/status", SafetyStatus, self._on_safety)
        node.subscribe("perception/objects/events", ObjectEvent, self._on_object_event)
        node.subscribe("perception/objects", TrackedObjectArray, self._on_objects)
        if self.companion:
            node.subscribe("fmu/out/vehicle_status", VehicleStatus, self._on_vehicle_status)
        self._refresh_params()
        node.every(0.05, self._tick, name="link")
        node.every(p.param_refresh_s, self._refresh_params, name="params")
        node.every(1.0, self._publish_link, name="gcs_link")
        self.link.start(self._on_mav_locked)
        self.log.info("gcs_link", bind=f"{self.link.local_address[0]}:{self.link.local_address[1]}",
                      remote=f"{p.gcs_ip}:{p.remote_port}", signing=self.link.signing,
                      signing_key=key_source or None, signing_link_id=p.signing_link_id if key_source else None)

    def stop(self) -> None:
        link = getattr(self, "link", None)
        if link is not None:
            link.close()

    # ------------------------------------------------------------ stack inputs

    def _on_vehicle(self, msg: VehicleState) -> None:
        self.tel.vehicle = msg

    def _on_gps(self, msg: GpsPosition) -> None:
        self.tel.gps, self.tel.gps_rx_s = msg, time.monotonic()

    def _on_estimator_status(self, msg: EstimatorStatus) -> None:
        self.tel.estimator, self.tel.estimator_rx_s = msg, time.monotonic()

    def _on_safety(self, msg: SafetyStatus) -> None:
        self.tel.safety, self.tel.safety_rx_s = msg, time.monotonic()
        for severity, text in self.safety.update(msg):
            self._notify(text, None, severity)

    def _on_object_event(self, msg: ObjectEvent) -> None:
        said = event_text(msg)
        if said is not None:
            self._notify(said[1], None, said[0])

    def _on_objects(self, msg: TrackedObjectArray) -> None:
        for m in self.objects.contacts(msg, time.monotonic()):
            self.link.send(m, broadcast=True)

    def _on_vehicle_status(self, msg: VehicleStatus) -> None:
        """identity=companion: take the flight controller's system id (we are a component of it)."""
        sysid = int(msg.system_id)
        if 1 <= sysid <= 255 and sysid != self.link.system_id:
            self.log.info("system_id_from_flight_controller", system_id=sysid, previous=self.link.system_id,
                          component_id=contract.COMPANION_COMPONENT_ID)
            self.link.set_system_id(sysid)

    def _on_home_position(self, msg: HomePosition) -> None:
        home = home_from_msg(msg)
        if home is None:
            self.node.report_bad_input("fmu/out/home_position", "non-finite or out-of-range home")
            return
        was_pending = self.homes.pending
        self.homes.offer(home)
        if self.homes.pending is not None and self.homes.pending != was_pending:
            self.log.info("home_change_deferred", reason="mission upload under way",
                          latitude_deg=home.lat_deg, longitude_deg=home.lon_deg, altitude_amsl_m=home.alt_m)

    def _upload_under_way(self) -> bool:
        t = self.missions.transfer
        return self.missions.loading or (t is not None and t.direction == "upload")

    def _apply_home(self, new: Home, old: Home, source: str) -> None:
        """The home in force changed: every conversion uses it from now on; ground stations are told
        (HOME_POSITION at once, as PX4 sends it on change)."""
        self.home = self.tel.home = self.cmds.home = new
        shift = origin_shift_m(old, new)
        self.log.info("home_changed", source=source, latitude_deg=new.lat_deg, longitude_deg=new.lon_deg,
                      altitude_amsl_m=new.alt_m, local_m=[round(v, 3) for v in new.local_m],
                      previous=[old.lat_deg, old.lon_deg, old.alt_m], shift_m=round(shift, 3))
        if self.missions.items and (shift > 0.5 or abs(new.alt_m - new.local_m[2] - old.alt_m + old.local_m[2]) > 0.5):
            self.log.warn("mission_converted_about_previous_home", shift_m=round(shift, 3),
                          hint="the loaded mission's local positions were converted about the previous home; "
                               "upload it again")
        self.link.send(self.tel.home_position(), broadcast=True)

    def _on_mission_status(self, msg: MissionStatus) -> None:
        held = msg.message if msg.state == MissionStatus.STATE_HOLDING else None
        if held and held != self._held_reason:
            # why the mission holds (an unreachable waypoint, a failsafe, ...), once per reason
            self._notify(f"Mission HOLDING: {held}", None, M.MAV_SEVERITY_WARNING)
        self._held_reason = held
        self.tel.mission = msg
        if msg.mission_id and (msg.mission_id, msg.total_waypoints) != self.synced:
            self._fetch_mission()
        self._progress(self.progress.on_status(msg.mission_id, msg.state, msg.active_waypoint, msg.total_waypoints))
        self._sync_plan()
        if msg.state == MissionStatus.STATE_EXECUTING and msg.mission_id == self.speeds.mission_id:
            self._apply_mission_speed(msg.active_waypoint)   # however the mission was started
        restore = self.speeds.observe(msg.mission_id, msg.state, msg.active_waypoint, msg.total_waypoints)
        if restore is not None:
            self._restore_speed(restore, f"mission {self.speeds.mission_id or '-'} over ({msg.state})")

    @property
    def wp_seqs(self) -> list[int]:
        return self.progress.wp_seqs

    def _sync_plan(self) -> None:
        self.tel.mission_total = len(self.missions.items)
        self.tel.mission_id = self.missions.plan_id

    def _progress(self, reached: list[int]) -> None:
        """MISSION_ITEM_REACHED for each seq, to every ground station; MISSION_CURRENT at once when
        the current item or the mission state changed (as PX4 sends it on change)."""
        for seq in reached:
            self.link.send(M.MAVLink_mission_item_reached_message(seq), broadcast=True)
        if 0 <= self.progress.current < len(self.missions.items):
            self.missions.current = self.progress.current
        now = (self.progress.current, self.progress.state)
        if reached or now != self._last_progress:
            self._last_progress = now
            self._sync_plan()
            self.link.send(self.tel.mission_current(), broadcast=True)

    def _on_reached(self, msg: WaypointReached) -> None:
        self._progress(self.progress.on_reached(msg.mission_id, msg.index))
        if msg.mission_id == self.speeds.mission_id:
            self._apply_mission_speed(msg.index + 1)         # the speed for the next leg, at once

    def _position(self) -> tuple[float, float, float]:
        v = self.tel.vehicle
        return (v.position_m.x, v.position_m.y, v.position_m.z) if v else (0.0, 0.0, 0.0)

    # ------------------------------------------------------------ timers

    @property
    def gcs_connected(self) -> bool:
        return bool(self.verdict.connected)

    def _tick(self) -> None:
        stall = self.clock.tick()
        if stall:
            self.log.warn("gcs_stalled", stalled_s=round(stall + self.clock.stall_s, 2),
                          hint="not counted in ground-station heartbeat ages")
        now = time.monotonic()
        for msg in self.sched.due(now):
            self.link.send(msg)
        self.missions.tick(now)
        self.homes.poll()                # a home held back during an upload, once it is over
        self.cmds.tick(now, timeout_s=self.params.call_timeout_s + 2.0)
        self._sync_plan()
        self._check_peers(self.clock())

    def _check_peers(self, now: float) -> None:
        """gcs/link is up while any ground station is alive (heartbeat within gcs_timeout_s of
        listening time); no verdict before a full timeout after start (presence.py)."""
        alive = {p.address for p in self.link.ground_stations(now)}
        for addr in sorted(self.gcs_alive - alive):
            self.log.warn("gcs_lost", address=f"{addr[0]}:{addr[1]}", timeout_s=self.params.gcs_timeout_s)
        for addr in sorted(alive - self.gcs_alive):
            peer = self.link.peers.get(addr)
            self.log.info("gcs_heard", address=f"{addr[0]}:{addr[1]}", system_id=peer.system_id if peer else None)
        self.gcs_alive = alive
        before = self.verdict.connected
        now_connected = self.verdict.update(now, bool(alive))
        if now_connected == before:
            return
        if now_connected:
            self.log.info("gcs_link_up", system_id=self.gcs_sysid,
                          address=f"{self.link.remote[0]}:{self.link.remote[1]}")
        elif before:
            self.log.warn("gcs_link_lost", timeout_s=self.params.gcs_timeout_s)
        else:
            self.log.info("gcs_link_none", listened_s=self.params.gcs_timeout_s)
        self._publish_link()

    def _addresses(self) -> str:
        return ",".join(f"{a[0]}:{a[1]}" for a in sorted(self.gcs_alive))

    def _publish_link(self) -> None:
        if self.verdict.connected is None:
            return   # no verdict yet (presence.py)
        age = self.clock() - self.gcs_last_hb if self.gcs_last_hb is not None else None
        addr = f"{self.link.remote[0]}:{self.link.remote[1]}" if self.link.learnt else ""
        self.pub_link.publish(GcsLink(header=self.node.header(), connected=self.gcs_connected, address=addr,
                                      system_id=self.gcs_sysid, last_heartbeat_age_s=age,
                                      packets_received=self.link.parser.received,
                                      packets_invalid=self.link.parser.invalid_total))

    # ------------------------------------------------------------ MAVLink in

    def _on_mav_locked(self, msg) -> None:
        self.node.run_callback(f"mavlink:{msg.get_type()}", self._on_mav, msg)

    def _on_mav(self, msg) -> None:
        t = msg.get_type()
        now = time.monotonic()
        target_sys = getattr(msg, "target_system", None)
        if target_sys not in (None, 0, self.link.system_id) and t != "FILE_TRANSFER_PROTOCOL":
            self.ignored["other_target"] = self.ignored.get("other_target", 0) + 1
            return
        if self.companion and t != "HEARTBEAT":
            # Only what is addressed to our component; the flight controller answers the rest
            # (parameters asked of every component are ours to answer too).
            comp = getattr(msg, "target_component", None)
            if comp is not None and comp != self.link.component_id and not (
                    comp == 0 and t in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ")):
                self.ignored["other_component"] = self.ignored.get("other_component", 0) + 1
                return
        if t == "HEARTBEAT":
            if msg.get_srcSystem() != self.link.system_id and self.link.is_ground_station(msg):
                self.gcs_last_hb = self.clock()
                self.gcs_sysid = msg.get_srcSystem()
                self._check_peers(self.gcs_last_hb)
            elif msg.get_srcSystem() != self.link.system_id:
                self.ignored["heartbeat_not_gcs"] = self.ignored.get("heartbeat_not_gcs", 0) + 1
        elif self.missions.handle(msg, now):
            pass
        elif t in ("COMMAND_LONG", "COMMAND_INT"):
            self.cmds.handle(msg, now)
        elif t == "PARAM_REQUEST_LIST":
            for i, e in enumerate(self.table.entries):
                self.link.send(self.table.value_msg(i, e))
        elif t == "PARAM_REQUEST_READ":
            self._param_read(msg)
        elif t == "PARAM_SET":
            self._param_set(msg)
        elif t == "MISSION_SET_CURRENT":
            if self._set_current(msg.seq):
                self.link.send(self.tel.mission_current())
        elif t == "SET_MODE":
            mode = mode_from_custom_mode(msg.base_mode, msg.custom_mode)
            if mode is None:
                self.cmds.ack(M.MAVLINK_MSG_ID_SET_MODE, M.MAV_RESULT_DENIED, (msg.get_srcSystem(), msg.get_srcComponent()))
            else:
                peer = (msg.get_srcSystem(), msg.get_srcComponent())
                self.set_mode(mode, lambda ok, _m, *_: self.cmds.ack(
                    M.MAVLINK_MSG_ID_SET_MODE, M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_DENIED, peer))
        elif t == "MANUAL_CONTROL":
            self.pub_joy.publish(Joystick(header=self.node.header(), x=msg.x / 1000.0, y=msg.y / 1000.0,
                                          z=msg.z / 1000.0, r=msg.r / 1000.0, buttons=msg.buttons,
                                          source_system=msg.get_srcSystem()))
        elif t == "FILE_TRANSFER_PROTOCOL":
            self.link.send(ftp.nak(msg, ftp.ERR_FILE_NOT_FOUND))   # ground stations fall back at once
        elif t == "TIMESYNC":
            if msg.tc1 == 0:
                self.link.send(M.MAVLink_timesync_message(time.monotonic_ns(), msg.ts1))
        else:
            self.ignored[t] = self.ignored.get(t, 0) + 1

    # ------------------------------------------------------------ parameters

    def _refresh_params(self) -> None:
        for svc in self.table.sources:
            if svc == self.NAME:
                self.table.update_service(svc, self.node.param_list().params)
                continue

            def done(res, svc=svc) -> None:
                if isinstance(res, CallError):
                    return  # service not running: keep what we had
                self.table.update_service(svc, res.params)

            self.node.call_async(f"config/{svc}/@params", None, ParamList, done, timeout_s=2.0)

    def _param_read(self, msg) -> None:
        """PARAM_REQUEST_READ; an unknown name gets no PARAM_VALUE (PX4), only PARAM_ERROR."""
        name = decode_param_id(msg.param_id)
        found = self.table.lookup(name, msg.param_index)
        if found is not None:
            self.link.send(self.table.value_msg(*found))
            return
        self.ignored["unknown_param"] = self.ignored.get("unknown_param", 0) + 1
        if msg.param_index >= 0:
            self._notify(f"[pm] unknown param ID: {msg.param_index}", self._peer(msg), M.MAV_SEVERITY_INFO)
        self._param_error(msg, name, M.MAV_PARAM_ERROR_DOES_NOT_EXIST)

    def _peer(self, msg) -> tuple[int, int]:
        return msg.get_srcSystem(), msg.get_srcComponent()

    def _param_error(self, msg, name: str, error: int) -> None:
        self.link.send(M.MAVLink_param_error_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                     name.encode()[:16], getattr(msg, "param_index", -1), error))

    def _param_set(self, msg) -> None:
        """PARAM_SET: to the owning service(s) (an alias: every owner present), then the value in
        force to every ground station (as PX4 does); refusals explained in a STATUSTEXT."""
        name = decode_param_id(msg.param_id)
        peer = self._peer(msg)
        found = self.table.lookup(name)
        if found is None:
            self.ignored["unknown_param"] = self.ignored.get("unknown_param", 0) + 1
            self._notify(f"[pm] unknown param: {name}", peer, M.MAV_SEVERITY_INFO)
            self._param_error(msg, name, M.MAV_PARAM_ERROR_DOES_NOT_EXIST)
            return
        index, entry = found
        if entry.readonly:
            self._notify(f"{name} is read-only: {entry.readonly}", peer, M.MAV_SEVERITY_WARNING)
            self._param_error(msg, name, M.MAV_PARAM_ERROR_READ_ONLY)
            self.link.send(self.table.value_msg(index, entry))
            return
        try:
            value = decode_value(msg.param_value, msg.param_type, entry.ptype)
        except Exception:  # noqa: BLE001 - an undecodable value: echo the current one
            self.link.send(self.table.value_msg(index, entry))
            return
        targets = entry.targets or ((entry.service, entry.name),)
        replies: dict[tuple[str, str], ParamSetReply] = {}

        def record(target: tuple[str, str], reply: ParamSetReply) -> None:
            replies[target] = reply
            if len(replies) < len(targets):
                return
            for (svc, pname), rep in replies.items():
                if rep.success and rep.value is not None:
                    self.table.set_value(svc, pname, rep.value)
                elif not rep.success:
                    self.log.warn("param_set_rejected", param=name, service=svc, name=pname, value=value,
                                  error=rep.message)
                    if entry.targets:
                        self._notify(f"{name}: {svc} refused {value}: {rep.message}", peer, M.MAV_SEVERITY_WARNING)
            now = self.table.lookup(name)
            if now is not None:   # always echoed, to every ground station (as PX4 does): the value in force
                self.link.send(self.table.value_msg(*now), broadcast=True)

        for svc, pname in targets:
            if svc == self.NAME:
                record((svc, pname), self.node.set_param(pname, value))
                continue

            def done(res, target=(svc, pname)) -> None:
                if isinstance(res, CallError):
                    res = ParamSetReply(success=False, message=str(res))
                record(target, res)

            self.node.call_async(f"config/{svc}/@set", ParamSet(name=pname, value=value), ParamSetReply, done,
                                 timeout_s=self.params.call_timeout_s)

    # ------------------------------------------------------------ missions

    def _load(self, items, done) -> None:
        default_alt = self.table.find("mission", "takeoff_altitude_m")
        # PX4: an item without an acceptance radius (param2 0) uses NAV_ACC_RAD (the planner's)
        radius = self.table.find("planner", "acceptance_radius_m")
        self.loads += 1
        try:
            mission, seqs = convert_items(items, self.home, mission_id=f"gcs-{self.loads}",
                                          default_takeoff_m=float(default_alt[1].value) if default_alt else 3.0,
                                          acceptance_radius_m=float(radius[1].value) if radius else 0.5)
        except MissionConversionError as e:
            done(False, str(e), e.result)
            return
        speeds = waypoint_speeds(items, seqs)
        found = self.table.find(SPEED_SERVICE, SPEED_PARAM)
        if found is not None:
            lo, hi = found[1].min, found[1].max
            for v in speeds:
                if v is not None and v != SPEED_DEFAULT and ((lo is not None and v < lo) or (hi is not None and v > hi)):
                    done(False, f"DO_CHANGE_SPEED {v} m/s outside {found[1].mav_name} [{lo}, {hi}]",
                         M.MAV_MISSION_INVALID_PARAM2)
                    return

        def loaded(res) -> None:
            if isinstance(res, CallError):
                done(False, str(res), M.MAV_MISSION_ERROR)
                return
            if res.success:
                self.progress.load(mission.mission_id, items, seqs)
                self._end_speed_scope("mission replaced")
                self.speeds = SpeedSchedule(speeds, mission.mission_id)
                self.synced = (mission.mission_id, len(mission.waypoints))
            done(res.success, res.message, M.MAV_MISSION_DENIED)   # accepts the items: the new plan id
            if res.success:
                # total and plan id together, once the items are in: MISSION_CURRENT streamed in
                # between carried the new total with the old plan id (0 after a first upload)
                self._sync_plan()
                self.tel.mission_seq = 0

        self.node.call_async("mission/srv/load", LoadMissionRequest(mission_json=mission.to_json()),
                             LoadMissionReply, loaded, timeout_s=self.params.call_timeout_s)

    def _fetch_mission(self) -> None:
        """The mission service has a mission we did not upload: fetch it (mission/srv/get) and
        serve it as items (NAV_TAKEOFF + NAV_WAYPOINTs, see mission_items.mission_to_items). Not while
        a transfer is under way; a failed fetch is retried after 5 s."""
        busy = self.missions.loading or self.missions.transfer is not None
        if self.fetching or busy or time.monotonic() - self.fetch_failed_s < 5.0:
            return
        self.fetching = True

        def done(res) -> None:
            self.fetching = False
            if isinstance(res, CallError) or not res.success:
                self.fetch_failed_s = time.monotonic()
                return
            key = (res.mission_id, res.num_waypoints)
            if key == self.synced or self.missions.loading or self.missions.transfer is not None:
                return   # ours (an upload overtook the status), or busy: the next status retries
            try:
                mission = parse_mission(res.mission_json)
            except SchemaError as e:
                self.fetch_failed_s = time.monotonic()
                self.log.warn("mission_fetch_invalid", error=str(e))
                return
            self.missions.items = mission_to_items(mission, self.home)
            self.missions.current = 0
            self.progress.load(mission.mission_id, self.missions.items,
                               list(range(1, len(mission.waypoints) + 1)))   # item 0 is the takeoff
            self._sync_plan()
            self._end_speed_scope("mission replaced")
            self.speeds = SpeedSchedule([], mission.mission_id)
            self.tel.mission_seq = 0
            self.synced = key
            self.log.info("mission_synced", mission_id=mission.mission_id, items=len(self.missions.items))

        self.node.call_async("mission/srv/get", Empty(), GetMissionReply, done, timeout_s=self.params.call_timeout_s)

    def _set_current(self, seq: int) -> bool:
        """MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT: the mission jumps (flies to that item
        next, as PX4 does), not only MISSION_CURRENT; a refusal by the mission is a STATUSTEXT."""
        k = self.progress.waypoint_for(seq)
        ok = k is not None and self.missions.set_current(seq)
        if ok:
            def done(jumped: bool, message: str, failed: bool = False) -> None:
                if not jumped:
                    self._notify(f"Mission jump to item {seq} refused: {message}", None)
            self.node.call_async("mission/srv/command", MissionCommand(command="SET_CURRENT", waypoint_index=k),
                                 Reply, self._reply_cb(done), timeout_s=self.params.call_timeout_s)
            self.progress.set_current(seq)
            self.tel.mission_seq = seq
        return ok

    def _notify(self, text: str, peer: tuple[int, int] | None, severity: int = M.MAV_SEVERITY_CRITICAL) -> None:
        """A STATUSTEXT (critical, as PX4 reports a refused mission or mode change) to the ground
        station `peer` (None: to every ground station)."""
        self.notices += 1
        for m in statustext(severity, text, self.notices):
            if peer is None:
                self.link.send(m, broadcast=True)
            else:
                self.link.send(m, peer=peer)

    def _request_message(self, msg_id: int, param2: float) -> int:
        msg = self.tel.build(msg_id)
        if msg is None:
            return M.MAV_RESULT_UNSUPPORTED
        self.link.send(msg)
        return M.MAV_RESULT_ACCEPTED

    # ------------------------------------------------------------ ops (commands -> stack)

    def _reply_cb(self, done):
        def cb(res) -> None:
            if isinstance(res, CallError):
                done(False, str(res), True)      # the call failed (FAILED), not a refusal (DENIED)
            else:
                done(res.success, res.message)
        return cb

    def arm(self, arm: bool, force: bool, done) -> None:
        self.node.call_async("fmu/srv/arm", ArmRequest(arm=arm, force=force), ArmReply,
                             self._reply_cb(done), timeout_s=self.params.call_timeout_s)

    def mission_command(self, command: str, done) -> None:
        self.node.call_async("mission/srv/command", MissionCommand(command=command), Reply,
                             self._reply_cb(done), timeout_s=self.params.call_timeout_s)

    def set_mode(self, mode: str, done) -> None:
        if mode == "MISSION":
            self.mission_start(done)
        elif mode == "TAKEOFF":
            self.takeoff(None, done)
        elif mode in ("HOLD", "LAND", "RTL"):
            # Through the mission manager (so it stops pushing goals); on the ground it refuses,
            # then the flight controller decides.
            def after(ok: bool, message: str, failed: bool = False) -> None:
                if ok:
                    done(True, message)
                else:
                    self._fmu_set_mode(mode, done)
            self.mission_command(mode, after)
        else:
            self._fmu_set_mode(mode, done)

    def _fmu_set_mode(self, mode: str, done) -> None:
        self.node.call_async("fmu/srv/set_mode", SetModeRequest(mode=mode), SetModeReply,
                             self._reply_cb(done), timeout_s=self.params.call_timeout_s)

    def mission_start(self, done) -> None:
        st = self.tel.mission
        # The mission manager (re)starts at its active waypoint, or at 0 when not started/complete.
        self.speeds.reset()
        k = st.active_waypoint if st is not None and 0 <= st.active_waypoint < len(self.wp_seqs) else 0
        self._apply_mission_speed(k)

        def started(ok: bool, message: str, failed: bool = False) -> None:
            if not ok:
                self._end_speed_scope("mission start failed")
            done(ok, message, failed)

        if st is not None and st.state == MissionStatus.STATE_IDLE:
            # On the ground: take off first; the mission manager starts the mission once up.
            def after_takeoff(ok: bool, message: str, failed: bool = False) -> None:
                if not ok:
                    started(False, message, failed)
                else:
                    self.mission_command("START", started)
            self.mission_command("TAKEOFF", after_takeoff)
        else:
            self.mission_command("START", started)

    def takeoff(self, altitude_m: float | None, done) -> None:
        if altitude_m is None:
            self.mission_command("TAKEOFF", done)
            return
        self.node.call_async("mission/action/takeoff/goal", TakeoffGoal(target_altitude_m=altitude_m), GoalReply,
                             self._reply_cb(done), timeout_s=self.params.call_timeout_s)

    def _planner_speed(self) -> float | None:
        found = self.table.find(SPEED_SERVICE, SPEED_PARAM)
        return float(found[1].value) if found is not None else None

    def change_speed(self, speed_mps: float | None, done) -> None:
        """DO_CHANGE_SPEED (command): the planner's live speed limit; None = its declared default.
        While our mission runs the change is mission-scoped (ends with it, mission_speed.py)."""
        st = self.tel.mission
        if st is not None and st.mission_id == self.speeds.mission_id and st.state in SpeedSchedule.RUNNING:
            self.speeds.begin(self._planner_speed())
        self._set_planner_speed(speed_mps, done)

    def _set_planner_speed(self, speed_mps: float | None, done) -> None:
        found = self.table.find(SPEED_SERVICE, SPEED_PARAM)
        if speed_mps is None:
            if found is None or found[1].default is None:
                done(False, f"{SPEED_SERVICE}.{SPEED_PARAM} default unknown (is the planner running?)")
                return
            speed_mps = float(found[1].default)

        def reply(res) -> None:
            if isinstance(res, CallError):
                done(False, str(res), True)
                return
            if res.success and res.value is not None:
                self.table.set_value(SPEED_SERVICE, SPEED_PARAM, res.value)
            if not res.success:
                self.log.warn("change_speed_rejected", speed_mps=speed_mps, error=res.message)
            done(res.success, res.message)

        self.node.call_async(f"config/{SPEED_SERVICE}/@set", ParamSet(name=SPEED_PARAM, value=float(speed_mps)),
                             ParamSetReply, reply, timeout_s=self.params.call_timeout_s)

    def _apply_mission_speed(self, k: int) -> None:
        speed = self.speeds.due(k)
        if speed is None:
            return
        self.speeds.begin(self._planner_speed())
        self.log.info("mission_speed", waypoint=k, speed_mps=speed if speed != SPEED_DEFAULT else "default")
        self._set_planner_speed(None if speed == SPEED_DEFAULT else speed,
                                lambda ok, message, *_: None if ok else self.log.warn("mission_speed_failed",
                                                                                      error=message))

    def _end_speed_scope(self, why: str) -> None:
        restore = self.speeds.end()
        if restore is not None:
            self._restore_speed(restore, why)

    def _restore_speed(self, speed_mps: float, why: str) -> None:
        """The mission that changed the planner's speed is over: the speed from before it."""
        self.log.info("mission_speed_restored", speed_mps=speed_mps, reason=why)
        self._set_planner_speed(speed_mps, lambda ok, message, *_: None if ok else self.log.warn(
            "mission_speed_restore_failed", speed_mps=speed_mps, error=message))

    def goto(self, enu, yaw_rad, done) -> None:
        goal = GoToPositionGoal(position_m=Vector3(x=enu[0], y=enu[1], z=enu[2]), yaw_rad=yaw_rad)
        self.node.call_async("mission/action/goto/goal", goal, GoalReply, self._reply_cb(done),
                             timeout_s=self.params.call_timeout_s)

    # ------------------------------------------------------------ diagnostics

    def health(self) -> Health:
        inv = self.link.parser.invalid_total
        values = {
            "gcs_connected": self.gcs_connected, "gcs_address": f"{self.link.remote[0]}:{self.link.remote[1]}",
            "ground_stations": len(self.gcs_alive), "ground_station_addresses": self._addresses(),
            "signing": self.link.signing, "signing_rejected": self.link.parser.signing_rejected,
            "identity": f"{self.params.identity} {self.link.system_id}:{self.link.component_id}",
            "geofence_reported": bool(self.tel.fence_bits()[0]),
            "bind": f"{self.link.local_address[0]}:{self.link.local_address[1]}",
            "mavlink_rx": self.link.parser.received, "mavlink_tx": self.link.sent,
            "mavlink_invalid": inv, "params_exposed": len(self.table), "mission_items": len(self.missions.items),
            "uploads_accepted": self.missions.uploads_accepted, "uploads_rejected": self.missions.uploads_rejected,
            "home_source": self.homes.source,
            "home": f"{self.home.lat_deg:.7f},{self.home.lon_deg:.7f},{self.home.alt_m:.2f}",
            "home_pending": self.homes.pending is not None,
        }
        for k, n in self.link.parser.invalid.items():
            values[f"mavlink_invalid[{k}]"] = n
        for k, n in self.missions.errors.items():
            values[f"mission_protocol[{k}]"] = n
        for k, n in self.cmds.results.items():
            values[f"command_ack[{k}]"] = n
        values["command_retransmissions"] = self.cmds.retransmissions
        values["ignored"] = sum(self.ignored.values())
        for k, n in self.ignored.items():
            values[f"ignored[{k}]"] = n
        values["stalls"] = self.clock.stalls
        level, message = DiagnosticStatus.OK, "ground station connected" if self.gcs_connected else "no ground station"
        if self.tel.vehicle is None:
            level, message = DiagnosticStatus.WARN, f"{message}; no state/vehicle"
        elif self.homes.source == SOURCE_PARAM:
            message += "; home from parameters (no fmu/out/home_position yet)"
        if inv or self.missions.errors:
            level = max(level, DiagnosticStatus.WARN)
            message += f"; {inv + sum(self.missions.errors.values())} invalid MAVLink inputs dropped"
        return Health(level, message, values)


def main(argv=None) -> int:
    return run(GcsService, argv)
