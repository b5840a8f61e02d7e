"""PX4 SITL (the SIH quadrotor, physics inside PX4) as a process `aero up --profile px4` supervises.

A PX4 build directory (what `make px4_sitl` leaves in build/px4_sitl_default, or the bundle in
../shared/px4) holds `bin/px4` and `etc/`. Each `aero up` runs it in a fresh work dir (default
parameters, its own dataman and ULog files) under the stack's log dir, as instance N: PX4's
onboard link binds UDP 14580+N and sends to 14540+N (where fmu listens), its GCS link binds
18570+N and sends to 14550; its shell commands (`bin/px4-commander`, `bin/px4-param`, ...) reach
it through /tmp/px4-sock-N, and it holds /tmp/px4_lock-N. Everything that would only make PX4 or
fmu fail after the start (a wrong directory, the instance already running, a port taken) is
refused here, in one line, before anything starts.

BOOT_PARAMS are what a companion-flown PX4 needs without RC and without a ground station; they
are set at boot (PX4_PARAM_<NAME>=<value>, applied by PX4's rcS after the airframe's defaults);
`aero up --gps-denied` adds fc_params' GPS-denied set (SIH's GPS without satellites, EKF2 on vision).

Never here: supervision policy (restart, stop) - that is aero up's, the same as for a service.
"""
from __future__ import annotations

import fcntl
import os
import shutil
import socket
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

from . import fc_params
from aeroperception.tools.common import CliError

NAME = "px4"                    # its name in profiles.yaml, pids.json, the status table and logs
DIR_ENV = "AERO_PX4_DIR"
AIRFRAME_ENV = {"PX4_SYS_AUTOSTART": "10040", "PX4_SIM_MODEL": "sihsim_quadx", "PX4_SIMULATOR": "sihsim"}
MAX_INSTANCE = 9                # above 9 PX4 sends every instance's onboard link to 14549
BOOTED = "Startup script returned successfully"    # PX4's log line once its MAVLink links are up
BOOT_FAILED = "Startup script returned with return value"

# {parameter: (value, why)}: set at every boot. docs/px4.md's boot table lists the same.
BOOT_PARAMS: dict[str, tuple[str, str]] = {
    "COM_RC_IN_MODE": ("4", "stick input disabled: there is no RC or joystick, so PX4 neither waits for "
                            "manual control nor fails safe on its absence (the stack flies it)"),
    "COM_RCL_EXCEPT": ("4", "OFFBOARD is exempt from the RC-loss failsafe (a vehicle that has RC and loses it "
                            "keeps following the companion)"),
    "NAV_DLL_ACT": ("0", "no PX4 failsafe on ground-station loss: the stack has no GCS of PX4's own; the "
                         "mission's ground-link policy decides (gcs/link)"),
    "COM_OBL_RC_ACT": ("3", "offboard loss -> Return (Land, then Descend, when it cannot): the default 0 (Position) "
                            "is a mode for a pilot's sticks; without a position estimate it falls back to Altitude "
                            "mode, where nobody holds the sticks (GPS lost on SIH: an unsteered descent, drifting "
                            "sideways, touching down at up to 1.5 m/s). With a position the failsafe is RTL either "
                            "way (no RC: PX4 turns Position into its RC-loss action, NAV_RCL_ACT Return)"),
}

# SIH's simulated IMU is far noisier than EKF2's defaults assume: measured in flight, per 4 ms sample,
# accelerometer 0.34 / 1.16 / 0.95 m/s² and gyro 0.10 / 0.05 / 0.02 rad/s (x / y / z) against EKF2's 0.35
# and 0.015. EKF2 then trusts its IMU prediction over SIH's GPS velocity (within 0.06 m/s of the truth):
# its velocity wandered 0.25-0.39 m/s RMS off the truth for seconds at a time (innovations 0.31 m/s RMS),
# which PX4's velocity loop flies and its position loop trails by velocity error / MPC_XY_P: figure8 at
# 3 m/s, 0.23-0.48 m cross-track by truth. With the noise matched (at EKF2's maxima): 0.12-0.14 m/s and
# 0.10-0.17 m (gyro 0.06: 0.13-0.21 m/s, 0.10-0.26 m). SIH only, with GPS: a real vehicle's EKF2 is tuned
# to its own IMU, and the GPS-denied set (vision) was measured without it.
SIH_EKF_PARAMS: dict[str, tuple[str, str]] = {
    "EKF2_ACC_NOISE": ("1.0", "m/s²; SIH's accelerometer noise (0.34-1.16 per sample; EKF2's maximum)"),
    "EKF2_GYR_NOISE": ("0.1", "rad/s; SIH's gyro noise (0.02-0.10 per sample; EKF2's maximum)"),
}

# Where SIH's world is (SIH_LOC_LAT0 / SIH_LOC_LON0 defaults; SIH_LOC_H0 0 in fc_params' SIH set):
# GPS-denied, fmu gives PX4 this as its local origin (fmu global_origin), so PX4's global position is
# SIH's own.
SIH_ORIGIN = "47.397742,8.545594,0"


@dataclass(frozen=True)
class Ports:
    """UDP ports of instance N (PX4's rcS and px4-rc.mavlink)."""

    instance: int

    @property
    def fmu(self) -> int:           # onboard link's remote: the companion (fmu) listens here
        return 14540 + self.instance

    @property
    def onboard(self) -> int:       # onboard link's local port
        return 14580 + self.instance

    @property
    def sih_display(self) -> int:   # SIH's display link sends its ground truth here (a test may listen)
        return 19410 + self.instance

    @property
    def bound_by_px4(self) -> tuple[int, ...]:
        """GCS link 18570+N, onboard 14580+N, payload 14280+N, gimbal 13030+N, SIH display 19450+N."""
        n = self.instance
        return (18570 + n, 14580 + n, 14280 + n, 13030 + n, 19450 + n)


def fcu_url(instance: int) -> str:
    return f"udpin:127.0.0.1:{Ports(instance).fmu}"


def build_dir(given: str | None) -> Path:
    """The PX4 build directory from --px4 or AERO_PX4_DIR, checked: bin/px4 executable, etc/ with rcS."""
    raw = given or os.environ.get(DIR_ENV, "")
    if not raw:
        raise CliError(f"--profile px4 needs a PX4 build: --px4 DIR or {DIR_ENV}=DIR (a directory holding "
                       "bin/px4 and etc/, e.g. PX4-Autopilot/build/px4_sitl_default after `make px4_sitl`)")
    d = Path(raw).expanduser().resolve()
    px4, rcs = d / "bin" / "px4", d / "etc" / "init.d-posix" / "rcS"
    if not d.is_dir():
        raise CliError(f"--px4 {raw}: no such directory (expected a PX4 build holding bin/px4 and etc/)")
    if not (px4.is_file() and os.access(px4, os.X_OK)):
        raise CliError(f"--px4 {raw}: no executable bin/px4 in {d} (point it at PX4-Autopilot/build/px4_sitl_default)")
    if not rcs.is_file():
        raise CliError(f"--px4 {raw}: no etc/init.d-posix/rcS in {d} (not a PX4 SITL build)")
    return d


def lock_path(instance: int) -> Path:
    return Path(f"/tmp/px4_lock-{instance}")


def lock_holder(instance: int) -> int | None:
    """The pid of the PX4 holding /tmp/px4_lock-N (PX4 takes a POSIX write lock on it), None if free.
    Asked with F_GETLK, which takes no lock itself (a PX4 starting at that moment is not disturbed)."""
    try:
        fd = os.open(lock_path(instance), os.O_RDONLY)
    except OSError:
        return None             # no file: nobody holds it
    try:
        query = struct.pack(_FLOCK, fcntl.F_WRLCK, os.SEEK_SET, 0, 0, 0)
        l_type, _whence, _start, _len, pid = struct.unpack(_FLOCK, fcntl.fcntl(fd, fcntl.F_GETLK, query))
    finally:
        os.close(fd)
    return None if l_type == fcntl.F_UNLCK else pid


_FLOCK = "hhqqi4x"              # struct flock on 64-bit Linux: type, whence, start, len, pid


def udp_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind((host, port))
            return True
        except OSError:
            return False


def busy_ports(instance: int) -> list[int]:
    """Ports instance N needs that something else holds (PX4 binds 0.0.0.0; fmu 127.0.0.1)."""
    p = Ports(instance)
    return [port for port in p.bound_by_px4 if not udp_free("0.0.0.0", port)] + \
        ([p.fmu] if not udp_free("127.0.0.1", p.fmu) else [])


def instance_free(instance: int) -> bool:
    return lock_holder(instance) is None and not busy_ports(instance)


def free_instance(start: int = 0) -> int | None:
    """The first instance from `start` whose lock and ports are free, nobody listening to its SIH
    display link either (a test about to start it: None when all of 0..9 are taken)."""
    return next((n for n in range(start, MAX_INSTANCE + 1)
                 if instance_free(n) and udp_free("127.0.0.1", Ports(n).sih_display)), None)


def check_instance(instance: int) -> None:
    """Refuse, in one line naming a way out, an instance that is running or whose ports are taken."""
    if not 0 <= instance <= MAX_INSTANCE:
        raise CliError(f"--px4-instance {instance}: expected 0..{MAX_INSTANCE}")
    other = free_instance()
    hint = f"--px4-instance {other}" if other is not None else f"another --px4-instance (0..{MAX_INSTANCE} are all taken)"
    pid = lock_holder(instance)
    if pid is not None:
        raise CliError(f"PX4 instance {instance} is already running (pid {pid} holds {lock_path(instance)}): "
                       f"stop it, or start this one as another instance with {hint}")
    busy = busy_ports(instance)
    if busy:
        raise CliError(f"PX4 instance {instance}: UDP port{'s' if len(busy) > 1 else ''} "
                       f"{', '.join(map(str, busy))} already in use (another PX4, sim or fmu?): use {hint}")


def work_dir(log_dir: Path) -> Path:
    """A fresh, empty work dir under the stack's log dir: PX4 starts from its default parameters."""
    return Path(tempfile.mkdtemp(prefix="px4-", dir=log_dir))


def argv(build: Path, instance: int, workdir: Path | str) -> list[str]:
    """`bin/px4 -d` (no interactive shell) with the parent-death signal SIGINT where setpriv exists,
    so a PX4 whose `aero up` was killed -9 still stops cleanly."""
    cmd = [str(build / "bin" / "px4"), "-d", "-i", str(instance), "-w", str(workdir), str(build / "etc")]
    setpriv = shutil.which("setpriv")
    return [setpriv, "--pdeathsig", "INT", "--", *cmd] if setpriv else cmd


def boot_env(environ: dict[str, str] | None = None, gps_denied: bool = False) -> dict[str, str]:
    """The airframe and BOOT_PARAMS as environment, plus with `gps_denied` the vision-only navigation
    set (fc_params.SETS["gps-denied-sih"]: GPS off in SIH, EKF2 on external vision), else SIH_EKF_PARAMS
    (EKF2's IMU noise matched to SIH's); PX4_PARAM_* the
    user exported win (their values are what PX4 gets, shown by --dry-run)."""
    environ = os.environ if environ is None else environ
    wanted = {f"PX4_PARAM_{name}": value
              for name, (value, _why) in (BOOT_PARAMS | ({} if gps_denied else SIH_EKF_PARAMS)).items()}
    if gps_denied:
        wanted |= fc_params.boot_env(fc_params.SETS["gps-denied-sih"])
    return dict(AIRFRAME_ENV) | {k: environ.get(k, v) for k, v in wanted.items()}


def describe(instance: int, workdir: Path | str) -> str:
    p = Ports(instance)
    return (f"PX4 SITL instance {instance}: MAVLink 127.0.0.1:{p.onboard} -> {p.fmu} (fmu), GCS link -> 14550; "
            f"work dir {workdir}")
