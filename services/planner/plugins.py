"""The planner's swappable parts and when one may be swapped.

Three slots, each a registry keyed by name and a planner parameter naming the one that runs:
trajectory_generator (services/lib/trajectory/generators.py), controller (controllers.py), estimator
(estimators.py). `planner/srv/select_plugin` (SetTrajectoryGenerator / SetController /
SetEstimator) and `aero param set planner <slot> NAME` are the same switch: both go through the
parameter, so there is one value of what runs and one rule for when it may change.

A switch is safe on the ground (landed or disarmed) or hovering (in the air, speed below
`hover_speed_mps`; the rule is services/lib/flight_state.py, shared with the mission's UAVMode); moving, the old part's reference and the new one's would disagree mid-way
(a trajectory's timing, a feed-forward the other controller drops), so it is refused, saying
how fast the vehicle moves. `vio` is refused while VIO's odometry is not fresh.

A switch persists (PARTS_FILE in the state directory, like the mission's progress) and a restarted
planner starts with the parts selected last, so a restart in flight never silently changes what
flies; restored over a different start-up value, it says so. A restored `vio` without VIO
odometry gives the planner no state: it sends no setpoints and the flight controller holds.
"""
from __future__ import annotations

from aeroperception.schemas import VehicleState
from aeroperception.services.lib.flight_state import is_hovering, on_ground, speed_mps
from aeroperception.services.lib.trajectory.generators import GENERATORS

from .controllers import CONTROLLERS
from .estimators import ESTIMATORS

REGISTRIES: dict[str, dict] = {"trajectory_generator": GENERATORS, "controller": CONTROLLERS, "estimator": ESTIMATORS}
PARTS_FILE = "planner_parts.json"


def selected_parts(params) -> dict[str, str]:
    """What runs in each slot (the snapshot persisted on every switch)."""
    return {role: params[role] for role in REGISTRIES}


def restore_parts(saved: dict | None, params) -> list[str]:
    """Set each slot to the part persisted last (`saved`: a snapshot, None = none); returns what
    was restored over a different value and what was not restorable, one line each."""
    notes = []
    for role, registry in REGISTRIES.items():
        name = (saved or {}).get(role)
        if name is None or name == params[role]:
            continue
        if name not in registry:
            notes.append(f"{role} {name!r} persisted but not registered: {params[role]!r} runs")
            continue
        notes.append(f"{role} {name!r} restored (selected before the restart) over {params[role]!r}")
        params.set(role, name)
    return notes


def switch_refusal(role: str, name: str, state: VehicleState | None, hover_speed_mps: float,
                   vio_fresh: bool = False) -> str:
    """Why `role` may not switch to `name` now ('' = it may). No vehicle state: the planner
    sends no setpoints, so any switch is safe."""
    registry = REGISTRIES[role]
    if name not in registry:
        return f"{role} {name!r} is not registered: {', '.join(registry)}"
    if state is not None and not on_ground(state) and not is_hovering(state, hover_speed_mps):
        return (f"moving at {speed_mps(state):.2f} m/s: switch the {role} on the ground or hovering "
                f"(below hover_speed_mps {hover_speed_mps:g} m/s)")
    if role == "estimator" and name == "vio" and not vio_fresh:
        return "no fresh state/visual_odometry: VIO must be running before it is the estimator"
    return ""
