"""mission/uav_status: one UAVStatus (with its UAVMode) for a dashboard, from the mission FSM,
the vehicle's state and what the other services say. Free of Zenoh; main.py publishes it at
status_rate_hz.

UAVMode.state, first rule that holds:
  no vehicle state -> IDLE; safety level EMERGENCY -> EMERGENCY; FSM TAKEOFF -> TAKING_OFF;
  FSM LAND -> LANDING; on the ground (landed or disarmed): armed -> ARMED, else LANDED after a
  flight and IDLE before one; in the air: speed below the hover speed -> HOVERING, else FLYING.
  "Hovering" is the planner's own rule for when a part may be switched (lib/flight_state.py), with
  the planner's live `hover_speed_mps` (main.py asks the planner for it every few seconds).
UAVMode.control_mode, by the flight controller's mode: OFFBOARD (the planner flies) ->
  VELOCITY with the planner's velocity controller, TRAJECTORY while it flies a trajectory,
  OFFBOARD otherwise; MANUAL / STABILIZED / ACRO / ALTCTL / RATTITUDE -> MANUAL; any other mode
  of the flight controller's own (HOLD, POSCTL, RTL, LAND, TAKEOFF, MISSION) -> POSITION.
submode: "rth" while the flight controller returns home, else the FSM state in lower case.
can_arm / can_takeoff: connected, on the ground, FSM IDLE (and disarmed, to arm); can_land:
connected, in the air, not already landing.
px4_latency_s: how old the flight controller's state is when the mission receives it (its stamp,
the FC's sample time on this host's clock, to arrival), the median of the last LATENCY_SAMPLES;
None before any. There is no gcs_latency_s: nothing times the ground link (gcs answers the ground
station's TIMESYNC, the ground station times it); gcs/link's last_heartbeat_age_s says how
recently the ground was heard.
"""
from __future__ import annotations

import os
import statistics
from collections import deque

from aeroperception.schemas import SafetyStatus, TrajectoryStatus, UAVMode, UAVStatus, VehicleState
from aeroperception.services.lib.flight_state import HOVER_SPEED_PARAM, is_hovering, on_ground

from .fsm import State

HOVER_SPEED_MPS = HOVER_SPEED_PARAM.default   # until the planner says
LATENCY_SAMPLES = 20
MANUAL_MODES = ("MANUAL", "STABILIZED", "ACRO", "ALTCTL", "RATTITUDE")


def uav_mode(fsm: State, vehicle: VehicleState | None, safety: SafetyStatus | None,
             planner: TrajectoryStatus | None, flew: bool, hover_speed_mps: float = HOVER_SPEED_MPS) -> UAVMode:
    mode = UAVMode(submode=fsm.value.lower())
    if vehicle is None:
        return mode
    mode.armed = vehicle.armed
    grounded = on_ground(vehicle)
    if safety is not None and safety.safety_level == SafetyStatus.LEVEL_EMERGENCY:
        mode.state = UAVMode.STATE_EMERGENCY
    elif fsm == State.TAKEOFF:
        mode.state = UAVMode.STATE_TAKING_OFF
    elif fsm == State.LAND:
        mode.state = UAVMode.STATE_LANDING
    elif grounded:
        mode.state = UAVMode.STATE_ARMED if vehicle.armed else UAVMode.STATE_LANDED if flew else UAVMode.STATE_IDLE
    else:
        mode.state = UAVMode.STATE_HOVERING if is_hovering(vehicle, hover_speed_mps) else UAVMode.STATE_FLYING
    fc_mode = vehicle.flight_mode
    if fc_mode == "OFFBOARD":
        mode.control_mode = UAVMode.MODE_OFFBOARD
        if planner is not None and planner.active_controller == "velocity":
            mode.control_mode = UAVMode.MODE_VELOCITY
        elif planner is not None and planner.status == TrajectoryStatus.STATUS_EXECUTING \
                and not planner.trajectory_id.startswith("goal-"):
            mode.control_mode = UAVMode.MODE_TRAJECTORY
    elif fc_mode in MANUAL_MODES:
        mode.control_mode = UAVMode.MODE_MANUAL
    else:
        mode.control_mode = UAVMode.MODE_POSITION
    if fc_mode == "RTL":
        mode.submode = "rth"
    idle = fsm == State.IDLE and vehicle.connected and grounded
    mode.can_arm = idle and not vehicle.armed
    mode.can_takeoff = idle
    mode.can_land = vehicle.connected and not grounded and fsm != State.LAND
    return mode


def machine_load() -> tuple[float, float]:
    """(CPU %, memory %) of this machine: the 1-minute load average over the cores, and the memory
    not available (/proc/meminfo); 0 where the OS does not say."""
    try:
        cpu = 100.0 * os.getloadavg()[0] / (os.cpu_count() or 1)
    except OSError:
        cpu = 0.0
    try:
        with open("/proc/meminfo") as f:
            info = {line.split(":")[0]: float(line.split()[1]) for line in f if ":" in line}
        memory = 100.0 * (1.0 - info["MemAvailable"] / info["MemTotal"])
    except (OSError, KeyError, ValueError, IndexError, ZeroDivisionError):
        memory = 0.0
    return cpu, memory


class UavStatusBuilder:
    """Remembers whether the vehicle has flown (LANDED vs IDLE), the planner's hover speed and the
    flight controller's latency, and builds each UAVStatus."""

    def __init__(self, uav_id: str):
        self.uav_id = uav_id
        self.flew = False
        self.hover_speed_mps = HOVER_SPEED_MPS
        self.fc_ages_s: deque[float] = deque(maxlen=LATENCY_SAMPLES)

    def heard_vehicle(self, age_s: float) -> None:
        """A state/vehicle sample arrived `age_s` after its stamp."""
        self.fc_ages_s.append(max(0.0, age_s))

    def heard_planner_params(self, values: dict) -> None:
        """The planner's parameters (config/planner/@params): its hover speed is the one judged by."""
        v = values.get("hover_speed_mps")
        if isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0:
            self.hover_speed_mps = float(v)

    def build(self, fsm: State, vehicle: VehicleState | None, safety: SafetyStatus | None,
              planner: TrajectoryStatus | None, gcs_connected: bool, mission_id: str,
              progress_percent: float) -> UAVStatus:
        if vehicle is not None and not on_ground(vehicle):
            self.flew = True
        cpu, memory = machine_load()
        return UAVStatus(
            uav_id=self.uav_id, uav_name=self.uav_id, current_state=vehicle or VehicleState(),
            current_mode=uav_mode(fsm, vehicle, safety, planner, self.flew, self.hover_speed_mps),
            active_estimator=planner.active_estimator if planner else "",
            active_controller=planner.active_controller if planner else "",
            active_trajectory_generator=planner.active_trajectory_generator if planner else "",
            safety_status=safety or SafetyStatus(),
            battery_remaining=vehicle.battery_remaining if vehicle else None,
            cpu_percent=cpu, memory_percent=memory,
            px4_connected=bool(vehicle and vehicle.connected), gcs_connected=gcs_connected,
            px4_latency_s=statistics.median(self.fc_ages_s) if self.fc_ages_s else None,
            current_mission_id=mission_id, mission_progress_percent=progress_percent)


def mission_progress_pct(state: State, mission, wp_index: int) -> float:
    """How far through its waypoints the mission is (0 with none loaded, or IDLE)."""
    if mission is None or state == State.IDLE or not mission.waypoints:
        return 0.0
    return 100.0 * min(1.0, max(0, wp_index) / len(mission.waypoints))


class GcsLinkWatch:
    """gcs/link repeats at 1 Hz; only a change of a link once seen is an event (a stack flying
    without any ground station is not "link lost")."""

    def __init__(self) -> None:
        self.up: bool | None = None      # None: never heard

    def heard(self, connected: bool) -> bool | None:
        """The new state when this is a change of a link once seen, else None."""
        was, self.up = self.up, connected
        return connected if was is not None and was != connected else None
