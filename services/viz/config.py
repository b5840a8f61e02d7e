"""viz's configuration: every parameter of contract.PARAMS, referenced once. The outputs and the
adapters are made from it at start (those parameters are start_only); show_truth and the rates
are read per sample, and a rate raised from 0 subscribes its keys then (VizService.on_config)."""
from __future__ import annotations

from dataclasses import dataclass

from aeroperception.services.runtime import param, section

from .viewer import Outputs


@dataclass(frozen=True)
class VizConfig:
    outputs: Outputs = section(Outputs)
    show_truth: bool = param("show_truth")
    pose_rate_hz: float = param("pose_rate_hz")
    image_rate_hz: float = param("image_rate_hz")
    cloud_rate_hz: float = param("cloud_rate_hz")
    costmap_rate_hz: float = param("costmap_rate_hz")
    setpoint_rate_hz: float = param("setpoint_rate_hz")
    objects_rate_hz: float = param("objects_rate_hz")
    image_jpeg_quality: int = param("image_jpeg_quality")
    trail_period_s: float = param("trail_period_s")
    trail_max_points: int = param("trail_max_points")
    flush_timeout_s: float = param("flush_timeout_s")

    def rate_hz(self, rate_param: str) -> float:
        """The sampling rate an adapter's `rate_param` names (one of the *_rate_hz fields)."""
        return getattr(self, rate_param)
