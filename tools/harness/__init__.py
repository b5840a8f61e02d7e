"""One test harness for everything that drives a running stack from outside: the tests, `aero chaos`,
`aero bench soak`, the benches and evals.

    processes   free_port, free_udp_port, aero_argv, aero, clean_env, interrupt, is_service_process,
                stop_up, profile_services, proc_stats
    waiting     poll_until (last value, falsy on timeout), wait_until (AssertionError naming what)
    topics      zenoh_client, token_alive, latest (None on timeout), wait_for_message and diag
                (AssertionError on timeout),
                sample_stream, Capture (every message on some keys with its arrival time)
    stack       Stack (a running `aero up`: ready, queried, commanded, landed, stopped by pid),
                StackFactory, StackStartError
    sim_stack   FlightStack (fmu reaches its FC through a MavlinkTap), SimStack (the built-in sim)
    px4_stack   Px4Stack (PX4 SITL, judged by SIH's truth), SihTruth
    mavlink_tap MavlinkTap, setpoint_problem, msgid
    vehicle     pos, speed

Everything runs on 127.0.0.1 with ports picked by the OS; every wait is bounded; every process is
stopped through its own handle or recorded pid (never by name).
"""
from .mavlink_tap import MavlinkTap, msgid, setpoint_problem
from .processes import (
    aero, aero_argv, clean_env, free_port, free_udp_port, interrupt, is_service_process, proc_stats, profile_services,
    stop_up,
)
from .px4_stack import Px4Stack, SihTruth
from .sim_stack import FlightStack, SimStack
from .stack import Stack, StackFactory, StackStartError
from .topics import Capture, diag, latest, sample_stream, token_alive, wait_for_message, zenoh_client
from .vehicle import pos, speed
from .waiting import poll_until, wait_until

__all__ = [
    "Capture", "FlightStack", "MavlinkTap", "Px4Stack", "SihTruth", "SimStack", "Stack", "StackFactory", "StackStartError", "aero", "aero_argv", "clean_env",
    "diag", "free_port", "free_udp_port", "interrupt", "is_service_process", "latest", "msgid", "poll_until", "pos",
    "proc_stats", "profile_services", "sample_stream", "setpoint_problem", "speed", "stop_up", "token_alive",
    "wait_for_message", "wait_until", "zenoh_client",
]
