"""`aero up`: the router plus a profile's services as supervised child processes.

One room per idea, read in this order: validation.py (the arguments, refused before anything
starts), sensors.py (a real vehicle's sensors file: its drivers and the perception they feed), launch.py (the launch plan: which services, each one's command line, from
tools/profiles.yaml), supervision.py (the router and the services as children, restarted with
back-off, stopped together) and status.py (the status table).

Each service runs as `python -m aeroperception.services.<name>`, its JSON log goes to
<log-dir>/<name>.log; Ctrl-C / SIGTERM stops every child (SIGTERM, then SIGKILL after 3 s), the
router last. <log-dir>/pids.json maps each running service to its process id (rewritten on every
start and exit), so scripts and tests can find a service's process without searching by name.

Supervision (ARCHITECTURE §8): children get AERO_SUPERVISOR_PID and exit when `aero up` dies,
even by kill -9 (runtime/supervision.py), so a new `aero up` never finds the old one's services.
Scheduling: `priorities:` in profiles.yaml (SCHED_RR where permitted, else nice) keeps the hot
path (router, fmu, planner) ahead of rendering and perception; what each process got is printed
at start.
"""
from __future__ import annotations

import argparse

from aeroperception.services.runtime.session import LINKS
from aeroperception.services.sim.contract import SENSOR_CHOICES
from aeroperception.tools.common import emit

from .. import ardupilot_sitl, px4_sitl
from ..router import THIN_LINK_HZ, thin_link_downsampling
from .launch import (  # noqa: F401 - the launch plan's names, used by tools and tests as cmd_up.X
    PRIORITIES_ENV, SENSOR_NAMES, SENSOR_SERVICES, SENSORS_RENDERED, ArduPilotPlan, LaunchPlan, Priority, Px4Plan,
    fed_services, gps_denied_needs, launch_plan, load_priorities, load_profiles, option_args, plan_ardupilot, plan_fc, plan_px4,
    print_plan, service_argv,
)
from .sensors import SensorPlan, plan_sensors  # noqa: F401
from .status import MESSAGE_COL, format_table  # noqa: F401
from .supervision import (  # noqa: F401
    STACK_DUMP_LINES, Child, RouterChild, last_error_line, shutdown, supervise, write_pids,
)
from .validation import (  # noqa: F401
    ENDPOINT_RE, FCU_URL_RE, check_fcu_url, check_installed, resolve_links, select_services, validate_args,
)

DEFAULT_PROFILE = "sim"                  # README command 1: `aero up`
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"    # the router's endpoint (`aero doctor` checks its port is free)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start the router and a profile's services, supervise them")
    p.add_argument("--profile", default=DEFAULT_PROFILE,
                   help=f"profile from tools/profiles.yaml (default {DEFAULT_PROFILE})")
    p.add_argument("--only", default="", help="comma-separated services to run from the profile")
    p.add_argument("--except", dest="exclude", default="", help="comma-separated services to skip")
    p.add_argument("--listen", default=DEFAULT_LISTEN,
                   help="router endpoint (use tcp/0.0.0.0:7447 to accept other machines)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="join another host's router, e.g. tcp/10.0.0.2:7447 (several machines; repeatable)")
    p.add_argument("--links", default=None, choices=LINKS,
                   help="how the services started here reach each other: direct (peers linked on loopback, "
                        "introduced by the router: one hop) or router (every sample through the router); "
                        "default direct, router when the router is secured (TLS or $AERO_ROUTER_CONFIG)")
    p.add_argument("--thin-link", action="append", default=[], metavar="IFACE",
                   help="router: network interface of a slow link to another host (e.g. wlan0); images "
                        "and scans leave through it downsampled (`aero router --help`; repeatable)")
    p.add_argument("--thin-link-hz", type=float, default=None, metavar="HZ",
                   help="router: per bulk stream through --thin-link (default 1)")
    p.add_argument("--log-dir", default=None, help="service logs (default ~/.aero/logs/<time>)")
    p.add_argument("--scenario", default=None, help="sim: scenario world (open_field, village, slope_forest)")
    p.add_argument("--speed", type=float, default=None, help="sim: run faster than real time (services follow sim/clock)")
    p.add_argument("--seed", type=int, default=None, help="sim: random seed (wind, noise)")
    p.add_argument("--sensors", default=None, choices=SENSOR_CHOICES,
                   help="sim: which scenario sensors to render (none: vehicle and truth only, least CPU)")
    p.add_argument("--fcu-url", default=None, help="fmu: MAVLink URL of the flight controller")
    p.add_argument("--sensors-file", default=None, metavar="FILE",
                   help="vehicle profile: the cameras and LiDAR it carries, their drivers and mounts (YAML; "
                        "docs: A real drone); adds the drivers and the perception they feed")
    p.add_argument("--px4", default=None, metavar="DIR",
                   help=f"px4 profile: the PX4 build to run as SITL (bin/px4 + etc/, e.g. "
                        f"PX4-Autopilot/build/px4_sitl_default; default ${px4_sitl.DIR_ENV})")
    p.add_argument("--px4-instance", type=int, default=None, metavar="N",
                   help="px4 profile: PX4 instance N (ports 14540+N / 14580+N, /tmp/px4_lock-N; default 0)")
    p.add_argument("--ardupilot", default=None, metavar="DIR",
                   help=f"ardupilot profile: ArduCopter SITL to run (the ardupilot-sitl-copter folder or its "
                        f".tar.gz, or an ArduPilot checkout after ./waf copter; default ${ardupilot_sitl.DIR_ENV})")
    p.add_argument("--ardupilot-instance", type=int, default=None, metavar="N",
                   help="ardupilot profile: ArduPilot instance N (-I N: TCP 5760+10N..5763+10N; fmu on UDP "
                        "14540+N; default 0)")
    p.add_argument("--gps-denied", action="store_true",
                   help="sim: the flight controller has no GPS-like position, only the VIO (fused with its "
                        "IMU); px4: PX4 boots for vision-only navigation (SIH GPS without satellites, EKF2 on "
                        "the ODOMETRY fmu sends: `aero fc params show gps-denied-sih`); the mission waits for "
                        "and holds on perception health (VIO TRACKING)")
    p.add_argument("--mission", default=None, metavar="FILE",
                   help="mission: load this mission file (JSON or YAML) at start-up (checked before anything starts)")
    p.add_argument("--arg", action="append", default=[], metavar="SERVICE:FLAG",
                   help="extra flag for one service, e.g. --arg planner:--param=kp=1.0")
    p.add_argument("--status-interval", type=float, default=2.0, help="seconds between status tables")
    p.add_argument("--dry-run", action="store_true",
                   help="validate the arguments and print each service's command line; start nothing")
    p.set_defaults(func=run)


def run(args) -> int:
    sensor_plan = plan_sensors(args)
    names = select_services(args, sensor_plan.services)
    check_installed(args.profile, names)
    if args.thin_link:  # the router would refuse them: say so before anything starts
        thin_link_downsampling(args.thin_link, THIN_LINK_HZ if args.thin_link_hz is None else args.thin_link_hz)
    validate_args(args, names)
    names, unfed = fed_services(names, args.sensors)
    for n, why in unfed.items():
        emit(f"aero up: not starting {n}: {why}")
    fc = plan_fc(args, names)
    plan = launch_plan(args, names, fc, resolve_links(args), sensor_plan.args)
    if args.dry_run:
        print_plan(args, plan)
        return 0
    return supervise(args, plan, load_priorities())
