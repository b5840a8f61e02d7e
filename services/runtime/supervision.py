"""How a process relates to its supervisor and to other copies of itself (ARCHITECTURE §8).

- One instance per service per vehicle: a service asks (liveliness, bounded wait) whether the same
  service is already alive for its vehicle and refuses to start if so, naming the running instance
  (`DuplicateInstanceError`, exit code EXIT_DUPLICATE). Each exclusive instance answers on
  INSTANCE_ROOT/<vehicle>/<service> with its pid, host and start stamp, so the refusal can say
  which process to stop, and two copies started at the same moment agree on one winner.
- Services do not outlive their supervisor: `aero up` puts its pid in AERO_SUPERVISOR_PID; the
  child asks the kernel for SIGTERM when its parent dies (Linux PR_SET_PDEATHSIG) and a watchdog
  thread checks the parent pid as a fallback, stopping the service cleanly and, if that hangs,
  exiting hard.
- Scheduling: `apply_priority` gives a process SCHED_RR or a nice value where permitted and says
  what it got, so `aero up` can keep the control hot path ahead of rendering and perception.

Never here: deciding restart policy (that is aero up's) or touching another process's state
beyond its scheduling.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

SUPERVISOR_ENV = "AERO_SUPERVISOR_PID"
INSTANCE_ROOT = "aero/instance"
EXIT_DUPLICATE = 3          # another instance of this service is alive for this vehicle
EXIT_ORPHANED = 4           # the supervisor died and the clean stop did not finish in time
PR_SET_PDEATHSIG = 1


# ---------------------------------------------------------------- one instance per vehicle


@dataclass(frozen=True)
class Instance:
    """Who holds a service's slot: answered on INSTANCE_ROOT/<vehicle>/<service>."""

    service: str
    vehicle: str
    pid: int
    host: str
    started_ns: int   # wall clock, taken just before the instance declared itself
    zid: str

    def to_json(self) -> bytes:
        return json.dumps(self.__dict__).encode()

    @classmethod
    def from_json(cls, data: bytes) -> "Instance | None":
        try:
            d = json.loads(data)
            return cls(str(d["service"]), str(d["vehicle"]), int(d["pid"]), str(d["host"]),
                       int(d["started_ns"]), str(d["zid"]))
        except (ValueError, KeyError, TypeError):
            return None

    @property
    def rank(self) -> tuple[int, str]:
        """Earliest start wins a simultaneous start; the session id breaks a tie."""
        return (self.started_ns, self.zid)


def this_instance(service: str, vehicle: str, zid: str) -> Instance:
    return Instance(service, vehicle, os.getpid(), socket.gethostname(), time.time_ns(), zid)


def winner(instances: list[Instance]) -> Instance | None:
    return min(instances, key=lambda i: i.rank) if instances else None


class DuplicateInstanceError(RuntimeError):
    """The same service is already alive for the same vehicle; str() is the one-line refusal."""

    def __init__(self, service: str, vehicle: str, other: Instance | None, now_ns: int | None = None):
        self.service, self.vehicle, self.other = service, vehicle, other
        super().__init__(duplicate_message(service, vehicle, other, now_ns))


def duplicate_message(service: str, vehicle: str, other: Instance | None, now_ns: int | None = None) -> str:
    if other is not None:
        age_s = max(0.0, ((now_ns or time.time_ns()) - other.started_ns) / 1e9)
        who = f"pid {other.pid} on host {other.host}, up {age_s:.0f} s"
    else:
        who = "its liveliness token is held by a process that does not say which"
    flag = f"--vehicle {vehicle}" if vehicle != "default" else "--vehicle NAME"
    return (f"{service} is already running for vehicle '{vehicle}' ({who}); stop that one first, "
            f"or run this one for another vehicle with {flag}")


# ---------------------------------------------------------------- parent death


def _libc() -> Any | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask Linux to send `sig` when the parent (the thread that forked us) dies. False elsewhere."""
    libc = _libc()
    if libc is None:
        return False
    return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0


def terminate(procs, timeout_s: float, kill_wait_s: float = 5.0,
              first_signal: Callable[[subprocess.Popen], int] = lambda p: signal.SIGTERM) -> None:
    """Ask every live process to stop at once (SIGTERM, or `first_signal(p)`: PX4 stops on SIGINT),
    wait for all within one shared timeout_s; the rest get SIGTERM if they were asked otherwise,
    then SIGKILL after kill_wait_s."""
    live = [p for p in procs if p.poll() is None]
    asked = {id(p): first_signal(p) for p in live}
    for p in live:
        _signal(p, asked[id(p)])
    deadline = time.monotonic() + timeout_s
    for p in live:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            if asked[id(p)] != signal.SIGTERM:
                _signal(p, signal.SIGTERM)
                try:
                    p.wait(kill_wait_s)
                    continue
                except subprocess.TimeoutExpired:
                    pass
            p.kill()
            p.wait(kill_wait_s)


def _signal(p: subprocess.Popen, sig: int) -> None:
    try:
        p.send_signal(sig)
    except ProcessLookupError:
        pass


def _pid_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@dataclass
class SupervisorBinding:
    """What bind_to_supervisor found and did (for the service's start-up log)."""

    supervisor_pid: int | None = None
    bound: bool = False            # watching the supervisor
    pdeathsig: bool = False        # the kernel will signal us when it dies
    orphaned: bool = False         # it was already gone when we started
    note: str = ""


def bind_to_supervisor(on_orphaned: Callable[[], None], grace_s: float = 3.0, poll_s: float = 0.5,
                       env: Mapping[str, str] | None = None) -> SupervisorBinding:
    """If started by a supervisor (AERO_SUPERVISOR_PID), stop when it dies.

    Linux: PR_SET_PDEATHSIG delivers SIGTERM (the service's normal clean stop). Everywhere: a
    daemon thread polls the parent pid; when the supervisor is gone it calls `on_orphaned()`
    (request a clean stop) and, if the process is still alive `grace_s` later, exits with
    EXIT_ORPHANED. A process that inherited the variable from further up (its parent is not the
    supervisor, which is still alive) is not bound.
    """
    raw = (os.environ if env is None else env).get(SUPERVISOR_ENV, "")
    b = SupervisorBinding()
    if not raw.isdigit():
        return b
    b.supervisor_pid = sup = int(raw)
    if os.getppid() != sup:
        if _pid_exists(sup):
            b.note = f"parent {os.getppid()} is not the supervisor {sup}: not bound"
            return b
        b.orphaned, b.note = True, f"supervisor {sup} already gone"
        on_orphaned()
        _exit_after(grace_s)
        return b
    b.pdeathsig = set_parent_death_signal(signal.SIGTERM)
    # The parent may have died between fork and prctl: then no signal will ever come.
    if os.getppid() != sup:
        b.orphaned, b.note = True, f"supervisor {sup} died during start-up"
        on_orphaned()
        _exit_after(grace_s)
        return b
    b.bound = True
    threading.Thread(target=_watch_parent, args=(sup, on_orphaned, grace_s, poll_s),
                     name="supervisor-watchdog", daemon=True).start()
    return b


def _watch_parent(sup: int, on_orphaned: Callable[[], None], grace_s: float, poll_s: float) -> None:
    while os.getppid() == sup:
        time.sleep(poll_s)
    on_orphaned()
    time.sleep(grace_s)
    os._exit(EXIT_ORPHANED)


def _exit_after(grace_s: float) -> None:
    def later() -> None:
        time.sleep(grace_s)
        os._exit(EXIT_ORPHANED)

    threading.Thread(target=later, name="orphan-exit", daemon=True).start()


# ---------------------------------------------------------------- scheduling


@dataclass(frozen=True)
class Priority:
    """A process's requested scheduling: SCHED_RR `realtime` (1-99) if set and permitted, else
    niceness `nice` (-20..19; negative needs the same permission, refused -> 0)."""

    realtime: int | None = None
    nice: int = 0

    @classmethod
    def parse(cls, name: str, spec: Any) -> "Priority":
        if spec is None:
            return cls()
        if isinstance(spec, int) and not isinstance(spec, bool):
            spec = {"nice": spec}
        if not isinstance(spec, dict) or set(spec) - {"realtime", "nice"}:
            raise ValueError(f"priority of {name}: expected {{realtime: 1..99, nice: -20..19}}, got {spec!r}")
        rt, nice = spec.get("realtime"), spec.get("nice", 0)
        if rt is not None and (not isinstance(rt, int) or isinstance(rt, bool) or not 1 <= rt <= 99):
            raise ValueError(f"priority of {name}: realtime {rt!r} is not an integer in 1..99")
        if not isinstance(nice, int) or isinstance(nice, bool) or not -20 <= nice <= 19:
            raise ValueError(f"priority of {name}: nice {nice!r} is not an integer in -20..19")
        return cls(rt, nice)

    def __str__(self) -> str:
        parts = ([f"SCHED_RR {self.realtime}"] if self.realtime else []) + [f"nice {self.nice}"]
        return " / ".join(parts)


def apply_priority(pid: int, prio: Priority) -> str:
    """Apply `prio` to process `pid` (0 = this one) as far as permitted; returns what it got,
    e.g. "SCHED_RR 20", "nice -10", "nice 0 (SCHED_RR, nice -10 not permitted)".

    Linux schedules threads: this sets the thread whose id is `pid` (a process's main thread),
    which its later threads inherit — call it before the process starts its threads.
    """
    refused: list[str] = []
    if prio.realtime:
        try:
            os.sched_setscheduler(pid, os.SCHED_RR, os.sched_param(prio.realtime))
            return f"SCHED_RR {prio.realtime}"
        except (PermissionError, OSError, AttributeError):
            refused.append(f"SCHED_RR {prio.realtime}")
    got = 0
    if prio.nice:
        try:
            os.setpriority(os.PRIO_PROCESS, pid, prio.nice)
            got = prio.nice
        except (PermissionError, OSError):
            refused.append(f"nice {prio.nice}")
            got = os.getpriority(os.PRIO_PROCESS, pid) if _pid_exists(pid or os.getpid()) else 0
    return f"nice {got}" + (f" ({', '.join(refused)} not permitted)" if refused else "")


def lower_own_priority(nice: int) -> str:
    """For helper processes that must never compete with the hot path (e.g. sensor rendering):
    back to SCHED_OTHER if a realtime parent passed its policy on, then niceness `nice`."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError:
        pass
    return f"nice {os.getpriority(os.PRIO_PROCESS, 0)}"
