"""Which received MAVLink messages are gcs's to answer, free of sockets and Zenoh.

As the vehicle (identity autopilot) gcs answers what is addressed to its system or to every
system; FILE_TRANSFER_PROTOCOL whatever its target (ground stations probe it, and are answered
at once that there is no file). As the flight controller's onboard computer (identity companion)
it also answers only what is addressed to its component (parameter requests to every component
too): the flight controller answers the rest on its own link. Heartbeats are always looked at.
"""
from __future__ import annotations

PARAM_REQUESTS = ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ")


def ignored_because(msg_type: str, target_system: int | None, target_component: int | None,
                    system_id: int, component_id: int, companion: bool) -> str | None:
    """Why a message is not ours ("other_target", "other_component"), or None when it is."""
    if target_system not in (None, 0, system_id) and msg_type != "FILE_TRANSFER_PROTOCOL":
        return "other_target"
    if companion and msg_type != "HEARTBEAT" and target_component is not None and target_component != component_id \
            and not (target_component == 0 and msg_type in PARAM_REQUESTS):
        return "other_component"
    return None
