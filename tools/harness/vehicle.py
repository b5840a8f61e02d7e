"""The vehicle as a harness judges it: position and speed of a VehicleState as plain numbers."""
from __future__ import annotations

import numpy as np

from aeroperception.schemas import VehicleState


def pos(m: VehicleState) -> np.ndarray:
    """Position [x, y, z] in metres (ENU)."""
    return m.position_m.to_array()


def speed(m: VehicleState) -> float:
    """Speed in m/s."""
    return float(np.linalg.norm(m.velocity_mps.to_array()))
