"""safety/status -> STATUSTEXT for ground stations (no Zenoh).

The safety service lists what is wrong (SafetyStatus.active_warnings / active_errors) at 1 Hz and
on change; a ground station should see each item once, when it appears, with a severity it
shows accordingly: warnings MAV_SEVERITY_WARNING, errors MAV_SEVERITY_CRITICAL (EMERGENCY while
safety's level is EMERGENCY), and a MAV_SEVERITY_INFO note when an item clears. Texts are prefixed
"Safety: " so the operator knows where they come from.
"""
from __future__ import annotations

from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import SafetyStatus

PREFIX = "Safety: "


class SafetyRelay:
    """What to tell ground stations about each new safety/status: [(severity, text)]."""

    def __init__(self) -> None:
        self.warnings: set[str] = set()
        self.errors: set[str] = set()

    def update(self, msg: SafetyStatus) -> list[tuple[int, str]]:
        warnings, errors = set(msg.active_warnings), set(msg.active_errors)
        error_sev = M.MAV_SEVERITY_EMERGENCY if msg.safety_level >= SafetyStatus.LEVEL_EMERGENCY \
            else M.MAV_SEVERITY_CRITICAL
        out = [(error_sev, PREFIX + e) for e in msg.active_errors if e not in self.errors]
        out += [(M.MAV_SEVERITY_WARNING, PREFIX + w) for w in msg.active_warnings if w not in self.warnings]
        out += [(M.MAV_SEVERITY_INFO, f"{PREFIX}cleared: {x}") for x in sorted((self.errors | self.warnings)
                                                                           - (errors | warnings))]
        self.warnings, self.errors = warnings, errors
        return out
