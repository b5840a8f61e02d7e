"""The mission service's configuration: every parameter of contract.PARAMS, referenced once
(runtime/config.py builds it, rebuilds it on a live change and calls MissionService.on_config once)."""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.services.runtime import param, section

from .fsm import Config
from .limits import Limits


@dataclass(frozen=True)
class MissionConfig:
    fsm: Config = section(Config)              # the mission FSM's settings (fsm.py)
    limits: Limits = section(Limits)           # what is accepted to fly, with the geofence (limits.py)
    bridge_timeout_s: float = param("bridge_timeout_s")
    status_rate_hz: float = param("status_rate_hz")
    mission_file: str = param("mission_file")
    state_dir: str = param("state_dir")
