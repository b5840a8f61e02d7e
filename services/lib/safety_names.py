"""The names of SafetyStatus's levels and actions, for messages and logs: safety says them in its
diagnostics and status text, the mission in why it held or landed. One table, so both say the
same word for the same value.
"""
from aeroperception.schemas import SafetyStatus

L, A = SafetyStatus, SafetyStatus   # LEVEL_* and ACTION_* constants

LEVEL_NAMES = {L.LEVEL_NOMINAL: "NOMINAL", L.LEVEL_WARNING: "WARNING", L.LEVEL_CAUTION: "CAUTION",
               L.LEVEL_EMERGENCY: "EMERGENCY"}
ACTION_NAMES = {A.ACTION_NONE: "NONE", A.ACTION_WARN: "WARN", A.ACTION_HOLD: "HOLD", A.ACTION_RTH: "RTH",
                A.ACTION_LAND: "LAND", A.ACTION_EMERGENCY_STOP: "EMERGENCY_STOP"}
