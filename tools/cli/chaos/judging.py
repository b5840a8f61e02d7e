"""Judging a fault row: did the vehicle stay safe by the ground truth, whatever the stack did?

Safe = no ground impact at speed, inside the geofence, every setpoint the FC received finite and
inside the envelope, and at the end either holding at rest, landed and disarmed, or flying on."""
from __future__ import annotations

from dataclasses import dataclass, field

from aeroperception.schemas import VehicleState
from aeroperception.services.lib.geofence import Geofence
from aeroperception.tools.harness import speed

IMPACT_SPEED_MPS = 1.5               # touching the ground faster than this is an impact
AT_REST_MPS = 0.3                    # a held vehicle is still below this (the built-in sim holds within ~0.1 m)
FLYING_ON_MPS = 0.5                  # ... and flies on above this
# PX4 SIH holds (our OFFBOARD hold as its own HOLD) on EKF2's GNSS-aided estimate, which wanders with
# SIH's GPS noise: 30 s of OFFBOARD hold measured truth speed p50 0.20, p95 0.45, max 0.52 m/s over a
# 1.8 m span. Its holds are judged still below this; flying on (the mission's 2 m/s) is above it.
HOLD_SETTLING_MPS = 1.0


def still_mps(fc: str) -> float:
    """Below this speed (truth) a held vehicle on flight controller `fc` ("sim"/"px4") is still."""
    return HOLD_SETTLING_MPS if fc == "px4" else AT_REST_MPS


def flying_on_mps(fc: str) -> float:
    """Above this speed (truth) a vehicle that should hold on `fc` flies on."""
    return HOLD_SETTLING_MPS if fc == "px4" else FLYING_ON_MPS


@dataclass
class RowResult:
    row: str
    injected: str
    expected: str
    observed: str = ""
    detect_s: float | None = None
    safe: bool | None = None
    safe_why: str = ""
    passed: bool = False
    duration_s: float = 0.0
    details: dict = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        return "PASS" if self.passed else "FAIL"


def judge_safety(track: list[tuple[float, VehicleState]], unsafe_setpoints: list[str], fence: Geofence,
                 mission_state: str, rest_mps: float = AT_REST_MPS) -> tuple[bool, str]:
    """Vehicle safe by the truth: no impact at speed, in the fence, no unsafe setpoint at the FC,
    and at the end holding (at rest in the air), landed and disarmed, or flying the mission."""
    if not track:
        return False, "no ground truth (sim gone?)"
    problems = []
    for _, m in track:
        if m.position_m.z < 0.1 and speed(m) > IMPACT_SPEED_MPS:
            problems.append(f"ground impact at {speed(m):.1f} m/s")
            break
    worst = min(fence.distance_to_boundary_m(m.position_m.x, m.position_m.y, m.position_m.z) for _, m in track)
    if worst < 0:
        problems.append(f"left the geofence by {-worst:.1f} m")
    if unsafe_setpoints:
        problems.append(f"{len(unsafe_setpoints)} unsafe setpoints at the FC ({unsafe_setpoints[0]})")
    end = track[-1][1]
    v_end = speed(end)
    if end.position_m.z < 0.2 and not end.armed:
        ending = "landed+disarmed"
    elif end.armed and end.position_m.z >= 0.2 and v_end < rest_mps:
        ending = f"holding at {end.position_m.z:.1f} m"
    elif end.armed and end.position_m.z >= 0.2 and end.flight_mode == "HOLD" and v_end < HOLD_SETTLING_MPS:
        ending = f"FC holding at {end.position_m.z:.1f} m ({v_end:.1f} m/s)"
    elif mission_state in ("EXECUTING", "LAND", "TAKEOFF") or end.flight_mode in ("LAND", "RTL"):
        ending = f"flying ({mission_state}, FC {end.flight_mode})"
    else:
        ending = ""
        problems.append(f"ends moving at {v_end:.1f} m/s in {end.flight_mode} with mission {mission_state}")
    return (not problems), "; ".join(problems) or ending
