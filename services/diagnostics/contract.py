"""Contract of the diagnostics service: keys in/out and parameters."""
from aeroperception.schemas import DiagnosticArray, DiagnosticStatus
from aeroperception.services.runtime import Param

NAME = "diagnostics"
INPUTS = {"diagnostics/*": DiagnosticStatus}            # every service's 1 Hz health
OUTPUTS = {"diagnostics/agg": DiagnosticArray}          # the roll-up, 1 Hz
PARAMS = [
    Param("stale_after_s", 3.0, "s", 0.5, 60.0, description="no status for this long -> STALE"),
    Param("publish_rate_hz", 1.0, "Hz", 0.1, 10.0, description="rate of diagnostics/agg"),
]
