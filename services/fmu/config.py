"""fmu's configuration: every parameter of contract.PARAMS, referenced once (runtime/config.py
builds it at start, rebuilds it on a live change and calls FmuService.on_config once)."""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.services.runtime import param, section

from .logic import parse_global_origin
from .offboard import ArbiterConfig


@dataclass(frozen=True)
class FmuConfig:
    offboard: ArbiterConfig = section(ArbiterConfig)        # follow / brake / hold (offboard.py)
    offboard_rate_hz: float = param("offboard_rate_hz")
    reboot_gap_s: float = param("reboot_gap_s")
    link_timeout_s: float = param("link_timeout_s")
    vio_timeout_s: float = param("vio_timeout_s")
    home_request_period_s: float = param("home_request_period_s")
    command_timeout_s: float = param("command_timeout_s")
    offboard_warmup_s: float = param("offboard_warmup_s")
    # start-only: the link and what is asked of the FC
    fcu_peer: str = param("fcu_peer")
    fcu_relock_s: float = param("fcu_relock_s")
    ground_truth_rate_hz: float = param("ground_truth_rate_hz")
    global_origin: tuple[float, float, float] | None = param("global_origin", parse_global_origin)  # a bad value fails start
    publish_imu: bool = param("publish_imu")
    source_system: int = param("source_system")
    source_component: int = param("source_component")
