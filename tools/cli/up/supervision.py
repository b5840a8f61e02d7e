"""`aero up`'s supervision: the router and the services as child processes, restarted with
back-off when they exit, stopped together (SIGTERM, then SIGKILL after 3 s; PX4: SIGINT), their
pids in <log-dir>/pids.json; the status table reprinted while they run (status.py).

The Zenoh router runs as a child too (`aero router`, log <log-dir>/router.log, pid in
<log-dir>/router.pid): when it dies it is restarted within a second (back-off 0.2 s doubling to
2 s) and every session reconnects by itself. A crashed service is restarted with back-off (1 s
doubling to 30 s). A service that refuses to start because the same service is already alive
for the vehicle (exit EXIT_DUPLICATE) is shown as "duplicate" and is not restarted until that
other instance's liveliness token goes away.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import zenoh

from aeroperception.services.runtime.node import LIVELINESS_ROOT
from aeroperception.services.runtime.session import LINKS_ENV, make_config, open_session
from aeroperception.services.runtime.signals import ShutdownFlag
from aeroperception.services.runtime.supervision import (
    EXIT_DUPLICATE, SUPERVISOR_ENV, Priority, apply_priority, terminate,
)
from aeroperception.tools.common import CliError, emit

from ..topic import decode_sample
from .status import format_table

if TYPE_CHECKING:
    from .launch import LaunchPlan


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
    # A process that is not one of our services (PX4 or ArduPilot SITL): its own environment and clean-stop
    # signal; it has no liveliness token of its own, so aero up holds one for it while it runs and
    # its log has shown `booted`.
    extra_env: dict[str, str] = field(default_factory=dict)
    stop_signal: int = signal.SIGTERM
    booted: str = ""
    cwd: Path | None = None     # its working directory (ArduPilot writes eeprom.bin, logs/ there)
    proxy_token: zenoh.LivelinessToken | None = None
    log_offset: int = 0

    def start(self, env: dict[str, str]) -> None:
        self.log_offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(self.argv, stdout=log, stderr=subprocess.STDOUT, env={**env, **self.extra_env},
                                     start_new_session=True, cwd=self.cwd)
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


def supervise(args, plan: "LaunchPlan", priorities: dict[str, Priority]) -> int:
    """Start the router, then every process of `plan` at its priority; keep them running until
    Ctrl-C / SIGTERM, then stop them all, the router last."""
    log_dir = Path(args.log_dir or Path.home() / ".aero" / "logs" / time.strftime("%Y%m%d-%H%M%S"))
    log_dir.mkdir(parents=True, exist_ok=True)
    endpoint, links, names, fc = plan.endpoint, plan.links, plan.names, plan.fc
    # AERO_SUPERVISOR_PID: every child exits when this process dies (runtime/supervision.py).
    env = dict(os.environ, AERO_CONNECT=endpoint, PYTHONUNBUFFERED="1",
               **{SUPERVISOR_ENV: str(os.getpid()), LINKS_ENV: links})
    vehicle = os.environ.get("AERO_VEHICLE") or "default"
    children = {n: Child(n, argv, log_dir / f"{n}.log", priority=priorities.get(n, Priority()))
                for n, argv in plan.argv.items()}
    if fc:   # the flight controller first: fmu finds it booting rather than absent
        children = {fc.name: fc.child(log_dir, priorities.get(fc.name, Priority())), **children}
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
    if fc:
        emit(f"aero up: {children[fc.name].health['message']}; log {children[fc.name].log_path}")
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



def shutdown(children) -> None:
    """Each child's clean-stop signal (SIGTERM; PX4: SIGINT) at once, then SIGTERM / SIGKILL."""
    signals = {c.proc.pid: c.stop_signal for c in children if c.proc is not None}
    terminate([c.proc for c in children if c.proc is not None], timeout_s=3.0, kill_wait_s=1.0,
              first_signal=lambda p: signals.get(p.pid, signal.SIGTERM))
