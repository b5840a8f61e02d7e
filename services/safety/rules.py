"""Safety's recommended action as an explicit rule table (like mission's TRANSITIONS), free of Zenoh.

RULES is ordered most severe first. Each row: a name, a condition on `Facts`, the (level, action)
while airborne, the (level, action) on the ground, and a message. The first matching row decides
`safety_level` and `recommended_action`; every matching row adds its message (to the errors when
its level is CAUTION or worse, else to the warnings; " -> HOLD" etc. when the row asks for motion),
so nothing is hidden behind the winner. Messages are stable while their condition holds (the
numbers are in SafetyStatus's fields), so a ground station can forward each one once.

On the ground no row recommends motion (HOLD/RTH/LAND become WARN): the problem is still reported
(a reason not to take off). A lost flight-controller link ranks above every motion row: nothing
the stack commands can reach the vehicle, its own failsafe flies it (action NONE, level EMERGENCY).
Nothing here commands the vehicle: mission acts on the recommendation; the flight controller's
failsafes stay the last word (ARCHITECTURE §8).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Callable

from aeroperception.schemas import SafetyStatus
from aeroperception.services.lib.safety_names import ACTION_NAMES

L, A = SafetyStatus, SafetyStatus   # LEVEL_* and ACTION_* constants


class Battery(IntEnum):
    """Battery class, worst of our thresholds and the FC's own warning."""

    UNKNOWN = -1
    OK = 0
    LOW = 1
    CRITICAL = 2
    EMERGENCY = 3


class GeofenceAction(IntEnum):
    """PX4 GF_ACTION values (4, terminate, is not offered)."""

    NONE = 0
    WARN = 1
    HOLD = 2
    RETURN = 3
    LAND = 5


@dataclass(frozen=True)
class Facts:
    """Everything the rules look at, already aggregated and judged fresh or stale."""

    airborne: bool = False                   # armed and not on the ground (last known state)
    fc_connected: bool = True                # state/vehicle fresh and `connected`
    fc_ever_connected: bool = True
    fmu_down: str = ""                       # why fmu is unusable (not alive / hung / ERROR), "" if fine
    services_down: tuple[str, ...] = ()      # other required services: "planner not alive", ...
    battery: Battery = Battery.OK
    battery_remaining: float | None = None
    geofence_status: int = SafetyStatus.GEOFENCE_OK
    distance_to_geofence_m: float | None = None
    geofence_action: GeofenceAction = GeofenceAction.HOLD
    gcs_lost: bool = False                   # a ground station was heard and is not any more
    perception_problem: str = ""             # "" when healthy or never heard of (optional input)
    fc_failsafe: str = ""                    # the FC reports a failsafe of its own: its mode
    estop: str = ""                          # emergency stop requested: what happened, "" if none


@dataclass(frozen=True)
class Rule:
    name: str
    when: Callable[[Facts], bool]
    airborne: tuple[int, int]                # (safety_level, recommended_action) in the air
    ground: tuple[int, int]                  # ... on the ground
    message: Callable[[Facts], str]


GROUND_WARN = (L.LEVEL_WARNING, A.ACTION_WARN)
VIOLATION = SafetyStatus.GEOFENCE_VIOLATION


def _geofence_breach(action: GeofenceAction) -> Callable[[Facts], bool]:
    return lambda f: f.geofence_status == VIOLATION and f.geofence_action == action


RULES: list[Rule] = [
    Rule("emergency_stop", lambda f: bool(f.estop),
         (L.LEVEL_EMERGENCY, A.ACTION_EMERGENCY_STOP), (L.LEVEL_EMERGENCY, A.ACTION_EMERGENCY_STOP),
         lambda f: f.estop),
    Rule("fc_link_lost", lambda f: not f.fc_connected,
         (L.LEVEL_EMERGENCY, A.ACTION_NONE), GROUND_WARN,
         lambda f: ("no flight controller link yet" if not f.fc_ever_connected else
                   "flight controller link lost" + (": its own failsafe flies the vehicle" if f.airborne else ""))),
    Rule("fmu_down", lambda f: bool(f.fmu_down),
         (L.LEVEL_EMERGENCY, A.ACTION_NONE), GROUND_WARN,
         lambda f: f.fmu_down + (": the flight controller's offboard-loss failsafe takes over" if f.airborne else "")),
    Rule("battery_emergency", lambda f: f.battery == Battery.EMERGENCY,
         (L.LEVEL_EMERGENCY, A.ACTION_LAND), GROUND_WARN,
         lambda f: "battery emergency"),
    Rule("geofence_land", _geofence_breach(GeofenceAction.LAND),
         (L.LEVEL_EMERGENCY, A.ACTION_LAND), GROUND_WARN,
         lambda f: "outside the geofence (geofence_action 5: land)"),
    Rule("battery_critical", lambda f: f.battery == Battery.CRITICAL,
         (L.LEVEL_CAUTION, A.ACTION_RTH), GROUND_WARN,
         lambda f: "battery critical"),
    Rule("geofence_return", _geofence_breach(GeofenceAction.RETURN),
         (L.LEVEL_CAUTION, A.ACTION_RTH), GROUND_WARN,
         lambda f: "outside the geofence (geofence_action 3: return)"),
    Rule("service_down", lambda f: bool(f.services_down),
         (L.LEVEL_CAUTION, A.ACTION_HOLD), GROUND_WARN,
         lambda f: ", ".join(f.services_down)),
    Rule("geofence_hold", _geofence_breach(GeofenceAction.HOLD),
         (L.LEVEL_CAUTION, A.ACTION_HOLD), GROUND_WARN,
         lambda f: "outside the geofence (geofence_action 2: hold)"),
    Rule("geofence_warn", _geofence_breach(GeofenceAction.WARN),
         GROUND_WARN, GROUND_WARN,
         lambda f: "outside the geofence (geofence_action 1: warn only)"),
    Rule("battery_low", lambda f: f.battery == Battery.LOW,
         GROUND_WARN, GROUND_WARN,
         lambda f: "battery low"),
    Rule("geofence_near", lambda f: f.geofence_status == SafetyStatus.GEOFENCE_WARNING,
         GROUND_WARN, GROUND_WARN,
         lambda f: "near the geofence boundary"),
    Rule("gcs_lost", lambda f: f.gcs_lost,
         GROUND_WARN, GROUND_WARN,
         lambda f: "ground station link lost"),
    Rule("perception_unhealthy", lambda f: bool(f.perception_problem),
         GROUND_WARN, GROUND_WARN,
         lambda f: f.perception_problem),
    Rule("fc_failsafe", lambda f: bool(f.fc_failsafe),
         GROUND_WARN, GROUND_WARN,
         lambda f: f"flight controller failsafe active ({f.fc_failsafe})"),
    Rule("battery_unknown", lambda f: f.battery == Battery.UNKNOWN and f.fc_connected,
         GROUND_WARN, GROUND_WARN,
         lambda f: "battery state unknown"),
]
RULE_NAMES = [r.name for r in RULES]


MOTION = (A.ACTION_HOLD, A.ACTION_RTH, A.ACTION_LAND)


@dataclass(frozen=True)
class Verdict:
    level: int = SafetyStatus.LEVEL_NOMINAL
    action: int = SafetyStatus.ACTION_NONE
    rules: tuple[str, ...] = ()              # every matching row, table order
    warnings: tuple[str, ...] = ()
    errors: tuple[str, ...] = ()

    @property
    def deciding_rule(self) -> str:
        return self.rules[0] if self.rules else ""


def evaluate(facts: Facts, rules: list[Rule] = RULES) -> Verdict:
    """The first matching row decides level and action; every matching row reports."""
    level, action = SafetyStatus.LEVEL_NOMINAL, SafetyStatus.ACTION_NONE
    names: list[str] = []
    warnings: list[str] = []
    errors: list[str] = []
    for rule in rules:
        if not rule.when(facts):
            continue
        row_level, row_action = rule.airborne if facts.airborne else rule.ground
        if not names:
            level, action = row_level, row_action
        names.append(rule.name)
        text = rule.message(facts)
        if row_action in MOTION:
            text += f" -> {ACTION_NAMES[row_action]}"
        (errors if row_level >= SafetyStatus.LEVEL_CAUTION else warnings).append(text)
    return Verdict(level, action, tuple(names), tuple(warnings), tuple(errors))
