"""ArduCopter SITL (physics inside the binary) as a process `aero up --profile ardupilot` supervises.

DIR (--ardupilot or AERO_ARDUPILOT_DIR) is one of:
- the relocatable bundle unpacked (`bin/arducopter`, `default_params/copter.parm`), or the folder holding
  it (`ardupilot-sitl-copter/`);
- that bundle as a .tar.gz: unpacked once into a cache dir (~/.cache/aero/ardupilot/<name>-<size>-<mtime>),
  reused by every later `aero up`;
- an ArduPilot checkout after `./waf copter` (`build/sitl/bin/arducopter`,
  `Tools/autotest/default_params/copter.parm`).

Each `aero up` runs it in a fresh work dir under the stack's log dir (it writes eeprom.bin, logs/ and
terrain/ there, so it starts from its default parameters) as instance N (`-I N`: its TCP ports
5760+10N..5763+10N), SERIAL0 sent as UDP to 127.0.0.1:14540+N, where fmu listens
(`--serial0 udpclient:...`: ArduPilot then does not wait for a TCP client). SERIAL1/SERIAL2 stay
ArduPilot's TCP listeners (on all interfaces; nothing here connects to them). Everything that would
only make it fail after the start (a wrong DIR, the instance's ports taken) is refused here, in one line.

Never here: supervision policy (restart, stop) - that is aero up's, the same as for PX4.
"""
from __future__ import annotations

import os
import shutil
import socket
import tarfile
import tempfile
from pathlib import Path

from aeroperception.tools.common import CliError

from . import px4_sitl

NAME = "ardupilot"              # its name in profiles.yaml, pids.json, the status table and logs
DIR_ENV = "AERO_ARDUPILOT_DIR"
CACHE_ENV = "AERO_CACHE_DIR"
MAX_INSTANCE = 9
BUNDLE = "ardupilot-sitl-copter"      # the folder the relocatable tarball unpacks to
# ArduPilot prints this once its parameters are loaded and its serial ports are open
BOOTED = "Loaded defaults from"
# The bundle's home (run-copter-sitl.sh): lat, lon, alt AMSL, heading
HOME = "47.397742,8.545594,488,0"

# (binary, default parameters) relative to DIR: the bundle, and an ArduPilot checkout after ./waf copter
LAYOUTS = (("bin/arducopter", "default_params/copter.parm"),
           ("build/sitl/bin/arducopter", "Tools/autotest/default_params/copter.parm"))


def fmu_port(instance: int) -> int:
    """Where fmu listens and ArduPilot's SERIAL0 sends (the PX4 convention: 14540+N)."""
    return 14540 + instance


def tcp_ports(instance: int) -> tuple[int, ...]:
    """ArduPilot's TCP listeners of instance N: SERIAL0 (unused here, udpclient), SERIAL1, SERIAL2."""
    return tuple(p + 10 * instance for p in (5760, 5762, 5763))


def fcu_url(instance: int) -> str:
    return f"udpin:127.0.0.1:{fmu_port(instance)}"


def cache_dir() -> Path:
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "aero") / "ardupilot"


def _layout(d: Path) -> tuple[Path, Path] | None:
    for binary, params in LAYOUTS:
        b, p = d / binary, d / params
        if b.is_file() and os.access(b, os.X_OK) and p.is_file():
            return b, p
    return None


def unpack(tarball: Path) -> Path:
    """The tarball unpacked once into the cache (atomically: a half-unpacked copy is never used)."""
    st = tarball.stat()
    dest = cache_dir() / f"{tarball.name.split('.')[0]}-{st.st_size}-{int(st.st_mtime)}"
    if dest.is_dir():
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".unpack-", dir=dest.parent))
    try:
        with tarfile.open(tarball) as tf:
            tf.extractall(tmp, filter="tar")
        try:
            tmp.rename(dest)
        except OSError:          # another aero up unpacked it first
            if not dest.is_dir():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def sitl(given: str | None) -> tuple[Path, Path]:
    """(arducopter binary, its default parameters) from --ardupilot or AERO_ARDUPILOT_DIR, checked."""
    raw = given or os.environ.get(DIR_ENV, "")
    if not raw:
        raise CliError(f"--profile ardupilot needs ArduCopter SITL: --ardupilot DIR or {DIR_ENV}=DIR (the "
                       f"{BUNDLE} folder or its .tar.gz, or an ArduPilot checkout after `./waf copter`)")
    d = Path(raw).expanduser().resolve()
    if d.is_file() and tarfile.is_tarfile(d):
        try:
            d = unpack(d)
        except (OSError, tarfile.TarError) as e:
            raise CliError(f"--ardupilot {raw}: cannot unpack into {cache_dir()}: {e}") from None
    elif not d.is_dir():
        raise CliError(f"--ardupilot {raw}: no such directory or .tar.gz (expected ArduCopter SITL: "
                       f"bin/arducopter + default_params/copter.parm)")
    for cand in (d, d / BUNDLE):
        found = _layout(cand)
        if found:
            return found
    raise CliError(f"--ardupilot {raw}: no executable bin/arducopter with default_params/copter.parm (nor "
                   f"build/sitl/bin/arducopter with Tools/autotest/default_params/copter.parm) in {d}")


def _tcp_free(port: int) -> bool:
    """Nobody listens on TCP `port` (ArduPilot's listeners bind all interfaces: asked over loopback)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) != 0


def busy_ports(instance: int) -> list[int]:
    """Ports instance N needs that something else holds: its TCP listeners (all interfaces), fmu's UDP."""
    return [p for p in tcp_ports(instance) if not _tcp_free(p)] + \
        ([fmu_port(instance)] if not px4_sitl.udp_free("127.0.0.1", fmu_port(instance)) else [])


def free_instance(start: int = 0) -> int | None:
    return next((n for n in range(start, MAX_INSTANCE + 1) if not busy_ports(n)), None)


def check_instance(instance: int) -> None:
    """Refuse, in one line naming a way out, an instance out of range or whose ports are taken."""
    if not 0 <= instance <= MAX_INSTANCE:
        raise CliError(f"--ardupilot-instance {instance}: expected 0..{MAX_INSTANCE}")
    busy = busy_ports(instance)
    if busy:
        other = free_instance()
        hint = f"--ardupilot-instance {other}" if other is not None else "another --ardupilot-instance"
        raise CliError(f"ArduPilot instance {instance}: port{'s' if len(busy) > 1 else ''} "
                       f"{', '.join(map(str, busy))} already in use (another ArduPilot, PX4 or fmu?): use {hint}")


def work_dir(log_dir: Path) -> Path:
    """A fresh, empty work dir under the stack's log dir: ArduPilot starts from its default parameters."""
    return Path(tempfile.mkdtemp(prefix="ardupilot-", dir=log_dir))


def argv(binary: Path, params: Path, instance: int) -> list[str]:
    """arducopter (quad, + frame, real time) sending SERIAL0 to fmu; runs in its work dir (cwd). With
    the parent-death signal SIGTERM where setpriv exists, so it stops when `aero up` is killed -9."""
    cmd = [str(binary), "--model", "+", "--speedup", "1", "--defaults", str(params), "-I", str(instance),
           "--home", HOME, "--serial0", f"udpclient:127.0.0.1:{fmu_port(instance)}"]
    setpriv = shutil.which("setpriv")
    return [setpriv, "--pdeathsig", "TERM", "--", *cmd] if setpriv else cmd


def describe(instance: int, workdir: Path | str) -> str:
    return (f"ArduCopter SITL instance {instance}: SERIAL0 -> udp 127.0.0.1:{fmu_port(instance)} (fmu); "
            f"work dir {workdir}")
