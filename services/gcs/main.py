"""Process shell: the UDP MAVLink link on one side, the stack (Zenoh) on the other.

A received MAVLink message goes through one table, `handlers`: {message type: handler(msg,
now_s)}; adding a message is one entry and its handler. What a handler asks of the stack goes
through the operations object (ops.StackOps), each call answering one Outcome.

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

import os
import time
from typing import Any, Callable

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import (
    BatteryState, DiagnosticStatus, EstimatorStatus, GcsLink, GpsPosition, HomePosition, Joystick, MissionStatus,
    ObjectEvent, SafetyStatus, TrackedObjectArray, VehicleState, VehicleStatus, WaypointReached,
)
from aeroperception.services.mavlink import ftp
from aeroperception.services.runtime import Health, Service, run

from . import contract
from .commands import CommandHandler
from .config import GcsConfig
from .home import SOURCE_PARAM, Home, HomeTracker, home_from_msg, mission_needs_upload_again, origin_shift_m
from .link import UdpLink, load_signing_key, parse_signing_key
from .messages import statustext
from .mission_progress import Progress
from .mission_sync import MissionSync
from .objects_relay import ObjectsRelay, event_text
from .ops import StackOps
from .param_protocol import ParamProtocol
from .params import ParamTable
from .presence import GroundStationFilter, ListeningClock, Presence
from .routing import ignored_because
from .safety_relay import SafetyRelay
from .telemetry import Scheduler, TelemetryState

Handler = Callable[[Any, float], None]   # handler(msg, now_s)


class GcsService(Service):
    """MAVLink endpoint for ground stations: presents the stack as one PX4 autopilot."""

    NAME = contract.NAME
    PARAMS = contract.PARAMS
    CONTRACT = contract
    CONFIG = GcsConfig
    CLI_PARAMS = ("local_port", "remote_port", "gcs_ip", "bind_ip", "signing_key_file", "signing_link_id")

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

    def wire(self) -> None:
        """The command-line flags are the parameters of the same names, set before the config is built."""
        for name in self.CLI_PARAMS:
            v = getattr(self.args, name, None)
            if v is not None:
                self.params.set(name, v)
        super().wire()

    def bind_selection(self) -> dict[str, Any]:
        """The flight controller's system id is taken only as its onboard computer (identity=companion)."""
        if self.cfg.identity == contract.IDENTITY_COMPANION:
            return {}
        return dict(inputs=[k for k in contract.INPUTS if k != "fmu/out/vehicle_status"])

    def on_config(self, cfg: GcsConfig) -> None:
        self.ops.timeout_s = cfg.call_timeout_s     # the only live parameter (contract.PARAMS)

    def _signing_key(self) -> tuple[bytes | None, str]:
        """The signing key and where it came from (never the key itself in any message)."""
        path = self.cfg.signing_key_file
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
        p, node = self.cfg, self.node
        self.notices = 0                      # STATUSTEXTs sent (chunk ids)
        self.ignored: dict[str, int] = {}     # MAVLink inputs dropped, by kind (diagnostics)
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
        self.presence = Presence(self.link, p.gcs_timeout_s, self.clock(), self.log)
        self.tel = TelemetryState(self.home, companion=self.companion)
        self.sched = Scheduler(p.telemetry_period_s, self.tel.build)
        if self.companion:   # the flight controller sends the vehicle's telemetry itself
            self.sched.periods = {M.MAVLINK_MSG_ID_HEARTBEAT: 1.0}
        self.safety = SafetyRelay()
        self.objects = ObjectsRelay()
        self.table = ParamTable(p.param_services)
        progress = self.tel.progress = Progress()   # MISSION_ITEM_REACHED / MISSION_CURRENT for our mission
        self.ops = StackOps(node.call_async, p.call_timeout_s, self.table, self.tel, progress, self.log)
        self.mission = MissionSync(self.ops, progress, self.tel, self.table, lambda: self.home, self.link.send,
                                   self._notify, self.log, item_timeout_s=p.mission_item_timeout_s,
                                   retries=p.mission_retries, max_items=p.max_mission_items)
        self.cmds = CommandHandler(self.link.send, self.ops, self.home, position_enu=self._position,
                                   request_message=self._request_message,
                                   set_interval=self.sched.set_interval, set_current=self.mission.set_current,
                                   notify=self._notify)
        self.param_proto = ParamProtocol(self.table, self.ops, self.NAME, node.param_list, node.set_param,
                                         self.link.send, self._notify, self._ignore, self.log)
        self.homes = HomeTracker(self.home, busy=lambda: self.mission.upload_under_way, apply=self._apply_home)
        self.handlers: dict[str, Handler] = {
            "HEARTBEAT": self._on_heartbeat,
            **self.mission.protocol.handlers(),           # MISSION_COUNT, MISSION_ITEM_INT, ... (mission_protocol.py)
            "MISSION_SET_CURRENT": self._on_mission_set_current,
            "COMMAND_LONG": self.cmds.handle,
            "COMMAND_INT": self.cmds.handle,
            "PARAM_REQUEST_LIST": self.param_proto.on_request_list,
            "PARAM_REQUEST_READ": self.param_proto.on_request_read,
            "PARAM_SET": self.param_proto.on_set,
            "SET_MODE": self.cmds.on_set_mode,
            "MANUAL_CONTROL": self._on_manual_control,
            "FILE_TRANSFER_PROTOCOL": self._on_ftp,
            "TIMESYNC": self._on_timesync,
        }
        self.param_proto.refresh()
        node.every(0.05, self._tick, name="link")
        node.every(p.param_refresh_s, self.param_proto.refresh, name="params")
        node.every(1.0, self._publish_link, name="gcs_link")
        self.link.start(self._on_mav_locked)
        self.log.info("gcs_link", bind=f"{self.link.local_address[0]}:{self.link.local_address[1]}",
                      remote=f"{p.gcs_ip}:{p.remote_port}", signing=self.link.signing,
                      signing_key=key_source or None, signing_link_id=p.signing_link_id if key_source else None)

    def stop(self) -> None:
        link = getattr(self, "link", None)
        if link is not None:
            link.close()

    # ------------------------------------------------------------ MAVLink in

    def _on_mav_locked(self, msg) -> None:
        self.node.run_callback(f"mavlink:{msg.get_type()}", self._on_mav, msg)

    def _on_mav(self, msg) -> None:
        t = msg.get_type()
        why = ignored_because(t, getattr(msg, "target_system", None), getattr(msg, "target_component", None),
                              self.link.system_id, self.link.component_id, self.companion)
        if why:
            self._ignore(why)
            return
        handler = self.handlers.get(t)
        if handler is None:
            self._ignore(t)
        else:
            handler(msg, time.monotonic())

    def _ignore(self, kind: str) -> None:
        self.ignored[kind] = self.ignored.get(kind, 0) + 1

    def _on_heartbeat(self, msg, now_s: float) -> None:
        if msg.get_srcSystem() == self.link.system_id:
            return
        if self.link.is_ground_station(msg):
            if self.presence.heard(msg.get_srcSystem(), self.clock()):
                self._publish_link()
        else:
            self._ignore("heartbeat_not_gcs")

    def _on_mission_set_current(self, msg, now_s: float) -> None:
        if self.mission.set_current(msg.seq):
            self.link.send(self.tel.mission_current())

    def _on_manual_control(self, msg, now_s: float) -> None:
        self.io["gcs/joystick"].publish(Joystick(header=self.node.header(), x=msg.x / 1000.0, y=msg.y / 1000.0,
                                      z=msg.z / 1000.0, r=msg.r / 1000.0, buttons=msg.buttons,
                                      source_system=msg.get_srcSystem()))

    def _on_ftp(self, msg, now_s: float) -> None:
        self.link.send(ftp.nak(msg, ftp.ERR_FILE_NOT_FOUND))   # ground stations fall back at once

    def _on_timesync(self, msg, now_s: float) -> None:
        if msg.tc1 == 0:
            self.link.send(M.MAVLink_timesync_message(time.monotonic_ns(), msg.ts1))

    def _request_message(self, msg_id: int, param2: float) -> int:
        msg = self.tel.build(msg_id)
        if msg is None:
            return M.MAV_RESULT_UNSUPPORTED
        self.link.send(msg)
        return M.MAV_RESULT_ACCEPTED

    def _notify(self, text: str, peer: tuple[int, int] | None, severity: int = M.MAV_SEVERITY_CRITICAL) -> None:
        """A STATUSTEXT (critical, as PX4 reports a refused mission or mode change) to the ground
        station `peer` (None: to every ground station)."""
        self.notices += 1
        for m in statustext(severity, text, self.notices):
            if peer is None:
                self.link.send(m, broadcast=True)
            else:
                self.link.send(m, peer=peer)

    # ------------------------------------------------------------ stack inputs (contract.INPUTS)

    def on_state_vehicle(self, msg: VehicleState) -> None:
        self.tel.vehicle = msg

    def on_fmu_out_battery_status(self, msg: BatteryState) -> None:
        self.tel.battery = msg

    def on_fmu_out_vehicle_gps_position(self, msg: GpsPosition) -> None:
        self.tel.gps, self.tel.gps_rx_s = msg, time.monotonic()

    def on_fmu_out_estimator_status(self, msg: EstimatorStatus) -> None:
        self.tel.estimator, self.tel.estimator_rx_s = msg, time.monotonic()

    def on_mission_status(self, msg: MissionStatus) -> None:
        self.mission.on_status(msg)

    def on_mission_waypoint_reached(self, msg: WaypointReached) -> None:
        self.mission.on_reached(msg)

    def on_safety_status(self, msg: SafetyStatus) -> None:
        self.tel.safety, self.tel.safety_rx_s = msg, time.monotonic()
        for severity, text in self.safety.update(msg):
            self._notify(text, None, severity)

    def on_perception_objects_events(self, msg: ObjectEvent) -> None:
        said = event_text(msg)
        if said is not None:
            self._notify(said[1], None, said[0])

    def on_perception_objects(self, msg: TrackedObjectArray) -> None:
        for m in self.objects.contacts(msg, time.monotonic()):
            self.link.send(m, broadcast=True)

    def on_fmu_out_vehicle_status(self, msg: VehicleStatus) -> None:
        """identity=companion: take the flight controller's system id (we are a component of it)."""
        sysid = int(msg.system_id)
        if 1 <= sysid <= 255 and sysid != self.link.system_id:
            self.log.info("system_id_from_flight_controller", system_id=sysid, previous=self.link.system_id,
                          component_id=contract.COMPANION_COMPONENT_ID)
            self.link.set_system_id(sysid)

    def on_fmu_out_home_position(self, msg: HomePosition) -> None:
        home = home_from_msg(msg)
        if home is None:
            self.node.report_bad_input("fmu/out/home_position", "non-finite or out-of-range home")
            return
        was_pending = self.homes.pending
        self.homes.offer(home)
        if self.homes.pending is not None and self.homes.pending != was_pending:
            self.log.info("home_change_deferred", reason="mission upload under way",
                          latitude_deg=home.lat_deg, longitude_deg=home.lon_deg, altitude_amsl_m=home.alt_m)

    def _apply_home(self, new: Home, old: Home, source: str) -> None:
        """The home in force changed: every conversion uses it from now on; ground stations are told
        (HOME_POSITION at once, as PX4 sends it on change)."""
        self.home = self.tel.home = self.cmds.home = new
        shift = origin_shift_m(old, new)
        self.log.info("home_changed", source=source, latitude_deg=new.lat_deg, longitude_deg=new.lon_deg,
                      altitude_amsl_m=new.alt_m, local_m=[round(v, 3) for v in new.local_m],
                      previous=[old.lat_deg, old.lon_deg, old.alt_m], shift_m=round(shift, 3))
        if self.mission.protocol.items and mission_needs_upload_again(old, new):
            self.log.warn("mission_converted_about_previous_home", shift_m=round(shift, 3),
                          hint="the loaded mission's local positions were converted about the previous home; "
                               "upload it again")
        self.link.send(self.tel.home_position(), broadcast=True)

    def _position(self) -> tuple[float, float, float]:
        v = self.tel.vehicle
        return (v.position_m.x, v.position_m.y, v.position_m.z) if v else (0.0, 0.0, 0.0)

    # ------------------------------------------------------------ timers, gcs/link

    def _tick(self) -> None:
        stall = self.clock.tick()
        if stall:
            self.log.warn("gcs_stalled", stalled_s=round(stall + self.clock.stall_s, 2),
                          hint="not counted in ground-station heartbeat ages")
        now = time.monotonic()
        for msg in self.sched.due(now):
            self.link.send(msg)
        self.mission.protocol.tick(now)
        self.homes.poll()                # a home held back during an upload, once it is over
        self.cmds.tick(now, timeout_s=self.cfg.call_timeout_s + 2.0)
        self.mission.sync_plan()
        if self.presence.update(self.clock()):   # gcs/link at once on a change (presence.py)
            self._publish_link()

    def _publish_link(self) -> None:
        pr = self.presence
        if pr.verdict.connected is None:
            return   # no verdict yet (presence.py)
        age = self.clock() - pr.last_heartbeat_s if pr.last_heartbeat_s is not None else None
        addr = f"{self.link.remote[0]}:{self.link.remote[1]}" if self.link.learnt else ""
        self.io["gcs/link"].publish(GcsLink(header=self.node.header(), connected=pr.connected, address=addr,
                                      system_id=pr.system_id, last_heartbeat_age_s=age,
                                      packets_received=self.link.parser.received,
                                      packets_invalid=self.link.parser.invalid_total))

    # ------------------------------------------------------------ diagnostics

    def health(self) -> Health:
        inv = self.link.parser.invalid_total
        missions = self.mission.protocol
        values = {
            "gcs_connected": self.presence.connected,
            "gcs_address": f"{self.link.remote[0]}:{self.link.remote[1]}",
            "ground_stations": len(self.presence.alive), "ground_station_addresses": self.presence.addresses(),
            "signing": self.link.signing, "signing_rejected": self.link.parser.signing_rejected,
            "identity": f"{self.cfg.identity} {self.link.system_id}:{self.link.component_id}",
            "geofence_reported": bool(self.tel.fence_bits()[0]),
            "bind": f"{self.link.local_address[0]}:{self.link.local_address[1]}",
            "mavlink_rx": self.link.parser.received, "mavlink_tx": self.link.sent,
            "mavlink_invalid": inv, "params_exposed": len(self.table), "mission_items": len(missions.items),
            "uploads_accepted": missions.uploads_accepted, "uploads_rejected": missions.uploads_rejected,
            "home_source": self.homes.source,
            "home": f"{self.home.lat_deg:.7f},{self.home.lon_deg:.7f},{self.home.alt_m:.2f}",
            "home_pending": self.homes.pending is not None,
        }
        for k, n in self.link.parser.invalid.items():
            values[f"mavlink_invalid[{k}]"] = n
        for k, n in missions.errors.items():
            values[f"mission_protocol[{k}]"] = n
        for k, n in self.cmds.results.items():
            values[f"command_ack[{k}]"] = n
        values["command_retransmissions"] = self.cmds.retransmissions
        values["ignored"] = sum(self.ignored.values())
        for k, n in list(self.ignored.items()):    # the MAVLink thread adds kinds meanwhile
            values[f"ignored[{k}]"] = n
        values["stalls"] = self.clock.stalls
        level, message = DiagnosticStatus.OK, "ground station connected" if self.presence.connected else "no ground station"
        if self.tel.vehicle is None:
            level, message = DiagnosticStatus.WARN, f"{message}; no state/vehicle"
        elif self.homes.source == SOURCE_PARAM:
            message += "; home from parameters (no fmu/out/home_position yet)"
        if inv or missions.errors:
            level = max(level, DiagnosticStatus.WARN)
            message += f"; {inv + sum(missions.errors.values())} invalid MAVLink inputs dropped"
        return Health(level, message, values)


def main(argv=None) -> int:
    return run(GcsService, argv)
