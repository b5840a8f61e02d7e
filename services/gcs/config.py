"""gcs's configuration: every parameter of contract.PARAMS, referenced once (runtime/config.py
builds it at start; only call_timeout_s may change live, GcsService.on_config)."""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.services.runtime import param


@dataclass(frozen=True)
class GcsConfig:
    # the ground-station link (link.py, presence.py)
    gcs_ip: str = param("gcs_ip")
    remote_port: int = param("remote_port")
    local_port: int = param("local_port")
    bind_ip: str = param("bind_ip")
    gcs_timeout_s: float = param("gcs_timeout_s")
    gcs_system_ids: str = param("gcs_system_ids")
    signing_key_file: str = param("signing_key_file")
    signing_link_id: int = param("signing_link_id")
    # who gcs is on it
    identity: str = param("identity")
    system_id: int = param("system_id")
    component_id: int = param("component_id")
    # what it sends and asks
    telemetry_period_s: float = param("telemetry_period_s")
    home_lat_deg: float = param("home_lat_deg")
    home_lon_deg: float = param("home_lon_deg")
    home_alt_m: float = param("home_alt_m")
    mission_item_timeout_s: float = param("mission_item_timeout_s")
    mission_retries: int = param("mission_retries")
    max_mission_items: int = param("max_mission_items")
    param_services: tuple[str, ...] = param("param_services", lambda text: tuple(text.split(",")))
    param_refresh_s: float = param("param_refresh_s")
    call_timeout_s: float = param("call_timeout_s")        # the only one live
