"""`aero doctor [--profile NAME]`: can this machine run the profile? One line per check:
status (ok / warn / FAIL), what was checked, and what to do about it.

Why: what stops a stack on a new machine is the machine, not the code: a missing extra (a service
crash-loops on ModuleNotFoundError), a port another process holds (the router or a MAVLink link
cannot bind), no PX4 build, a clock that is off. Each was found by a user reading a service log
after `aero up`; here each is one line before it, with the command that fixes it.

FAIL is only what stops the chosen profile (its services' modules, its ports, PX4 for the px4
profile): exit code 1. The rest (Docker, GPU, NTP, a PX4 build for other profiles) is warn or ok:
exit code 0. Every check is a plain function returning a Check, bounded in time (subprocesses
with a timeout, a Zenoh probe of at most 2 s only when something listens on the router's port).
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from aeroperception.services.runtime.params import parse_overrides
from aeroperception.tools import service_imports
from aeroperception.tools.common import CliError, emit

from . import px4_sitl
from . import up as cmd_up

OK, WARN, FAIL = "ok", "warn", "FAIL"
ENDPOINT_RE = re.compile(r"^(tcp|udp)/([^:/]+|\[[^\]]+\]):(\d{1,5})$")
PLAUSIBLE_AFTER = time.mktime((2025, 1, 1, 0, 0, 0, 0, 0, -1))   # before this the clock was never set
PLAUSIBLE_BEFORE = time.mktime((2100, 1, 1, 0, 0, 0, 0, 0, -1))


@dataclass(frozen=True)
class Check:
    status: str         # OK, WARN or FAIL
    what: str
    todo: str = ""      # what to do (empty: nothing)

    def line(self) -> str:
        return f"{self.status:<4}  {self.what}" + (f" -> {self.todo}" if self.todo else "")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("doctor", help="check this machine can run a profile: imports, ports, router, clock, "
                                      "PX4, Docker, GPU; one line each with what to do")
    p.add_argument("--profile", default=cmd_up.DEFAULT_PROFILE,
                   help=f"profile from tools/profiles.yaml (default {cmd_up.DEFAULT_PROFILE})")
    p.add_argument("--listen", default=cmd_up.DEFAULT_LISTEN,
                   help=f"the router endpoint aero up would listen on (default {cmd_up.DEFAULT_LISTEN})")
    p.add_argument("--px4", default=None, metavar="DIR",
                   help=f"PX4 build to check (default ${px4_sitl.DIR_ENV}, else ../shared/px4 beside the repository)")
    p.add_argument("--port", action="append", default=[], metavar="PROTO:PORT",
                   help="check these ports instead of the profile's, e.g. udp:14541 (repeatable)")
    p.set_defaults(func=run)


# ---------------------------------------------------------------- imports


def check_service(service: str, install: str) -> Check:
    """The third-party modules `service`'s code imports are all findable (find_spec: nothing imported)."""
    needed = sorted(service_imports.service_modules(service))
    missing = service_imports.missing_modules(needed)
    if missing:
        return Check(FAIL, f"{service}: not installed: {', '.join(missing)}", install)
    optional = service_imports.optional_modules(service)
    lacking = service_imports.missing_modules(optional)
    if lacking:
        return Check(WARN, f"{service}: imports found ({', '.join(needed)}) but not the optional "
                           f"{', '.join(lacking)}: {'; '.join(optional[m] for m in lacking)}", install)
    return Check(OK, f"{service}: imports found ({', '.join(needed) or 'none'})")


def check_onnx(gpu: bool) -> Check:
    """onnxruntime's execution providers (the detector takes the first of TensorRT, CUDA, CPU)."""
    try:
        import onnxruntime as ort
    except Exception as e:  # noqa: BLE001 - a broken install raises more than ImportError
        return Check(WARN, f"onnxruntime: cannot import ({type(e).__name__}: {e})",
                     "the detector needs it: install the perception extra")
    have = set(ort.get_available_providers())
    names = {"CPU": "CPUExecutionProvider", "CUDA": "CUDAExecutionProvider", "TensorRT": "TensorrtExecutionProvider"}
    listed = ", ".join(f"{k} {'yes' if v in have else 'no'}" for k, v in names.items())
    what = f"onnxruntime {ort.__version__} providers: {listed}"
    if names["CPU"] not in have:
        return Check(WARN, what, "no CPU provider: reinstall onnxruntime")
    if gpu and names["CUDA"] not in have:
        return Check(WARN, what, "a GPU is here but the detector will run on the CPU: pip install onnxruntime-gpu")
    return Check(OK, what)


def gpu_names(timeout_s: float = 5.0) -> list[str]:
    """NVIDIA GPUs `nvidia-smi -L` lists ([] without the tool or a driver)."""
    if not shutil.which("nvidia-smi"):
        return []
    r = _run(["nvidia-smi", "-L"], timeout_s)
    return [ln.strip() for ln in r.stdout.splitlines() if ln.strip().startswith("GPU")] if r and r.returncode == 0 else []


def check_gpu(gpus: list[str]) -> Check:
    if gpus:
        return Check(OK, f"GPU: {'; '.join(gpus)}")
    return Check(OK, "GPU: none found (nvidia-smi): the detector runs on the CPU")


# ---------------------------------------------------------------- ports


@dataclass(frozen=True)
class PortUse:
    """A port the profile binds (must be free), or a peer's port it sends to (`bind` False: informational)."""

    proto: str          # "tcp" or "udp"
    host: str
    port: int
    who: str
    bind: bool = True


def _flag_params(flags) -> dict[str, str]:
    """--param overrides among a profile's flags for one service (`--param k=v` or `--param=k=v`)."""
    items, flags = [], [str(f) for f in flags]
    for i, f in enumerate(flags):
        if f == "--param" and i + 1 < len(flags):
            items.append(flags[i + 1])
        elif f.startswith("--param="):
            items.append(f.removeprefix("--param="))
    return parse_overrides(items)


def _param_default(params, name: str):
    return next(p.default for p in params if p.name == name)


def parse_endpoint(endpoint: str) -> tuple[str, str, int]:
    m = ENDPOINT_RE.match(endpoint)
    if not m:
        raise CliError(f"--listen {endpoint!r}: expected tcp/HOST:PORT, e.g. {cmd_up.DEFAULT_LISTEN}")
    return m.group(1), m.group(2).strip("[]"), int(m.group(3))


def profile_ports(profile: str, listen: str = cmd_up.DEFAULT_LISTEN) -> list[PortUse]:
    """The ports `aero up --profile PROFILE` binds, from where its processes take them: the router's
    --listen, fmu's default --fcu-url, the sim's MAVLink bind, PX4 instance 0's, gcs and viz params
    (their contracts' defaults, the profile's --param overrides applied); plus the ground station's."""
    from aeroperception.services.fmu.contract import DEFAULT_FCU_URL
    from aeroperception.services.gcs import contract as gcs
    from aeroperception.services.sim.vehicle.endpoint import PX4_SITL_BIND

    spec = cmd_up.load_profiles()[profile]
    services, flags = spec["services"], spec["args"]
    proto, host, port = parse_endpoint(listen)
    out = [PortUse(proto, host, port, "the router (aero up --listen)")]
    if px4_sitl.NAME in services:
        ports = px4_sitl.Ports(0)
        out += [PortUse("udp", "0.0.0.0", p, "PX4 SITL instance 0") for p in ports.bound_by_px4]
        fcu = px4_sitl.fcu_url(0)
    else:
        fcu = DEFAULT_FCU_URL
        if "sim" in services:
            out.append(PortUse("udp", *PX4_SITL_BIND, "sim MAVLink (PX4 SITL's onboard port)"))
    if "fmu" in services:
        _kind, fhost, fport = fcu.split(":")
        out.append(PortUse("udp", fhost, int(fport), "fmu <- flight controller"))
    if "gcs" in services:
        p = {**{k: _param_default(gcs.PARAMS, k) for k in ("bind_ip", "local_port", "gcs_ip", "remote_port")},
             **_flag_params(flags.get("gcs", []))}
        if int(p["local_port"]):
            out.append(PortUse("udp", str(p["bind_ip"]), int(p["local_port"]), "gcs MAVLink"))
        out.append(PortUse("udp", str(p["gcs_ip"]), int(p["remote_port"]), "ground station (gcs sends here)", bind=False))
    if "viz" in services:
        from aeroperception.services.viz import contract as viz

        p = {**{k: _param_default(viz.PARAMS, k) for k in ("bind_ip", "web_port", "grpc_port")},
             **_flag_params(flags.get("viz", []))}
        out += [PortUse("tcp", str(p["bind_ip"]), int(p[k]), f"viz {k}") for k in ("web_port", "grpc_port") if int(p[k])]
    return out


def parse_port(text: str) -> PortUse:
    proto, sep, port = text.partition(":")
    if proto not in ("tcp", "udp") or not sep or not port.isdigit() or not 0 < int(port) < 65536:
        raise CliError(f"--port {text!r}: expected tcp:PORT or udp:PORT, e.g. udp:14540")
    return PortUse(proto, "127.0.0.1", int(port), "given with --port")


def port_free(use: PortUse) -> bool:
    """Whether the port can be bound now, as its user binds it (TCP: SO_REUSEADDR, like a listener)."""
    kind = socket.SOCK_STREAM if use.proto == "tcp" else socket.SOCK_DGRAM
    with socket.socket(socket.AF_INET6 if ":" in use.host else socket.AF_INET, kind) as s:
        if kind == socket.SOCK_STREAM:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((use.host, use.port))
            return True
        except OSError:
            return False


def check_port(use: PortUse) -> Check:
    where = f"port {use.proto} {use.host}:{use.port}, {use.who}"
    free = port_free(use)
    if not use.bind:
        return Check(OK, f"{where}: " + ("free: no ground station listening on this host" if free
                                         else "a ground station listens (QGroundControl?)"))
    if free:
        return Check(OK, f"{where}: free")
    return Check(FAIL, f"{where}: in use", f"stop what holds it (`ss -{use.proto[0]}lnp | grep :{use.port}` "
                                          "shows it: another aero up, PX4 or ground station?)")


def check_router(endpoint: str, probe_s: float = 2.0) -> Check:
    """Informational: is a Zenoh router already answering at `endpoint` (a stack running here)?"""
    proto, host, port = parse_endpoint(endpoint)
    target = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    try:
        with socket.create_connection((target, port), timeout=1.0):
            pass
    except OSError:
        return Check(OK, f"router: none at {endpoint} (aero up starts one)")
    from aeroperception.services.runtime.node import LIVELINESS_ROOT
    from aeroperception.services.runtime.session import make_config, open_session

    url = f"{proto}/{target}:{port}"
    conf = make_config(None, url, mode="client")
    # A listener that never answers Zenoh's handshake would hold zenoh.open for its 10 s default.
    conf.insert_json5("transport/unicast/open_timeout", str(int(probe_s * 1000)))
    session = open_session(conf, max_wait_s=probe_s)
    if session is None:
        return Check(WARN, f"router: something listens at {url} but no Zenoh router answers",
                     "see what holds the port (ss -tlnp)")
    try:
        n = sum(1 for _ in session.liveliness().get(f"{LIVELINESS_ROOT}/**", timeout=1.0))
    except Exception:  # noqa: BLE001 - informational only
        n = 0
    finally:
        session.close()
    return Check(OK, f"router: a Zenoh router answers at {url}, {n} service(s) alive (a stack is running: "
                     "aero node list)")


# ---------------------------------------------------------------- clock


def _run(argv: list[str], timeout_s: float) -> subprocess.CompletedProcess | None:
    try:
        return subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired):
        return None


def ntp_synchronised(timeout_s: float = 3.0) -> tuple[bool | None, str]:
    """(synchronised, by what): timedatectl's NTPSynchronized, else chrony's leap status;
    (None, why) when neither answers (no systemd in a container, no chrony)."""
    if shutil.which("timedatectl"):
        r = _run(["timedatectl", "show", "-p", "NTPSynchronized", "--value"], timeout_s)
        if r and r.returncode == 0 and r.stdout.strip() in ("yes", "no"):
            return r.stdout.strip() == "yes", "timedatectl"
    if shutil.which("chronyc"):
        r = _run(["chronyc", "-n", "tracking"], timeout_s)
        m = re.search(r"^Leap status\s*:\s*(.+)$", r.stdout if r and r.returncode == 0 else "", re.M)
        if m:
            return m.group(1).strip() == "Normal", "chronyc"
    return None, "neither timedatectl nor chronyc answered"


def check_clock(now_s: float | None = None, ntp: tuple[bool | None, str] | None = None) -> list[Check]:
    """Monotonic time advances (every rate loop and timeout rests on it); system time is plausible
    (log and recording stamps, TLS certificates); NTP keeps hosts' stamps comparable."""
    out = []
    t0 = time.monotonic()
    time.sleep(0.01)
    dt = time.monotonic() - t0
    res = time.get_clock_info("monotonic").resolution
    out.append(Check(OK, f"clock: monotonic advances ({dt * 1e3:.1f} ms over a 10 ms sleep, resolution {res:g} s)")
               if 0.005 < dt < 1.0 else Check(FAIL, f"clock: monotonic advanced {dt:.3f} s over a 10 ms sleep",
                                              "the host's clocksource is broken: check dmesg"))
    now_s = time.time() if now_s is None else now_s
    stamp = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(now_s))
    out.append(Check(OK, f"clock: system time {stamp}") if PLAUSIBLE_AFTER < now_s < PLAUSIBLE_BEFORE
               else Check(WARN, f"clock: system time {stamp} is implausible",
                          "set it (timedatectl set-ntp true, or date -s): logs, recordings and TLS use it"))
    synced, how = ntp_synchronised() if ntp is None else ntp
    if synced is None:
        out.append(Check(WARN, f"clock: NTP state unknown ({how})",
                         "several hosts' stamps agree only if each is synchronised (chrony or systemd-timesyncd)"))
    elif synced:
        out.append(Check(OK, f"clock: NTP synchronised ({how})"))
    else:
        out.append(Check(WARN, f"clock: NTP not synchronised ({how})", "timedatectl set-ntp true (or start chrony)"))
    return out


# ---------------------------------------------------------------- PX4, Docker


def shared_px4_dir() -> Path | None:
    """../shared/px4 beside the repository (a checkout only): where the tests' PX4 bundle lives."""
    root = service_imports.repo_root()
    return root.parent / "shared" / "px4" if root else None


def check_px4(given: str | None, required: bool) -> Check:
    """A PX4 SITL build: --px4, else $AERO_PX4_DIR, else ../shared/px4; checked as aero up checks it
    (px4_sitl.build_dir). Absent: FAIL for a profile that starts PX4, warn for the others."""
    bad = FAIL if required else WARN
    raw = given or os.environ.get(px4_sitl.DIR_ENV, "")
    if not raw:
        shared = shared_px4_dir()
        if shared is None or not (shared / "bin" / "px4").exists():
            bundle = next(iter(sorted(shared.glob("*.tar.gz"))), None) if shared and shared.is_dir() else None
            todo = (f"extract it: mkdir -p DIR && tar -xzf {bundle} -C DIR; then {px4_sitl.DIR_ENV}=DIR or --px4 DIR"
                    if bundle else f"build PX4 (make px4_sitl) and set {px4_sitl.DIR_ENV}=PX4-Autopilot/build/px4_sitl_default")
            where = f"; {shared} holds only {bundle.name}" if bundle else ""
            return Check(bad, f"PX4: no SITL build given (--px4 or ${px4_sitl.DIR_ENV}) or found{where}", todo)
        raw = str(shared)
    try:
        d = px4_sitl.build_dir(raw)
    except CliError as e:
        return Check(bad, f"PX4: {e}", f"point --px4 or {px4_sitl.DIR_ENV} at a PX4 SITL build")
    return Check(OK, f"PX4: SITL build at {d} (bin/px4)")


def check_docker(timeout_s: float = 10.0) -> Check:
    """Docker is only for deploy/docker-local.sh and the compose test: never more than warn."""
    if not shutil.which("docker"):
        return Check(WARN, "Docker: no docker CLI", "only deploy/docker-local.sh needs it (apt-get install docker.io)")
    r = _run(["docker", "info", "--format", "{{.ServerVersion}}"], timeout_s)
    if r is None or r.returncode != 0:
        why = (r.stderr.strip().splitlines() or ["no answer"])[-1] if r else f"no answer within {timeout_s:.0f} s"
        return Check(WARN, f"Docker: CLI present, engine not reachable ({why[:120]})",
                     "start dockerd, or add yourself to the docker group")
    return Check(OK, f"Docker: engine {r.stdout.strip()}")


# ---------------------------------------------------------------- the whole report


def checks(profile: str, listen: str = cmd_up.DEFAULT_LISTEN, px4: str | None = None,
           ports: list[PortUse] | None = None) -> list[Check]:
    services = cmd_up.select_services(argparse.Namespace(profile=profile, only="", exclude=""))
    install = service_imports.install_command(cmd_up.load_profiles()[profile]["install"])
    out = [check_service(s, install) for s in services if s != px4_sitl.NAME]
    out += [check_port(u) for u in (profile_ports(profile, listen) if ports is None else ports)]
    out.append(check_router(listen))
    out += check_clock()
    out.append(check_px4(px4, required=px4_sitl.NAME in services))
    out.append(check_docker())
    gpus = gpu_names()
    out += [check_gpu(gpus), check_onnx(bool(gpus))]
    return out


def run(args) -> int:
    ports = [parse_port(p) for p in args.port] or None
    found = checks(args.profile, args.listen, args.px4, ports)
    for c in found:
        emit(c.line())
    count = {s: sum(c.status == s for c in found) for s in (FAIL, WARN, OK)}
    emit(f"aero doctor: profile {args.profile}: {count[FAIL]} FAIL, {count[WARN]} warn, {count[OK]} ok "
         f"(python {sys.version.split()[0]} at {sys.executable})")
    return 1 if count[FAIL] else 0
