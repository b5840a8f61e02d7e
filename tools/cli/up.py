"""`aero up`: the router plus a profile's services as supervised child processes.

The Zenoh router runs as a child too (`aero router`, log <log-dir>/router.log, pid in
<log-dir>/router.pid): when it dies it is restarted within a second (back-off 0.2 s doubling to
2 s) and every session reconnects by itself. Each service runs as `python -m
aeroperception.services.<name>`, its JSON log goes to <log-dir>/<name>.log, a crashed service is
restarted with back-off (1 s doubling to 30 s), and Ctrl-C / SIGTERM stops every child (SIGTERM,
then SIGKILL after 3 s), the router last.
<log-dir>/pids.json maps each running service to its process id (rewritten on every start and
exit), so scripts and tests can find a service's process without searching by name.

Supervision (ARCHITECTURE §8): children get AERO_SUPERVISOR_PID and exit when `aero up` dies,
even by kill -9 (runtime/supervision.py), so a new `aero up` never finds the old one's services.
A service that refuses to start because the same service is already alive for the vehicle
(exit EXIT_DUPLICATE) is shown as "duplicate" and is not restarted until that other instance's
liveliness token goes away. Scheduling: `priorities:` in profiles.yaml (SCHED_RR where
permitted, else nice) keeps the hot path (router, fmu, planner) ahead of rendering and
perception; what each process got is printed at start.
"""
from __future__ import annotations

import argparse
import difflib
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import yaml
import zenoh

from aeroperception.services.runtime.node import LIVELINESS_ROOT
from aeroperception.services.sim.contract import SENSOR_CHOICES
from aeroperception.services.runtime.session import LINKS, LINKS_ENV, make_config, open_session
from aeroperception.services.runtime.signals import ShutdownFlag
from aeroperception.services.runtime.supervision import (
    EXIT_DUPLICATE, SUPERVISOR_ENV, Priority, apply_priority, terminate,
)

from . import px4_sitl
from .router import THIN_LINK_HZ, thin_link_downsampling
from .topic import LEVEL_NAMES as LEVELS
from .topic import decode_sample
from aeroperception.tools import service_imports
from aeroperception.tools.common import CliError, emit


def _union(base: list, more) -> list:
    return [*base, *(x for x in more or () if x not in base)]


def load_profiles() -> dict[str, dict]:
    """{profile: {"services": [...], "args": {service: [flags]}, "install": [pip extras]}}; a bare
    list means services only. `extends: OTHER` starts from an earlier profile's services, args and
    extras and adds its own."""
    text = resources.files("aeroperception.tools").joinpath("profiles.yaml").read_text()
    out = {}
    for name, spec in yaml.safe_load(text)["profiles"].items():
        spec = {"services": spec} if isinstance(spec, list) else dict(spec)
        base = out[spec["extends"]] if spec.get("extends") else {"services": [], "args": {}, "install": []}
        out[name] = {"services": _union(base["services"], spec["services"]),
                     "args": {**base["args"], **dict(spec.get("args") or {})},
                     "install": _union(base["install"], spec.get("install"))}
    return out


PRIORITIES_ENV = "AERO_PRIORITIES"  # "off": every process at the default (for A/B benchmarks)


def load_priorities() -> dict[str, Priority]:
    """{process: Priority} from the `priorities:` section of profiles.yaml (unlisted: nice 0);
    empty when AERO_PRIORITIES=off."""
    if os.environ.get(PRIORITIES_ENV, "").lower() in ("off", "0", "no", "false"):
        return {}
    text = resources.files("aeroperception.tools").joinpath("profiles.yaml").read_text()
    raw = yaml.safe_load(text).get("priorities") or {}
    try:
        return {str(name): Priority.parse(str(name), spec) for name, spec in raw.items()}
    except ValueError as e:
        raise CliError(f"tools/profiles.yaml: {e}") from None


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
    p.add_argument("--px4", default=None, metavar="DIR",
                   help=f"px4 profile: the PX4 build to run as SITL (bin/px4 + etc/, e.g. "
                        f"PX4-Autopilot/build/px4_sitl_default; default ${px4_sitl.DIR_ENV})")
    p.add_argument("--px4-instance", type=int, default=None, metavar="N",
                   help="px4 profile: PX4 instance N (ports 14540+N / 14580+N, /tmp/px4_lock-N; default 0)")
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


@dataclass
class Child:
    name: str
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    restarts: int = 0
    backoff_s: float = 1.0
    next_start: float = 0.0
    last_exit: int | None = None
    alive: bool = False
    health: dict = field(default_factory=dict)
    priority: Priority = field(default_factory=Priority)
    sched: str = ""             # what the scheduler granted, e.g. "SCHED_RR 20"
    token: bool = False         # aero/alive/<vehicle>/<name> exists (ours or another instance's)
    waiting_since: float | None = None  # refused as a duplicate; waiting for the other to stop
    last_error: str = ""
    # A process that is not one of our services (PX4 SITL): its own environment and clean-stop
    # signal; it has no liveliness token of its own, so aero up holds one for it while it runs and
    # its log has shown `booted`.
    extra_env: dict[str, str] = field(default_factory=dict)
    stop_signal: int = signal.SIGTERM
    booted: str = ""
    proxy_token: zenoh.LivelinessToken | None = None
    log_offset: int = 0

    def start(self, env: dict[str, str]) -> None:
        self.log_offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(self.argv, stdout=log, stderr=subprocess.STDOUT, env={**env, **self.extra_env},
                                     start_new_session=True)
        log.close()
        self.started_at = time.monotonic()
        # Right after exec, before the interpreter starts any thread: later threads inherit it.
        self.sched = apply_priority(self.proc.pid, self.priority)

    def held_elsewhere(self, now: float) -> bool:
        """Refused as a duplicate and the other instance is still alive: do not restart yet."""
        if self.last_exit != EXIT_DUPLICATE or not self.token:
            self.waiting_since = None
            return False
        if self.waiting_since is None:
            self.waiting_since = now
            emit(f"aero up: {self.name} not started: the same service is already running for this "
                 f"vehicle (see {self.log_path}); starting it when that one stops")
        return True

    def hold_token(self, session: zenoh.Session, key: str) -> None:
        """For a process with `booted`: declare its liveliness token once its log says it booted,
        undeclare it when it exits."""
        running = self.proc is not None and self.proc.poll() is None
        if running and self.proxy_token is None:
            with open(self.log_path, "rb") as f:
                f.seek(self.log_offset)
                if self.booted.encode() in f.read():
                    self.proxy_token = session.liveliness().declare_token(key)
        elif not running:
            self.drop_token()

    def drop_token(self) -> None:
        if self.proxy_token is not None:
            self.proxy_token.undeclare()
            self.proxy_token = None

    def status(self) -> str:
        if self.proc is None and self.last_exit == EXIT_DUPLICATE:
            return "duplicate"
        if self.proc is None or self.proc.poll() is not None:
            return "restarting" if self.restarts or self.last_exit is not None else "starting"
        return "alive" if self.alive else "starting"


def write_pids(path: Path, children) -> None:
    """{service: pid} of the running children, replaced atomically so readers never see half a file."""
    pids = {c.name: c.proc.pid for c in children if c.proc is not None}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(pids, indent=1) + "\n")
    os.replace(tmp, path)


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


def select_services(args) -> list[str]:
    profiles = load_profiles()
    if args.profile not in profiles:
        raise CliError(f"unknown profile {args.profile!r}{_did_you_mean(args.profile, profiles)}; "
                       f"profiles: {', '.join(profiles)}")
    names = list(profiles[args.profile]["services"])
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


# `aero up --sensors`: what the simulator renders for each choice (the IMU always, but with none),
# and the services that exist only to process one sensor: not started when it is not rendered (a
# lidar service without scans would say WARN for ever); perception is told which sources run.
SENSORS_RENDERED = {"all": {"camera", "lidar"}, "camera": {"camera"}, "lidar": {"lidar"}, "imu": set(), "none": set()}
SENSOR_SERVICES = {"vio": "camera", "detector": "camera", "objects": "camera", "lidar": "lidar"}
SENSOR_NAMES = {"camera": "cameras", "lidar": "LiDAR"}


def fed_services(names: list[str], sensors: str | None) -> tuple[list[str], dict[str, str]]:
    """(services to start, {left out: why}) for `--sensors` (None: all); perception is left out
    when none of its sources (vio, detector, lidar) runs."""
    from aeroperception.services.perception.logic import SOURCES

    rendered = SENSORS_RENDERED[sensors or "all"]
    out = {n: f"--sensors {sensors} renders no {SENSOR_NAMES[SENSOR_SERVICES[n]]}"
           for n in names if n in SENSOR_SERVICES and SENSOR_SERVICES[n] not in rendered}
    kept = [n for n in names if n not in out]
    if "perception" in kept and not any(s in kept for s in SOURCES):
        out["perception"] = "none of its sources (vio, detector, lidar) runs"
        kept.remove("perception")
    return kept, out


# `aero up --gps-denied`: the sim FC estimates position from the VIO only (SIM_GPS_DENIED); the
# mission gates EXECUTING on perception/health (requirements VIO-3, MIS-1).
GPS_DENIED_NEEDS = ("vio", "perception")
GPS_DENIED_ARGS = {
    # EKF2_EV_NOISE_MD=1: vio's covariance includes its accumulated drift (services/vio/drift.py),
    # a common offset of every later sample, not per-sample noise: fuse with EKF2_EVP_NOISE instead.
    "sim": ["--param", "SIM_GPS_DENIED=true", "--param", "EKF2_EV_NOISE_MD=1"],
    "mission": ["--param", "require_perception=true"],
}
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
    everything = load_profiles()[args.profile]["services"]
    if getattr(args, "gps_denied", False):
        # A profile without them (px4, vehicle) gets its vision from elsewhere (another host's VIO)
        missing = [n for n in GPS_DENIED_NEEDS if n in everything and n not in names]
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


@dataclass(frozen=True)
class Px4Plan:
    """The PX4 SITL a px4 profile starts: checked build dir and a free instance."""

    build: Path
    instance: int
    gps_denied: bool = False    # boot for vision-only navigation (fc_params' gps-denied-sih set)

    def env(self) -> dict[str, str]:
        return px4_sitl.boot_env(gps_denied=self.gps_denied)

    def child(self, log_dir: Path, priority: Priority) -> Child:
        workdir = px4_sitl.work_dir(log_dir)
        c = Child(px4_sitl.NAME, px4_sitl.argv(self.build, self.instance, workdir), log_dir / f"{px4_sitl.NAME}.log",
                  priority=priority, extra_env=self.env(), stop_signal=signal.SIGINT,
                  booted=px4_sitl.BOOTED)
        c.health = {"level": 0, "message": px4_sitl.describe(self.instance, workdir)}
        return c


def plan_px4(args, names: list[str]) -> Px4Plan | None:
    """With px4 in the selection: its build and instance checked before anything starts, and fmu
    pointed at it. Without: --px4 / --px4-instance are refused, not ignored."""
    px4_dir, instance = getattr(args, "px4", None), getattr(args, "px4_instance", None)
    if px4_sitl.NAME not in names:
        if px4_dir is not None or instance is not None:
            flag = "--px4" if px4_dir is not None else "--px4-instance"
            raise CliError(f"{flag}: profile {args.profile} starts no PX4 (use --profile px4)")
        return None
    if args.fcu_url is not None:
        raise CliError(f"--fcu-url: fmu talks to the PX4 this profile starts ({px4_sitl.fcu_url(instance or 0)}); "
                       "drop --fcu-url, or use --profile vehicle for a flight controller of your own")
    plan = Px4Plan(px4_sitl.build_dir(px4_dir), 0 if instance is None else instance, getattr(args, "gps_denied", False))
    px4_sitl.check_instance(plan.instance)
    args.fcu_url = px4_sitl.fcu_url(plan.instance)
    if plan.gps_denied:   # first, so the user's own --arg fmu:--param=global_origin=... wins
        args.arg.insert(0, f"fmu:--param=global_origin={px4_sitl.SIH_ORIGIN}")
    return plan


def service_argv(name: str, args, endpoint: str, profile_args: list[str] = (), running: list[str] = ()) -> list[str]:
    """The child's command line: the profile's flags for it first, so --arg/--fcu-url override them.
    `running`: every service started (perception's `sources` are those of them it watches)."""
    argv = [sys.executable, "-m", f"aeroperception.services.{name}", "--connect", endpoint, *profile_args]
    if name == "perception" and running:
        from aeroperception.services.perception.logic import SOURCES

        argv += ["--param", "sources=" + ",".join(s for s in SOURCES if s in running)]
    # GPS-denied, the VIO's age is checked (fmu) against the sim's stamps: every service follows
    # sim/clock even at x1, where a sim that fell behind real time re-anchors and lags the wall clock.
    # Without the sim (vehicle), or with PX4's (the sim follows it: no sim/clock), wall time.
    follows_px4 = px4_sitl.NAME in load_profiles()[args.profile]["services"]
    sim_clock = "sim" in running and not follows_px4
    if (args.speed is not None and args.speed != 1.0) or (getattr(args, "gps_denied", False) and sim_clock):
        argv.append("--sim-time")
    if name == "sim":
        for flag, val in (("--scenario", args.scenario), ("--speed", args.speed), ("--seed", args.seed),
                          ("--sensors", args.sensors)):
            if val is not None:
                argv += [flag, str(val)]
    if name == "recorder" and args.scenario is not None:
        argv += ["--scenario", args.scenario]   # metadata of the recording
    if name == "fmu" and args.fcu_url:
        argv += ["--fcu-url", args.fcu_url]
    if name == "mission" and getattr(args, "mission", None):
        argv.append(f"--param=mission_file={Path(args.mission).resolve()}")
    if getattr(args, "gps_denied", False) and not (name == "sim" and follows_px4):   # PX4's EKF2 estimates
        argv += GPS_DENIED_ARGS.get(name, [])
    for item in args.arg:
        svc, sep, flag = item.partition(":")
        if not sep:
            raise CliError(f"--arg {item!r}: expected SERVICE:FLAG, e.g. planner:--param=kp=1.0")
        if svc == name:
            argv.append(flag)
    return argv


class RouterChild:
    """The Zenoh router as a child process (`aero router`): started before the services, restarted
    at once when it dies; sessions (services, this supervisor's own) reconnect by themselves."""

    BACKOFF_S, MAX_BACKOFF_S = 0.2, 2.0

    def __init__(self, listen: str, log_dir: Path, env: dict[str, str], priority: Priority | None,
                 connect: list[str] = (), thin_links: list[str] = (), thin_link_hz: float | None = None):
        argv = [sys.executable, "-m", "aeroperception.tools.cli", "router", "--listen", listen]
        for ep in connect:
            argv += ["--connect", ep]
        for iface in thin_links:
            argv += ["--thin-link", iface]
        if thin_link_hz is not None:
            argv += ["--thin-link-hz", str(thin_link_hz)]
        self.child = Child("router", argv, log_dir / "router.log", priority=priority or Priority(),
                           backoff_s=self.BACKOFF_S)
        self.pid_path = log_dir / "router.pid"
        self.env = env

    @property
    def proc(self) -> subprocess.Popen | None:
        return self.child.proc

    def start(self, stop: threading.Event, timeout_s: float = 10.0) -> None:
        """Start it and wait until it listens; a router that cannot start is a CliError with its reason."""
        log = self.child.log_path
        offset = log.stat().st_size if log.exists() else 0
        self._start()
        deadline = time.monotonic() + timeout_s
        while not stop.wait(0.05):
            text = log.read_bytes()[offset:].decode(errors="replace") if log.exists() else ""
            if "aero router: zid" in text:
                return
            if self.proc.poll() is not None:
                lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
                why = lines[-1].removeprefix("aero: ") if lines else f"exit code {self.proc.returncode}"
                raise CliError(why)
            if time.monotonic() > deadline:
                self.stop()
                raise CliError(f"the router did not start within {timeout_s:.0f} s (log: {log})")

    def _start(self) -> None:
        self.child.start(self.env)
        tmp = self.pid_path.with_suffix(".tmp")
        tmp.write_text(f"{self.proc.pid}\n")
        os.replace(tmp, self.pid_path)

    def supervise(self, now: float) -> None:
        """Called every loop: notice a dead router and start a new one after a short back-off."""
        c = self.child
        code = c.proc.poll() if c.proc else None
        if c.proc is not None and code is not None:
            c.last_exit, c.proc = code, None
            if now - c.started_at > 30:
                c.backoff_s = self.BACKOFF_S
            c.next_start = now + c.backoff_s
            emit(f"aero up: router exited with code {code}; restarting in {c.backoff_s:.1f} s "
                 f"(log: {c.log_path})")
            c.backoff_s = min(c.backoff_s * 2, self.MAX_BACKOFF_S)
        if c.proc is None and now >= c.next_start:
            c.restarts += 1
            self._start()
            emit(f"aero up: router restarted (pid {c.proc.pid}, {c.sched})")

    def stop(self) -> None:
        shutdown([self.child])
        self.pid_path.unlink(missing_ok=True)


def run(args) -> int:
    names = select_services(args)
    check_installed(args.profile, names)
    if args.thin_link:  # the router would refuse them: say so before anything starts
        thin_link_downsampling(args.thin_link, THIN_LINK_HZ if args.thin_link_hz is None else args.thin_link_hz)
    validate_args(args, names)
    names, unfed = fed_services(names, args.sensors)
    for n, why in unfed.items():
        emit(f"aero up: not starting {n}: {why}")
    px4 = plan_px4(args, names)
    links = resolve_links(args)
    services = [n for n in names if n != px4_sitl.NAME]
    if args.dry_run:
        endpoint = args.listen.replace("0.0.0.0", "127.0.0.1")
        profile_args = load_profiles()[args.profile]["args"]
        joins = f", joining {', '.join(args.connect)}" if args.connect else ""
        emit(f"aero up: profile {args.profile}, router on {args.listen}{joins}, {links} links; would start:")
        if px4:
            env = " ".join(f"{k}={v}" for k, v in px4.env().items())
            emit(f"  {px4_sitl.NAME:<12} {env} " + " ".join(px4_sitl.argv(px4.build, px4.instance, "<log-dir>/px4-XXXX")))
        for n in services:
            emit(f"  {n:<12} " + " ".join(service_argv(n, args, endpoint, [str(a) for a in profile_args.get(n, [])],
                                                         services)))
        return 0
    log_dir = Path(args.log_dir or Path.home() / ".aero" / "logs" / time.strftime("%Y%m%d-%H%M%S"))
    log_dir.mkdir(parents=True, exist_ok=True)
    endpoint = args.listen.replace("0.0.0.0", "127.0.0.1")
    # AERO_SUPERVISOR_PID: every child exits when this process dies (runtime/supervision.py).
    env = dict(os.environ, AERO_CONNECT=endpoint, PYTHONUNBUFFERED="1",
               **{SUPERVISOR_ENV: str(os.getpid()), LINKS_ENV: links})
    vehicle = os.environ.get("AERO_VEHICLE") or "default"
    priorities = load_priorities()
    profile_args = load_profiles()[args.profile]["args"]
    children = {n: Child(n, service_argv(n, args, endpoint, [str(a) for a in profile_args.get(n, [])], services),
                         log_dir / f"{n}.log", priority=priorities.get(n, Priority())) for n in services}
    if px4:   # the flight controller first: fmu finds it booting rather than absent
        children = {px4_sitl.NAME: px4.child(log_dir, priorities.get(px4_sitl.NAME, Priority())), **children}
    lock = threading.Lock()

    stop = ShutdownFlag().install().event
    router = RouterChild(args.listen, log_dir, env, priorities.get("router"), args.connect,
                         args.thin_link, args.thin_link_hz)
    router.start(stop)
    session = open_session(make_config(None, endpoint, mode="client"), stop, max_wait_s=10)
    if session is None:
        router.stop()
        if stop.is_set():
            return 0
        raise CliError(f"cannot connect to the router at {endpoint} (log: {router.child.log_path})")

    def on_token(s: zenoh.Sample) -> None:
        name = str(s.key_expr).rsplit("/", 1)[-1]
        with lock:
            if name in children:
                c = children[name]
                c.token = s.kind == zenoh.SampleKind.PUT
                c.alive = c.token and c.proc is not None  # not another instance's token

    def on_diag(s: zenoh.Sample) -> None:
        try:
            _sid, d = decode_sample(s)
        except Exception:  # noqa: BLE001 - a bad diagnostics payload must not stop supervision
            return
        if isinstance(d, dict):
            with lock:
                c = children.get(str(d.get("name")))
                if c:
                    c.health = d

    subs = [session.liveliness().declare_subscriber(f"{LIVELINESS_ROOT}/{vehicle}/*", on_token, history=True),
            session.declare_subscriber("diagnostics/*", on_diag),
            session.declare_subscriber("*/diagnostics/*", on_diag)]

    emit(f"aero up: profile {args.profile} ({', '.join(names) or 'no services'}), router on {args.listen}, "
         f"{links} links, logs in {log_dir}")
    pids_path = log_dir / "pids.json"
    for c in children.values():
        c.start(env)
    if px4:
        emit(f"aero up: {children[px4_sitl.NAME].health['message']}; log {children[px4_sitl.NAME].log_path}")
    write_pids(pids_path, children.values())
    emit("aero up: scheduling: " + ", ".join(f"{c.name} {c.sched}" for c in [router.child, *children.values()]))

    tty = sys.stdout.isatty()
    last_table = ""
    next_table = 0.0
    while not stop.wait(0.2):
        now = time.monotonic()
        router.supervise(now)
        with lock:
            changed = False
            for c in children.values():
                code = c.proc.poll() if c.proc else 0
                if c.proc is not None and code is not None:
                    c.last_exit, c.proc, c.alive = code, None, False
                    c.last_error = last_error_line(c.log_path)
                    if now - c.started_at > 30:
                        c.backoff_s = 1.0
                    c.next_start = now + c.backoff_s
                    emit(f"aero up: {c.name} exited with code {code}"
                         + (f" ({c.last_error})" if c.last_error else "")
                         + f"; restarting in {c.backoff_s:.0f} s (log: {c.log_path})")
                    c.backoff_s = min(c.backoff_s * 2, 30.0)
                    changed = True
                if c.proc is None and now >= c.next_start and not c.held_elsewhere(now):
                    c.restarts += 1
                    c.start(env)
                    changed = True
                if c.booted:
                    c.hold_token(session, f"{LIVELINESS_ROOT}/{vehicle}/{c.name}")
            if changed:
                write_pids(pids_path, children.values())
            table = format_table(children.values(), None if tty else 240)  # logs: long lines are fine
        if now >= next_table and (tty or table != last_table):
            # A reader that went away (`aero up | head`) must not stop the supervision.
            emit(("\x1b[2J\x1b[H" if tty else "") + table)
            last_table = table
            next_table = now + args.status_interval
    emit("aero up: stopping")
    shutdown(children.values())
    for c in children.values():
        c.drop_token()
    pids_path.unlink(missing_ok=True)
    for s in subs:
        s.undeclare()
    session.close()
    router.stop()
    return 0


# Lines of a faulthandler stack dump (services/runtime/service.py enables it) other than its
# "Fatal Python error: Segmentation fault" headline.
STACK_DUMP_LINES = ("File \"", "Thread 0x", "Current thread 0x", "Stack (most recent", "Extension modules:",
                    "<no Python frame>", "Garbage-collecting", "<unknown>")


def last_error_line(log_path: Path, tail_bytes: int = 16384) -> str:
    """The last error a service wrote before it exited: a JSON log record at level error, or a
    plain line (a traceback's last line, `aero run X: ...`, a native crash's "Fatal Python error: ..."
    above its stack dump). "" when there is none."""
    try:
        with open(log_path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - tail_bytes))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return ""
    for line in reversed(lines[-200:]):
        line = line.strip()
        if not line or line.startswith(STACK_DUMP_LINES):
            continue  # faulthandler's dump (a native crash, or kill -USR1): its headline says what
        try:
            rec = json.loads(line)
        except ValueError:
            return line
        if not isinstance(rec, dict):
            return line
        if rec.get("level") == "error":
            detail = rec.get("error") or rec.get("message") or ", ".join(
                f"{k}={v}" for k, v in rec.items() if k not in ("ts", "service", "level", "event"))
            return f"{rec.get('event', 'error')}: {detail}" if detail else str(rec.get("event", ""))
    return ""


MESSAGE_COL = 13 + 1 + 10 + 1 + 6 + 1 + 8 + 2


def format_table(children, width: int | None = None) -> str:
    """One row per service; the message wraps on word boundaries under its column (at most three
    lines, then "..."), so a URL or a number is never cut."""
    width = width or shutil.get_terminal_size((120, 24)).columns
    msg_width = max(30, width - MESSAGE_COL - 1)
    rows = [f"{'SERVICE':<13} {'STATE':<10} {'HEALTH':<6} {'RESTARTS':>8}  MESSAGE"]
    for c in children:
        lvl = LEVELS.get(c.health.get("level"), "-") if c.alive else "-"
        if c.alive:
            msg = c.health.get("message", "")
        elif c.last_exit is not None:
            msg = f"exit {c.last_exit}" + (f": {c.last_error}" if c.last_error else "")
        else:
            msg = ""
        lines = textwrap.wrap(msg, msg_width, break_long_words=False, break_on_hyphens=False,
                              max_lines=3, placeholder=" ...") or [""]
        rows.append(f"{c.name:<13} {c.status():<10} {lvl:<6} {c.restarts:>8}  {lines[0]}")
        rows += [" " * MESSAGE_COL + line for line in lines[1:]]
    return "\n".join(rows)


def shutdown(children) -> None:
    """Each child's clean-stop signal (SIGTERM; PX4: SIGINT) at once, then SIGTERM / SIGKILL."""
    signals = {c.proc.pid: c.stop_signal for c in children if c.proc is not None}
    terminate([c.proc for c in children if c.proc is not None], timeout_s=3.0, kill_wait_s=1.0,
              first_signal=lambda p: signals.get(p.pid, signal.SIGTERM))
