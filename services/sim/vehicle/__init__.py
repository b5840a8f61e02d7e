"""Simulated PX4 multirotor speaking MAVLink 2 over UDP exactly like PX4 SITL.

Layout mirrors PX4's modules: `params` (every parameter, declared once), `dynamics`
(`Multirotor` airframe + battery), `control` (mc_pos_control-like cascade), `commander`
(arming, modes, offboard rules, failsafes, auto modes), `model` (`SimVehicle`: all of the above on
a sim clock, no I/O), `mavlink_module` (messages <-> vehicle: `mavlink_receiver` in,
`mavlink_streams` out), `endpoint` (UDP socket) and
`runner` (`SimVehicleRunner`: fixed-step loop paced at `speed` x real time).

Standalone: `python -m aeroperception.services.sim.vehicle --help`.
"""
from .commander import Ack, Commander
from .control import PositionController, Setpoint
from .dynamics import Battery, Multirotor, RigidBodyState
from .endpoint import PX4_SITL_BIND, PX4_SITL_TARGET, MavlinkEndpoint, parse_address
from .mavlink_module import MavlinkModule
from .mavlink_receiver import setpoint_from_mavlink
from .model import SimVehicle
from .params import PARAMS, make_params
from .runner import SimVehicleRunner

__all__ = [
    "Ack", "Commander", "PositionController", "Setpoint", "Battery", "Multirotor", "RigidBodyState",
    "PX4_SITL_BIND", "PX4_SITL_TARGET", "MavlinkEndpoint", "parse_address", "MavlinkModule",
    "setpoint_from_mavlink", "SimVehicle", "PARAMS", "make_params", "SimVehicleRunner",
]
