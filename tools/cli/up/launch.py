"""`aero up`'s launch plan: which services a profile starts and each one's command line.

What a service gets is data in tools/profiles.yaml: the profile's `args:`, the `options:` of `aero
up` handed to it (--scenario, --fcu-url, --mission, ...) and, with --gps-denied, the `gps_denied:`
flags (a profile's `gps_denied_args:` replace a service's). What is logic stays here: which services
the chosen --sensors feed, perception's `sources` (the services started), --sim-time (who follows
the simulator's clock) and the PX4 SITL a px4 profile starts. Reads and plans; starts nothing.
"""
from __future__ import annotations

import os
import signal
import sys
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import yaml

from aeroperception.services.runtime.supervision import Priority
from aeroperception.tools.common import CliError, emit

from .. import ardupilot_sitl, px4_sitl
from .supervision import Child


def _profiles_yaml() -> dict:
    return yaml.safe_load(resources.files("aeroperception.tools").joinpath("profiles.yaml").read_text())


def _union(base: list, more) -> list:
    return [*base, *(x for x in more or () if x not in base)]


def load_profiles() -> dict[str, dict]:
    """{profile: {"services": [...], "args": {service: [flags]}, "install": [pip extras],
    "gps_denied_args": {service: [flags]}}}; a bare list means services only. `extends: OTHER`
    starts from an earlier profile's services, args, extras and GPS-denied flags and adds its own."""
    raw = _profiles_yaml()
    root = {"services": [], "args": {}, "install": [],
            "gps_denied_args": dict((raw.get("gps_denied") or {}).get("args") or {})}
    out = {}
    for name, spec in raw["profiles"].items():
        spec = {"services": spec} if isinstance(spec, list) else dict(spec)
        base = out[spec["extends"]] if spec.get("extends") else root
        out[name] = {"services": _union(base["services"], spec["services"]),
                     "args": {**base["args"], **dict(spec.get("args") or {})},
                     "install": _union(base["install"], spec.get("install")),
                     "gps_denied_args": {**base["gps_denied_args"], **dict(spec.get("gps_denied_args") or {})}}
    return out


def gps_denied_needs() -> list[str]:
    """The services --gps-denied cannot do without (profiles.yaml `gps_denied: needs:`)."""
    return list((_profiles_yaml().get("gps_denied") or {}).get("needs") or [])


def option_args(name: str, args) -> list[str]:
    """The flags service `name` gets from `aero up`'s options (profiles.yaml `options:`), in the
    order declared; an option not given (None or empty) adds nothing."""
    out: list[str] = []
    for option, flags in ((_profiles_yaml().get("options") or {}).get(name) or {}).items():
        value = getattr(args, option, None)
        if value is None or value == "":
            continue
        path = str(Path(value).resolve()) if isinstance(value, str) else str(value)
        out += [str(f).format(value=value, path=path) for f in flags]
    return out


PRIORITIES_ENV = "AERO_PRIORITIES"  # "off": every process at the default (for A/B benchmarks)


def load_priorities() -> dict[str, Priority]:
    """{process: Priority} from the `priorities:` section of profiles.yaml (unlisted: nice 0);
    empty when AERO_PRIORITIES=off."""
    if os.environ.get(PRIORITIES_ENV, "").lower() in ("off", "0", "no", "false"):
        return {}
    raw = _profiles_yaml().get("priorities") or {}
    try:
        return {str(name): Priority.parse(str(name), spec) for name, spec in raw.items()}
    except ValueError as e:
        raise CliError(f"tools/profiles.yaml: {e}") from None


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



@dataclass(frozen=True)
class Px4Plan:
    """The PX4 SITL a px4 profile starts: checked build dir and a free instance."""

    build: Path
    instance: int
    gps_denied: bool = False    # boot for vision-only navigation (fc_params' gps-denied-sih set)
    name = px4_sitl.NAME

    def env(self) -> dict[str, str]:
        return px4_sitl.boot_env(gps_denied=self.gps_denied)

    def child(self, log_dir: Path, priority: Priority) -> Child:
        workdir = px4_sitl.work_dir(log_dir)
        c = Child(px4_sitl.NAME, px4_sitl.argv(self.build, self.instance, workdir), log_dir / f"{px4_sitl.NAME}.log",
                  priority=priority, extra_env=self.env(), stop_signal=signal.SIGINT,
                  booted=px4_sitl.BOOTED)
        c.health = {"level": 0, "message": px4_sitl.describe(self.instance, workdir)}
        return c

    def dry_run(self) -> str:
        env = " ".join(f"{k}={v}" for k, v in self.env().items())
        return f"{env} " + " ".join(px4_sitl.argv(self.build, self.instance, "<log-dir>/px4-XXXX"))


@dataclass(frozen=True)
class ArduPilotPlan:
    """The ArduCopter SITL an ardupilot profile starts: checked binary and parameters, a free instance."""

    binary: Path
    params: Path
    instance: int
    name = ardupilot_sitl.NAME

    def argv(self) -> list[str]:
        return ardupilot_sitl.argv(self.binary, self.params, self.instance)

    def child(self, log_dir: Path, priority: Priority) -> Child:
        workdir = ardupilot_sitl.work_dir(log_dir)
        c = Child(ardupilot_sitl.NAME, self.argv(), log_dir / f"{ardupilot_sitl.NAME}.log", priority=priority,
                  cwd=workdir, booted=ardupilot_sitl.BOOTED)
        c.health = {"level": 0, "message": ardupilot_sitl.describe(self.instance, workdir)}
        return c

    def dry_run(self) -> str:
        return "(in <log-dir>/ardupilot-XXXX) " + " ".join(self.argv())


def plan_ardupilot(args, names: list[str]) -> ArduPilotPlan | None:
    """With ardupilot in the selection: its SITL and instance checked before anything starts, and fmu
    pointed at it. Without: --ardupilot / --ardupilot-instance are refused, not ignored."""
    given, instance = getattr(args, "ardupilot", None), getattr(args, "ardupilot_instance", None)
    if not _fc_selected(args, names, ardupilot_sitl.NAME, "ArduPilot", given, instance,
                        ardupilot_sitl.fcu_url(instance or 0)):
        return None
    if getattr(args, "gps_denied", False):
        raise CliError("--gps-denied: not yet for --profile ardupilot (EKF3 external navigation is issue 37's "
                       "next step); fly it with GPS")
    binary, params = ardupilot_sitl.sitl(given)
    plan = ArduPilotPlan(binary, params, 0 if instance is None else instance)
    ardupilot_sitl.check_instance(plan.instance)
    args.fcu_url = ardupilot_sitl.fcu_url(plan.instance)
    return plan


def plan_fc(args, names: list[str]) -> Px4Plan | ArduPilotPlan | None:
    """The SITL flight controller the profile starts (PX4 or ArduPilot), None for none."""
    px4 = plan_px4(args, names)
    ardu = plan_ardupilot(args, names)
    return px4 or ardu


def _fc_selected(args, names: list[str], name: str, label: str, given, instance, fcu_url: str) -> bool:
    """Whether SITL `name` (px4 / ardupilot) starts; its --NAME / --NAME-instance refused without it,
    and --fcu-url refused with it (fmu talks to that SITL)."""
    if name not in names:
        if given is not None or instance is not None:
            flag = f"--{name}" if given is not None else f"--{name}-instance"
            raise CliError(f"{flag}: profile {args.profile} starts no {label} (use --profile {name})")
        return False
    if args.fcu_url is not None:
        raise CliError(f"--fcu-url: fmu talks to the {label} this profile starts ({fcu_url}); "
                       "drop --fcu-url, or use --profile vehicle for a flight controller of your own")
    return True


def plan_px4(args, names: list[str]) -> Px4Plan | None:
    """With px4 in the selection: its build and instance checked before anything starts, and fmu
    pointed at it. Without: --px4 / --px4-instance are refused, not ignored."""
    px4_dir, instance = getattr(args, "px4", None), getattr(args, "px4_instance", None)
    if not _fc_selected(args, names, px4_sitl.NAME, "PX4", px4_dir, instance, px4_sitl.fcu_url(instance or 0)):
        return None
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
    profile = load_profiles()[args.profile]
    follows_px4 = px4_sitl.NAME in profile["services"] or ardupilot_sitl.NAME in profile["services"]
    sim_clock = "sim" in running and not follows_px4
    if (args.speed is not None and args.speed != 1.0) or (getattr(args, "gps_denied", False) and sim_clock):
        argv.append("--sim-time")
    argv += option_args(name, args)
    if getattr(args, "gps_denied", False):
        argv += [str(a) for a in profile["gps_denied_args"].get(name, [])]
    for item in args.arg:
        svc, sep, flag = item.partition(":")
        if not sep:
            raise CliError(f"--arg {item!r}: expected SERVICE:FLAG, e.g. planner:--param=kp=1.0")
        if svc == name:
            argv.append(flag)
    return argv


@dataclass
class LaunchPlan:
    """What `aero up` starts: the SITL flight controller (px4 / ardupilot profile) and each service's
    command line."""

    profile: str
    names: list[str]                # every process, the SITL included
    fc: Px4Plan | ArduPilotPlan | None
    links: str                      # direct | router
    endpoint: str                   # where the children connect (the router, on this host)
    argv: dict[str, list[str]]      # {service: command line}, in start order

    @property
    def services(self) -> list[str]:
        return list(self.argv)


def launch_plan(args, names: list[str], fc: Px4Plan | ArduPilotPlan | None, links: str,
                sensor_args: dict[str, list[str]] | None = None) -> LaunchPlan:
    """Each service's command line; the profile's flags for it first, then the sensors file's
    (service_argv)."""
    endpoint = args.listen.replace("0.0.0.0", "127.0.0.1")
    profile_args = load_profiles()[args.profile]["args"]
    sensor_args = sensor_args or {}
    services = [n for n in names if n not in (px4_sitl.NAME, ardupilot_sitl.NAME)]
    argv = {n: service_argv(n, args, endpoint, [str(a) for a in [*profile_args.get(n, []), *sensor_args.get(n, [])]],
                            services) for n in services}
    return LaunchPlan(args.profile, names, fc, links, endpoint, argv)


def print_plan(args, plan: LaunchPlan) -> None:
    """`aero up --dry-run`: what would start, one command line per process."""
    joins = f", joining {', '.join(args.connect)}" if args.connect else ""
    emit(f"aero up: profile {args.profile}, router on {args.listen}{joins}, {plan.links} links; would start:")
    if plan.fc:
        emit(f"  {plan.fc.name:<12} {plan.fc.dry_run()}")
    for n, argv in plan.argv.items():
        emit(f"  {n:<12} " + " ".join(argv))
