"""`aero up`'s argument checks: everything that would only make a child crash-loop is refused,
in one line naming what to do, before anything starts. Reads the arguments and profiles.yaml;
starts nothing."""
from __future__ import annotations

import difflib
import math
import os
import re

from aeroperception.tools import service_imports
from aeroperception.tools.common import CliError

from .. import px4_sitl
from .launch import gps_denied_needs, load_profiles


def _did_you_mean(word: str, choices) -> str:
    near = difflib.get_close_matches(word, list(choices), n=3, cutoff=0.5)
    return f" (did you mean {', '.join(near)}?)" if near else ""


def check_installed(profile: str, names: list[str]) -> None:
    """Refuse, in one line and before anything starts, services whose modules are not installed
    (they would only crash-loop): the modules, who needs them, and the one command that installs
    the profile's extras (profiles.yaml `install:`). Found by reading the services' source and
    find_spec: nothing is imported."""
    short = service_imports.shortfall(names)
    if short.modules:
        who = "; ".join(f"{m} ({', '.join(short.needed_by[m])})" for m in short.modules)
        extras = load_profiles()[profile]["install"]
        raise CliError(f"profile {profile}: not installed: {who}. Install with: "
                       f"{service_imports.install_command(extras)}"
                       f" (or leave them out with --except {','.join(sorted({s for v in short.needed_by.values() for s in v}))})")


def select_services(args, added: list[str] = ()) -> list[str]:
    """The profile's services (and those a sensors file `added`), narrowed by --only / --except."""
    profiles = load_profiles()
    if args.profile not in profiles:
        raise CliError(f"unknown profile {args.profile!r}{_did_you_mean(args.profile, profiles)}; "
                       f"profiles: {', '.join(profiles)}")
    names = list(profiles[args.profile]["services"])
    names += [n for n in added if n not in names]
    for flag, text in (("--only", args.only), ("--except", args.exclude)):
        for s in (s.strip() for s in text.split(",")):
            if s and s not in names:
                raise CliError(f"{flag} {s}: not in profile {args.profile}{_did_you_mean(s, names)}; "
                               f"its services: {', '.join(names)}")
    if args.only:
        only = {s.strip() for s in args.only.split(",") if s.strip()}
        names = [n for n in names if n in only]
    excl = {s.strip() for s in args.exclude.split(",") if s.strip()}
    return [n for n in names if n not in excl]


# pymavlink connection strings: udp/udpin/udpout/udpbcast/tcp/tcpin:HOST:PORT, or a serial device
# with an optional baud rate (/dev/ttyACM0,921600; COM3).
FCU_URL_RE = re.compile(r"^(?:(?:udp|udpin|udpout|udpbcast|tcp|tcpin):[A-Za-z0-9_.\-]+:(\d{1,5})"
                        r"|(?:/dev/\S+|COM\d+)(?:,\d+)?)$")


def check_fcu_url(url: str) -> None:
    """Refuse, in one line, a --fcu-url pymavlink could not open."""
    m = FCU_URL_RE.match(url)
    if not m or (m.group(1) and not 0 < int(m.group(1)) < 65536):
        raise CliError(f"--fcu-url {url!r}: expected udpin:HOST:PORT, udpout:HOST:PORT, "
                       "tcp:HOST:PORT or a serial device /dev/ttyACM0,921600")


ENDPOINT_RE = re.compile(r"^(?:tcp|udp|tls|quic|ws)/[A-Za-z0-9_.\-\[\]:]+:\d{1,5}$")


def resolve_links(args) -> str:
    """direct unless the router is secured: a direct link is plain TCP on loopback, around the
    router's TLS and ACL, so a secured stack keeps every sample on the router."""
    secured = not args.listen.startswith("tcp/") or bool(os.environ.get("AERO_ROUTER_CONFIG"))
    if args.links == "direct" and secured:
        raise CliError("--links direct: the router is secured (TLS listen or $AERO_ROUTER_CONFIG) and direct links "
                       "would bypass its ACL; drop --links or use --links router")
    return args.links or ("router" if secured else "direct")


def validate_args(args, names: list[str]) -> None:
    """Refuse, before anything starts, what would only make a child crash-loop."""
    if args.speed is not None and not (math.isfinite(args.speed) and args.speed > 0):
        raise CliError(f"--speed {args.speed:g}: must be a number > 0 (1 = real time, 4 = four times faster)")
    if px4_sitl.NAME in names and "sim" in names:   # the simulator follows PX4's physics (sim --follow)
        for flag, value in (("--speed", args.speed), ("--seed", args.seed)):
            if value is not None:
                raise CliError(f"{flag}: PX4 SITL flies the vehicle in real time with its own wind and sensor noise; "
                               f"drop {flag} (it applies to the built-in simulator, --profile sim)")
    if args.scenario is not None and "sim" in names:
        from aeroperception.services.sim.world.scenario import ScenarioError, available_scenarios, load_scenario

        try:
            load_scenario(args.scenario)
        except ScenarioError as e:
            raise CliError(f"--scenario: {e}{_did_you_mean(args.scenario, available_scenarios())}") from None
    profile = load_profiles()[args.profile]["services"]
    everything = profile + [n for n in names if n not in profile]     # a sensors file's services too
    if getattr(args, "gps_denied", False):
        # A profile without them (px4, vehicle) gets its vision from elsewhere (another host's VIO)
        missing = [n for n in gps_denied_needs() if n in everything and n not in names]
        if missing:
            raise CliError(f"--gps-denied needs {', '.join(missing)} (the vision position and its health): "
                           "do not leave them out with --only/--except")
        if args.sensors not in (None, "all", "camera"):
            raise CliError(f"--gps-denied needs the cameras: drop --sensors {args.sensors}")
    if getattr(args, "mission", None) is not None:
        from aeroperception.schemas import SchemaError, load_mission_file

        if "mission" not in names:
            raise CliError("--mission needs the mission service: do not leave it out with --only/--except")
        try:
            load_mission_file(args.mission)
        except SchemaError as e:
            raise CliError(f"--mission {args.mission}: {e}") from None
    if args.fcu_url is not None:
        check_fcu_url(args.fcu_url)
    for ep in args.connect:
        if not ENDPOINT_RE.match(ep):
            raise CliError(f"--connect {ep!r}: expected a Zenoh endpoint like tcp/10.0.0.2:7447")
    for item in args.arg:
        svc, sep, flag = item.partition(":")
        if not sep or not flag:
            raise CliError(f"--arg {item!r}: expected SERVICE:FLAG, e.g. planner:--param=kp=1.0")
        if svc not in everything:
            raise CliError(f"--arg {item!r}: no service {svc!r} in profile {args.profile}"
                           f"{_did_you_mean(svc, everything)}")

