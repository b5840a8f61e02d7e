"""Contract of the diagnostics service: keys in/out and parameters."""
from aeroperception.schemas import DiagnosticArray, DiagnosticStatus
from aeroperception.services.runtime import Param, Topic, Topics

NAME = "diagnostics"
INPUTS = Topics(Topic("diagnostics/*", DiagnosticStatus, note="every service's health"))
OUTPUTS = Topics(Topic("diagnostics/agg", DiagnosticArray, 1.0, note="the roll-up (publish_rate_hz)"))
LIVELINESS = ("*",)     # a service whose token went away is STALE at once
PARAMS = [
    Param("stale_after_s", 3.0, "s", 0.5, 60.0, description="no status for this long -> STALE"),
    Param("publish_rate_hz", 1.0, "Hz", 0.1, 10.0, description="rate of diagnostics/agg"),
]
