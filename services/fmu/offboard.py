"""What fmu streams to the flight controller each tick: the planner's setpoint, a brake, or a hold.

Plain logic, no Zenoh or sockets: the shell feeds it setpoints, planner health, published state
stamps and the vehicle's position/velocity, and sends what `tick()` returns. It must never let
a non-finite, out-of-envelope or stale setpoint reach the flight controller (ARCHITECTURE §8).

Following the planner needs `resume_count` consecutive fresh, valid setpoints (hysteresis: a
load spike that delays one setpoint past `timeout_s` does not flap follow/hold every few ms).
A setpoint is fresh when its header stamp (the planner copies the stamp of the state/vehicle it
was computed from) is not older than the first state fmu published in this session
(`state_epoch_ns`: start-up, or the flight-controller link coming back) and not more than
`max_age_s` older than the newest state fmu published. So a restarted fmu never forwards motion
planned from the old fmu's state, and a planner resumed from SIGSTOP cannot replay its backlog.

Stopping is brake-then-hold: on losing the planner at speed, stream a zero-velocity setpoint
(the FC's velocity loop brakes as hard as its limits allow) until the vehicle is slower than
`brake_speed_mps` (or `brake_timeout_s` passed), then hold the position where it actually
stopped. Freezing the hold point at the instant of loss (what fmu did) overshoots by the
braking distance and flies back; predicting the stop point (v^2 / 2a) depends on the FC's
acceleration limits and gains, which differ between PX4, ArduPilot and the sim; measuring
where the vehicle stops does not.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aeroperception.schemas import TrajectorySetpoint, Vector3
from aeroperception.services.runtime.config import param, section

FOLLOW, BRAKE, HOLD = "follow", "brake", "hold"

# SET_POSITION_TARGET_LOCAL_NED (what PX4 offboard takes) carries position, velocity,
# acceleration, yaw and yaw rate, but no jerk: forwarding the rest would drop it unseen.
JERK_REFUSED = "jerk_valid: jerk feed-forward cannot be sent (SET_POSITION_TARGET_LOCAL_NED has no jerk field)"

# Hold reasons (diagnostics `hold_reason`)
WAIT_FRESH = "waiting for fresh planner setpoints"
PLANNER_SILENT = "planner silent"
LINK_REGAINED = "flight-controller link regained"


class StreamWarmth:
    """How long fmu's setpoint stream to the flight controller has run without a gap.

    PX4 accepts OFFBOARD only once it has received setpoints for a while (the sim: faster than
    COM_OF_MIN_HZ for COM_OF_WARM_T); a mode request right after fmu (re)started streaming
    (start-up, link regained, FC reboot) is refused TEMPORARILY_REJECTED. fmu owns the stream,
    so its set_mode waits until the stream is warm instead of every caller retrying.
    """

    def __init__(self, max_gap_s: float = 0.5):
        self.max_gap_s = max_gap_s
        self.since_s = math.nan
        self.last_s = -math.inf

    def sent(self, now_s: float) -> None:
        if now_s - self.last_s > self.max_gap_s:
            self.since_s = now_s  # a gap: PX4 restarts its count too
        self.last_s = now_s

    def age_s(self, now_s: float) -> float:
        """Seconds the stream has run without a gap (0 when it is not running)."""
        if now_s - self.last_s > self.max_gap_s:
            return 0.0
        return now_s - self.since_s


@dataclass(frozen=True)
class Envelope:
    """Limits of a setpoint fmu forwards (the vehicle's envelope, ENU about the local origin):
    contract.PARAMS of the same names."""

    max_velocity_mps: float = param("max_velocity_mps")
    max_acceleration_mps2: float = param("max_acceleration_mps2")
    max_distance_m: float = param("max_distance_m")     # horizontal distance of a position setpoint from the origin
    max_altitude_m: float = param("max_altitude_m")     # position setpoint z (up) limits
    min_altitude_m: float = param("min_altitude_m")
    max_yaw_rate_radps: float = param("max_yaw_rate_radps")

    def problem(self, sp: TrajectorySetpoint) -> str:
        """Why `sp` must not be forwarded ('' if it may). Only the parts marked valid are
        checked (unused fields may be anything, NaN included, per the schema)."""
        if sp.jerk_valid:
            return JERK_REFUSED
        if not (sp.position_valid or sp.velocity_valid):
            return "neither position nor velocity valid"
        if sp.position_valid:
            p = sp.position_m.to_array()
            if not np.all(np.isfinite(p)):
                return "non-finite position"
            if math.hypot(p[0], p[1]) > self.max_distance_m:
                return f"position {math.hypot(p[0], p[1]):.0f} m from the origin > max_distance_m {self.max_distance_m:g}"
            if not self.min_altitude_m <= p[2] <= self.max_altitude_m:
                return f"position z {p[2]:.1f} m outside [{self.min_altitude_m:g}, {self.max_altitude_m:g}] m"
        for valid, vec, what, unit, limit, name in (
                (sp.velocity_valid, sp.velocity_mps, "velocity", "m/s", self.max_velocity_mps, "max_velocity_mps"),
                (sp.acceleration_valid, sp.acceleration_mps2, "acceleration", "m/s^2", self.max_acceleration_mps2,
                 "max_acceleration_mps2")):
            v = vec.to_array()
            if valid and not np.all(np.isfinite(v)):
                return f"non-finite {what}"
            if valid and np.linalg.norm(v) > limit:
                return f"{what} {np.linalg.norm(v):.1f} {unit} > {name} {limit:g}"
        if sp.yaw_valid and not math.isfinite(sp.yaw_rad):
            return "non-finite yaw"
        if sp.yaw_rate_valid and not (math.isfinite(sp.yaw_rate_radps) and abs(sp.yaw_rate_radps) <= self.max_yaw_rate_radps):
            return f"yaw rate {sp.yaw_rate_radps} rad/s not finite or > {self.max_yaw_rate_radps:g}"
        return ""


def brake_setpoint(yaw_rad: float) -> TrajectorySetpoint:
    """Stop: zero velocity on every axis, position uncontrolled, yaw kept."""
    return TrajectorySetpoint(velocity_valid=True, yaw_valid=True, velocity_mps=Vector3(), yaw_rad=yaw_rad)


hold_setpoint = TrajectorySetpoint.hold   # one home: the schema's hold constructor


@dataclass(frozen=True)
class ArbiterConfig:
    """What the arbiter decides by (contract.PARAMS; runtime/config.py builds it)."""

    envelope: Envelope = section(Envelope)
    timeout_s: float = param("setpoint_timeout_s")
    resume_count: int = param("resume_setpoints")
    max_age_s: float = param("setpoint_max_age_s")
    brake_speed_mps: float = param("brake_speed_mps")
    brake_timeout_s: float = param("brake_timeout_s")


class OffboardArbiter:
    """Decides follow / brake / hold. Times are monotonic seconds; stamps are the node clock's ns.
    `cfg` may be replaced at any time (a live parameter change)."""

    def __init__(self, cfg: ArbiterConfig):
        self.cfg = cfg
        self.phase = HOLD                       # FOLLOW / BRAKE / HOLD
        self.reason = WAIT_FRESH                # why not following ('' while following)
        self.planner_ok, self.planner_why = True, ""
        self.setpoint: TrajectorySetpoint | None = None   # the last forwarded planner setpoint
        self.last_rx_s = -math.inf              # last fresh valid setpoint
        self.streak = 0                         # consecutive fresh valid setpoints while not following
        self.state_epoch_ns: int | None = None  # first state published this session
        self.newest_state_ns = 0
        self.brake_since_s = -math.inf
        self.hold_at: tuple[np.ndarray, float] | None = None
        self.counters = {"setpoints_rejected": 0, "setpoints_stale": 0, "setpoints_ignored": 0,
                         "holds_entered": 0, "follow_resumed": 0}
        self.last_rejection = ""

    # ------------------------------------------------------------ inputs

    def on_state(self, stamp_ns: int, new_session: bool = False) -> None:
        """fmu published state/vehicle with this stamp. new_session: the first after start-up or
        after the FC link came back; setpoints must be newer than it, and we hold meanwhile."""
        if new_session or self.state_epoch_ns is None:
            self.state_epoch_ns = stamp_ns
            if new_session and self.phase == FOLLOW:
                self.stop(LINK_REGAINED)
        self.newest_state_ns = max(self.newest_state_ns, stamp_ns)

    def on_planner_health(self, ok: bool, why: str) -> bool:
        """Liveliness / ERROR fast path. Returns True if it changed."""
        if ok == self.planner_ok:
            return False
        self.planner_ok, self.planner_why = ok, "" if ok else why
        if not ok:
            self.stop(why)
        elif self.phase != FOLLOW:
            self.reason = WAIT_FRESH
        return True

    def stale_reason(self, sp: TrajectorySetpoint) -> str:
        stamp = sp.header.stamp_ns
        if self.state_epoch_ns is None:
            return "no state published yet"
        if stamp < self.state_epoch_ns:
            return "computed before this fmu session's first state"
        if stamp < self.newest_state_ns - self.cfg.max_age_s * 1e9:
            return f"{(self.newest_state_ns - stamp) / 1e9:.2f} s older than the newest state"
        return ""

    def on_setpoint(self, sp: TrajectorySetpoint, now_s: float) -> TrajectorySetpoint | None:
        """A planner setpoint arrived. Returns it if it is to be forwarded now, else None."""
        if not self.planner_ok:
            self.counters["setpoints_ignored"] += 1
            return None
        problem = self.cfg.envelope.problem(sp)
        if problem:
            self.counters["setpoints_rejected"] += 1
            self.last_rejection = problem
            self.stop(f"setpoint rejected: {problem}")
            self.streak = 0
            return None
        stale = self.stale_reason(sp)
        if stale:
            self.counters["setpoints_stale"] += 1
            self.last_rejection = f"stale setpoint: {stale}"
            if self.phase != FOLLOW:
                self.streak = 0
                self.reason = f"stale setpoints ({stale})"
            return None
        if self.phase == FOLLOW:
            self.setpoint, self.last_rx_s = sp, now_s
            return sp
        self.streak = self.streak + 1 if now_s - self.last_rx_s <= self.cfg.timeout_s else 1
        self.last_rx_s = now_s
        if self.streak < self.cfg.resume_count:
            return None
        self.phase, self.reason, self.hold_at, self.setpoint = FOLLOW, "", None, sp
        self.counters["follow_resumed"] += 1
        return sp

    def stop(self, reason: str) -> None:
        """Stop following: brake, then hold where the vehicle stops."""
        if self.phase == FOLLOW:
            self.phase, self.brake_since_s, self.hold_at = BRAKE, -math.inf, None
            self.counters["holds_entered"] += 1
        self.reason = reason
        self.streak = 0

    # ------------------------------------------------------------ output

    def tick(self, now_s: float, position_m: np.ndarray, velocity_mps: np.ndarray,
             yaw_rad: float) -> tuple[str, TrajectorySetpoint]:
        """(phase, setpoint to stream now). In FOLLOW the setpoint is the planner's last one."""
        if self.phase == FOLLOW and now_s - self.last_rx_s > self.cfg.timeout_s:
            self.stop(PLANNER_SILENT)
        if self.phase == FOLLOW:
            return FOLLOW, self.setpoint
        if self.phase == BRAKE:
            if self.brake_since_s == -math.inf:
                self.brake_since_s, self._brake_yaw = now_s, yaw_rad
            slow = float(np.linalg.norm(velocity_mps)) < self.cfg.brake_speed_mps
            if not slow and now_s - self.brake_since_s < self.cfg.brake_timeout_s:
                return BRAKE, brake_setpoint(self._brake_yaw)
            self.phase, self.hold_at = HOLD, (np.array(position_m, dtype=float), self._brake_yaw)
        if self.hold_at is None:  # holding from the start (no motion followed yet): brake first
            self.phase, self.brake_since_s = BRAKE, -math.inf
            return self.tick(now_s, position_m, velocity_mps, yaw_rad)
        return HOLD, hold_setpoint(*self.hold_at)

    def label(self) -> str:
        """diagnostics `planner`: streaming, or holding (with the planner's own failure)."""
        if self.phase == FOLLOW:
            return "streaming"
        return f"holding ({self.planner_why})" if self.planner_why else "holding"
