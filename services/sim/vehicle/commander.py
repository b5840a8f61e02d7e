"""Arming, flight modes, failsafes and the auto-mode behaviours, after PX4's commander + navigator.

The Commander turns requests (arm, set mode, takeoff, offboard setpoints, ...) into one Setpoint
per physics step, with PX4's rules where the stack depends on them:
- OFFBOARD is accepted only after setpoints have streamed faster than COM_OF_MIN_HZ for
  COM_OF_WARM_T; when they stop for COM_OF_LOSS_T the vehicle fails over to COM_OBL_ACT (default
  RTL, as PX4 SITL without RC; or HOLD, then LAND after COM_OBL_HOLD_T; or LAND). When setpoints
  come back during that failsafe the vehicle returns to OFFBOARD (SIM_OF_RESUME, as PX4: its
  failsafe clears with the condition). A user mode change takes over from the failsafe.
- Arming is refused without a position, in the air, in OFFBOARD without a stream, or after
  flight termination; force (param2 = 21196) skips the checks except termination.
- The land detector declares ON_GROUND after LNDMC_TRIG_TIME resting on the ground, and the
  vehicle auto-disarms COM_DISARM_LAND after landing (COM_DISARM_PRFLT if it never took off).
  Disarmed, it switches to the last mode asked for that it can be armed in, as PX4's user mode
  intention does: after a LAND or RTL it reports OFFBOARD (or HOLD) again.
- TAKEOFF climbs to the target then switches to HOLD; RTL climbs to RTL_RETURN_ALT, returns and
  lands; LAND descends at PX4's landing speeds.
Results are MAVLink MAV_RESULT values, as PX4's commander acks vehicle commands.
Everything is ENU; home is the local origin at ground level (z = 0). Over sloped terrain the
ground under the vehicle is `state.ground_z_m`: landing slows down by height above it, and a
take-off climbs MIS_TAKEOFF_ALT above it (PX4 sets home where it arms; here home stays the origin).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from aeroperception.services.runtime.params import ParamSet

from .control import Setpoint
from .dynamics import RigidBodyState

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
DENIED = mavlink.MAV_RESULT_DENIED
TEMPORARILY_REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED

FLYABLE_MODES = ("OFFBOARD", "POSCTL", "HOLD", "LAND", "RTL", "TAKEOFF")
PREVENTS_ARMING = ("LAND", "RTL")   # PX4 cannot be armed in these: not where it goes back to on disarm
OFFBOARD_LOSS_MODES = {0: "LAND", 1: "HOLD", 2: "RTL"}   # COM_OBL_ACT
FS_OFFBOARD_LOST = "offboard setpoints lost"
FS_NO_POSITION = "Navigation error: No valid position estimate"   # PX4's text (modeCheck.cpp)
FS_BATTERY_CRITICAL = "battery critical"
FS_BATTERY_EMERGENCY = "battery emergency"
FS_TERMINATION = "flight termination"
_TAKEOFF_DONE_M = 0.2
_TAKEOFF_MIN_AGL_M = 1.0   # an explicit take-off target is at least min(this, itself) above the terrain here


@dataclass(frozen=True)
class Ack:
    """A command's MAV_RESULT and, when refused, why (what PX4 would say in a STATUSTEXT)."""

    result: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.result == ACCEPTED


class Commander:
    """Vehicle mode logic. Reads the vehicle state it is given (the estimator's view), never
    writes it. Call `update(now_s)` once per physics step; it returns None when the motors must
    be off (disarmed) and a Setpoint otherwise."""

    def __init__(self, params: ParamSet, state: RigidBodyState, battery_remaining=lambda: 1.0,
                 position_valid=None):
        self.p = params
        # the estimator's verdict (estimator.py); default: the SIM_POS_VALID switch alone
        self.position_valid = position_valid or (lambda: bool(self.p.SIM_POS_VALID))
        self.state = state
        self._battery_remaining = battery_remaining
        self.armed = False
        self.mode = "HOLD"
        self._mode_after_disarm = "HOLD"   # the last mode asked for that arming allows
        self.failsafe = False
        self.failsafe_reason = ""
        self.terminated = False
        self.landed = True
        self.has_flown = False
        self.last_reason = ""          # why the last request was refused, or the last failsafe
        self.counters = {"mode_changes": 0, "failsafes": 0, "auto_disarms": 0, "offboard_setpoints": 0,
                         "offboard_resumed": 0}
        self._armed_at_s = 0.0
        self._landed_at_s = 0.0
        self._resting_since_s: float | None = -math.inf  # on the ground since boot
        self._mode_since_s = 0.0
        self._bat_action_level = 0     # 0 none, 1 RTL done, 2 LAND done
        # offboard stream
        self._of_setpoint: Setpoint | None = None
        self._of_last_s = -math.inf
        self._of_stream_start_s = -math.inf
        # behaviour targets (ENU)
        self._hold_pos = np.zeros(3)
        self._hold_yaw = state.yaw_rad
        self._hold_sp: Setpoint | None = None     # HOLD's setpoint, built for the _hold_pos object _hold_sp_of (_hold)
        self._hold_sp_of: np.ndarray | None = None
        self._takeoff_alt_m = 0.0
        self._rtl_phase = "LAND"
        self._rtl_alt_m = 0.0
        self._enter_mode("HOLD", 0.0)

    # ------------------------------------------------------------------ derived state

    @property
    def landed_state(self) -> int:
        if self.landed:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.mode == "TAKEOFF":
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.mode == "LAND" or (self.mode == "RTL" and self._rtl_phase == "LAND"):
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def offboard_available(self, now_s: float) -> bool:
        """PX4's offboard signal: a stream faster than COM_OF_MIN_HZ for COM_OF_WARM_T."""
        alive = now_s - self._of_last_s <= 1.0 / self.p.COM_OF_MIN_HZ
        return alive and now_s - self._of_stream_start_s >= self.p.COM_OF_WARM_T

    def arming_problem(self, now_s: float) -> str:
        """Why arming would be refused now ('' if it would not): PX4's pre-arm checks."""
        if not self.position_valid():
            return FS_NO_POSITION
        if not self.landed:
            return "vehicle is not landed"
        if self._battery_remaining() < self.p.BAT_EMERGEN_THR:
            return "battery level emergency"
        if self.mode == "OFFBOARD" and not self.offboard_available(now_s):
            return "no offboard setpoint stream"
        return ""

    # ------------------------------------------------------------------ requests

    def on_offboard_setpoint(self, now_s: float, setpoint: Setpoint) -> None:
        if now_s - self._of_last_s > 1.0 / self.p.COM_OF_MIN_HZ:
            self._of_stream_start_s = now_s
        self._of_last_s = now_s
        self._of_setpoint = setpoint
        self.counters["offboard_setpoints"] += 1

    def arm(self, now_s: float, force: bool = False) -> Ack:
        if self.armed:
            return Ack(ACCEPTED)
        if self.terminated:
            return self._refuse(DENIED, "flight termination active: reboot to arm")
        problem = "" if force else self.arming_problem(now_s)
        if problem:
            return self._refuse(DENIED, f"arming denied: {problem}")
        self.armed = True
        self.has_flown = False
        self._armed_at_s = now_s
        self._hold_pos = self.state.position_enu_m.copy()  # hold / take off / land where we stand
        return Ack(ACCEPTED)

    def disarm(self, now_s: float, force: bool = False) -> Ack:
        if not self.armed:
            return Ack(ACCEPTED)
        if not force and not self.landed:
            return self._refuse(DENIED, "disarm denied: not landed (force to cut motors)")
        self._disarm(now_s)
        return Ack(ACCEPTED)

    def _disarm(self, now_s: float) -> None:
        self.armed = False
        if not self.terminated and self.mode != self._mode_after_disarm:
            self._enter_mode(self._mode_after_disarm, now_s)

    def set_mode(self, now_s: float, mode: str) -> Ack:
        """A user mode request (DO_SET_MODE / SET_MODE). Takes over from a failsafe."""
        if self.terminated:
            return self._refuse(DENIED, "flight termination active")
        if mode not in FLYABLE_MODES:
            return self._refuse(TEMPORARILY_REJECTED, f"mode {mode} not available in the simulator")
        if mode != "LAND" and not self.position_valid():   # PX4 can still descend without one
            return self._refuse(TEMPORARILY_REJECTED, f"{mode} not possible: {FS_NO_POSITION}")
        if mode == "OFFBOARD" and not self.offboard_available(now_s):
            return self._refuse(TEMPORARILY_REJECTED, f"offboard denied: no setpoint stream "
                                                      f"(> {self.p.COM_OF_MIN_HZ:g} Hz for {self.p.COM_OF_WARM_T:g} s)")
        self._clear_failsafe()
        if mode not in PREVENTS_ARMING:
            self._mode_after_disarm = mode
        if mode != self.mode:
            self._enter_mode(mode, now_s)
        return Ack(ACCEPTED)

    def takeoff(self, now_s: float, altitude_m: float = math.nan, yaw_rad: float = math.nan) -> Ack:
        """NAV_TAKEOFF: altitude above home (NaN: MIS_TAKEOFF_ALT). Like PX4, this only switches
        to TAKEOFF; a disarmed vehicle climbs once armed."""
        ack = self.set_mode(now_s, "TAKEOFF")
        if ack.ok:
            if math.isfinite(altitude_m):
                # Above home, as PX4; but never into (or just over) terrain higher than home.
                self._takeoff_alt_m = max(altitude_m, self.state.ground_z_m + min(altitude_m, _TAKEOFF_MIN_AGL_M))
            if math.isfinite(yaw_rad):
                self._hold_yaw = yaw_rad
        return ack

    def terminate(self, now_s: float) -> Ack:
        """DO_FLIGHTTERMINATION: motors off now, latched until reboot."""
        self.armed = False
        self.terminated = True
        self._set_failsafe(FS_TERMINATION)
        self._enter_mode("TERMINATION", now_s)
        return Ack(ACCEPTED)

    # ------------------------------------------------------------------ per-step logic

    def update(self, now_s: float) -> Setpoint | None:
        self._update_land_detector(now_s)
        if self.armed:
            self._check_failsafes(now_s)
            self._check_auto_disarm(now_s)
        if not self.armed:
            return None
        return self._behaviour(now_s)

    def _update_land_detector(self, now_s: float) -> None:
        s = self.state
        if not s.resting:
            self._resting_since_s = None
        elif self._resting_since_s is None:
            self._resting_since_s = now_s
        if self.armed and not s.on_ground:
            self.has_flown = True
        was_landed = self.landed
        if not s.on_ground:
            self.landed = False
        elif not self.landed:  # hysteresis: once landed, only leaving the ground clears it
            resting_long = (self._resting_since_s is not None
                            and now_s - self._resting_since_s >= self.p.LNDMC_TRIG_TIME)
            self.landed = resting_long or (not self.armed and s.resting)
        if self.landed and not was_landed:
            self._landed_at_s = now_s
            if self.failsafe and not self.terminated:
                self._clear_failsafe()

    def _check_failsafes(self, now_s: float) -> None:
        p = self.p
        in_air = not self.landed
        if self.mode == "OFFBOARD" and now_s - self._of_last_s > p.COM_OF_LOSS_T:
            self._set_failsafe(FS_OFFBOARD_LOST)
            self._enter_mode(OFFBOARD_LOSS_MODES[p.COM_OBL_ACT], now_s)
        elif (self.failsafe_reason == FS_OFFBOARD_LOST and p.SIM_OF_RESUME and self.mode != "OFFBOARD"
              and now_s - self._of_last_s <= 1.0 / p.COM_OF_MIN_HZ):
            self._clear_failsafe()
            self.counters["offboard_resumed"] += 1
            self._enter_mode("OFFBOARD", now_s)
        elif (self.failsafe_reason == FS_OFFBOARD_LOST and self.mode == "HOLD"
              and p.COM_OBL_HOLD_T >= 0 and now_s - self._mode_since_s >= p.COM_OBL_HOLD_T):
            self._enter_mode("LAND", now_s)
        if in_air and self.mode != "LAND" and not self.position_valid():
            self._set_failsafe(FS_NO_POSITION)
            self._enter_mode("LAND", now_s)
        if p.COM_LOW_BAT_ACT == 3 and in_air:
            remaining = self._battery_remaining()
            if remaining < p.BAT_EMERGEN_THR and self._bat_action_level < 2:
                self._bat_action_level = 2
                self._set_failsafe(FS_BATTERY_EMERGENCY)
                self._enter_mode("LAND", now_s)
            elif remaining < p.BAT_CRIT_THR and self._bat_action_level < 1:
                self._bat_action_level = 1
                self._set_failsafe(FS_BATTERY_CRITICAL)
                self._enter_mode("RTL", now_s)

    def _check_auto_disarm(self, now_s: float) -> None:
        if not self.landed:
            return
        limit = self.p.COM_DISARM_LAND if self.has_flown else self.p.COM_DISARM_PRFLT
        if limit >= 0 and now_s - max(self._landed_at_s, self._armed_at_s) >= limit:
            self._disarm(now_s)
            self.counters["auto_disarms"] += 1

    # ------------------------------------------------------------------ behaviours

    def _enter_mode(self, mode: str, now_s: float) -> None:
        s, p = self.state, self.p
        if mode != self.mode:
            self.counters["mode_changes"] += 1
        self.mode = mode
        self._mode_since_s = now_s
        self._hold_yaw = s.yaw_rad
        pos, vel = s.position_enu_m, s.velocity_enu_mps
        # Brake like PX4's HOLD: stop where a constant MPC_ACC_HOR deceleration gets us.
        self._hold_pos = pos + np.array([vel[0], vel[1], 0.0]) * math.hypot(vel[0], vel[1]) / (2.0 * p.MPC_ACC_HOR)
        if mode == "TAKEOFF":
            self._takeoff_alt_m = s.ground_z_m + p.MIS_TAKEOFF_ALT
        elif mode == "RTL":
            self._rtl_alt_m = max(pos[2], p.RTL_RETURN_ALT)
            self._rtl_phase = "LAND" if self.landed else "CLIMB"

    def _land_setpoint(self, xy) -> Setpoint:
        p = self.p
        alt = self.state.height_agl_m
        # PX4: fast above MPC_LAND_ALT1, MPC_LAND_SPEED below MPC_LAND_ALT2, linear between.
        span = max(p.MPC_LAND_ALT1 - p.MPC_LAND_ALT2, 1e-6)
        frac = min(max((alt - p.MPC_LAND_ALT2) / span, 0.0), 1.0)
        speed = p.MPC_LAND_SPEED + frac * max(p.MPC_Z_VEL_MAX_DN - p.MPC_LAND_SPEED, 0.0)
        return Setpoint(position_enu_m=np.array([xy[0], xy[1], math.nan]),
                        velocity_enu_mps=np.array([math.nan, math.nan, -speed]), yaw_rad=self._hold_yaw)

    def _behaviour(self, now_s: float) -> Setpoint:
        s, p = self.state, self.p
        mode = self.mode
        if mode == "OFFBOARD" and self._of_setpoint is not None:
            return self._of_setpoint
        if mode == "TAKEOFF":
            target = np.array([self._hold_pos[0], self._hold_pos[1], self._takeoff_alt_m])
            if abs(s.position_enu_m[2] - self._takeoff_alt_m) < _TAKEOFF_DONE_M and not self.landed:
                self._enter_mode("HOLD", now_s)
                self._mode_after_disarm = "HOLD"   # PX4's takeoff hands over to Hold as the user's mode
                self._hold_pos = target
            return Setpoint(position_enu_m=target, yaw_rad=self._hold_yaw, max_up_mps=p.MPC_TKO_SPEED)
        if mode == "LAND":
            return self._land_setpoint(self._hold_pos)
        if mode == "RTL":
            return self._rtl(now_s)
        return self._hold()  # HOLD, POSCTL (sticks centred)

    def _hold(self) -> Setpoint:
        """Hold _hold_pos at _hold_yaw. Asked every physics step while holding: built again only when
        either changes (both are replaced, never changed in place), not once a step."""
        sp = self._hold_sp
        if sp is None or self._hold_sp_of is not self._hold_pos or sp.yaw_rad != self._hold_yaw:
            sp = self._hold_sp = Setpoint.hold(self._hold_pos, self._hold_yaw)
            self._hold_sp_of = self._hold_pos
        return sp

    def _rtl(self, now_s: float) -> Setpoint:
        s, p = self.state, self.p
        if self._rtl_phase == "CLIMB":
            if s.position_enu_m[2] >= self._rtl_alt_m - 0.5:
                self._rtl_phase = "RETURN"
            return Setpoint.hold([self._hold_pos[0], self._hold_pos[1], self._rtl_alt_m], self._hold_yaw)
        if self._rtl_phase == "RETURN":
            dist = math.hypot(s.position_enu_m[0], s.position_enu_m[1])
            if dist < p.NAV_ACC_RAD and math.hypot(*s.velocity_enu_mps[:2]) < 0.5:
                self._rtl_phase = "LAND"
            sp = Setpoint.hold([0.0, 0.0, self._rtl_alt_m], self._hold_yaw)
            sp.max_xy_mps = p.MPC_XY_CRUISE
            return sp
        return self._land_setpoint((0.0, 0.0))

    # ------------------------------------------------------------------ helpers

    def _refuse(self, result: int, reason: str) -> Ack:
        self.last_reason = reason
        return Ack(result, reason)

    def _set_failsafe(self, reason: str) -> None:
        if not self.failsafe or reason != self.failsafe_reason:
            self.counters["failsafes"] += 1
        self.failsafe = True
        self.failsafe_reason = reason
        self.last_reason = reason

    def _clear_failsafe(self) -> None:
        self.failsafe = False
        self.failsafe_reason = ""
