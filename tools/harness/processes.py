"""Processes a harness starts and stops: free loopback ports, the `aero` command, a clean
environment, and stopping an `aero up` with every child it left, by pid (never by name)."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import zenoh


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that was free a moment ago (TCP by default, SOCK_DGRAM for UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago (MAVLink links of a test stack)."""
    return free_port(socket.SOCK_DGRAM)


def is_service_process(pid: int, name: str) -> bool:
    """Whether `pid` is (still) the process of service `name` (guards against reused pids)."""
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return f"aeroperception.services.{name}".encode() in cmd


def clean_env(endpoint: str | None = None) -> dict[str, str]:
    """This environment without AERO_* settings a developer may have exported (AERO_CONNECT=endpoint
    when given), unbuffered Python output."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AERO_")}
    env["PYTHONUNBUFFERED"] = "1"
    if endpoint:
        env["AERO_CONNECT"] = endpoint
    return env


def aero_argv() -> list[str]:
    """How to start the `aero` command: the installed script next to this interpreter, else -m."""
    script = Path(sys.executable).parent / "aero"
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-m", "aeroperception.tools.cli"]


def aero(*args: str, endpoint: str | None = None, timeout_s: float = 30.0,
         cwd: str | Path | None = None) -> subprocess.CompletedProcess:
    """Run `aero ARGS` to completion (AERO_CONNECT=endpoint when given) and capture its output."""
    return subprocess.run(aero_argv() + [str(a) for a in args], env=clean_env(endpoint),
                          cwd=cwd, capture_output=True, text=True, timeout=timeout_s,
                          stdin=subprocess.DEVNULL)


def interrupt(proc: subprocess.Popen, timeout_s: float = 10.0) -> int | None:
    """SIGINT (what Ctrl-C sends) and wait for the exit code; killed after timeout_s -> None."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
            return None
    return proc.returncode


def stop_up(session: zenoh.Session | None, proc: subprocess.Popen | None, children: dict[str, int],
            timeout_s: float = 8.0) -> int | None:
    """Stop an `aero up`: close our session, SIGINT it (it stops its children), kill it if it
    hangs, then SIGKILL any child it left behind (by the pid it recorded; SIGCONT first, in case
    a fault left it stopped). Returns aero up's exit code."""
    if session is not None:
        try:
            session.close()
        except Exception:  # noqa: BLE001 - the router may be gone
            pass
    if proc is not None and proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)
    for name, pid in children.items():
        if is_service_process(pid, name):
            try:
                os.kill(pid, signal.SIGCONT)
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    return proc.returncode if proc is not None else None


def profile_services(profile: str = "sim") -> list[str]:
    """The services `aero up --profile PROFILE` starts (profiles.yaml)."""
    from aeroperception.tools.cli.up import load_profiles

    return list(load_profiles()[profile]["services"])


_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def proc_stats(pid: int) -> tuple[int, float] | None:
    """(resident set size in bytes, user+system CPU seconds) of one process, from /proc."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        statm = Path(f"/proc/{pid}/statm").read_text().split()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()   # after "pid (comm) "
    cpu_s = (int(fields[11]) + int(fields[12])) / _CLK_TCK   # utime, stime
    return int(statm[1]) * _PAGE, cpu_s
