"""A running `aero up` as tests, `aero chaos` and the benches drive it: started on a free router port
with its logs and mission state in a private directory, ready once every service holds its
liveliness token (and, for a flight, once fmu hears the vehicle and streams the planner's
setpoints), queried and commanded through a client session, stopped by pid.

Never here: what a test or a fault row expects; only how to bring the stack up, ask it and land it.
"""
from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import zenoh

from aeroperception.schemas import (
    DiagnosticStatus, LoadMissionReply, LoadMissionRequest, MissionCommand, MissionStatus, Reply, SetModeReply,
    SetModeRequest, VehicleState,
)
from aeroperception.services.runtime.node import CallError, call
from aeroperception.services.runtime.session import make_config, open_session

from .processes import aero, aero_argv, clean_env, free_port, is_service_process, stop_up
from .topics import Capture, diag, latest, token_alive
from .waiting import poll_until, wait_until

STARTUP_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 8.0


class StackStartError(AssertionError):
    """`aero up` did not bring its services up in time; the message carries their logs."""


class Stack:
    """A running `aero up` (router + services as child processes) and a client session on it.

    The first run logs into `log_dir` (service logs, pids.json, aero-up.out, mission state in
    state/); each `restart` into a fresh `log_dir/run<N>` (`run_dir` is the current one).
    Subclasses add to the command line (`launch_args`) and to readiness (`wait_ready`).
    """

    def __init__(self, log_dir: str | Path, services: list[str], extra_args: Iterable[str] = (),
                 profile: str = "sim", timeout_s: float = STARTUP_TIMEOUT_S):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.services = list(services)
        self.extra_args = [str(a) for a in extra_args]
        self.profile, self.startup_timeout_s = profile, timeout_s
        self.session: zenoh.Session | None = None
        self.proc: subprocess.Popen | None = None
        self.starts = 0
        self.start()

    # -------------------------------------------------------- lifecycle

    def launch_args(self) -> list[str]:
        """Arguments for `aero up` besides profile, services, router and log dir (per start)."""
        return []

    def launch_env(self) -> dict[str, str]:
        """Environment for `aero up` besides a clean one (AERO_* dropped) and the private state dir."""
        return {}

    def wait_ready(self, deadline: float) -> None:
        """Readiness beyond every service's liveliness token (StackStartError if not by `deadline`)."""

    def start(self) -> None:
        self.starts += 1
        self.run_dir = self.log_dir if self.starts == 1 else self.log_dir / f"run{self.starts}"
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        argv = aero_argv() + ["up", "--profile", self.profile, "--only", ",".join(self.services),
                              "--listen", self.endpoint, "--log-dir", str(self.run_dir),
                              *self.launch_args(), *self.extra_args]
        self._stdout_path = self.run_dir / "aero-up.out"
        with open(self._stdout_path, "wb") as out:
            # Each stack persists mission state in its own folder (never the user's ~/.aero).
            env = dict(clean_env(), AERO_STATE_DIR=str(self.run_dir / "state"), **self.launch_env())
            self.proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, env=env)
        try:
            deadline = time.monotonic() + self.startup_timeout_s
            self._wait_up(deadline)
            self.wait_ready(deadline)
        except BaseException:
            self.stop()
            raise

    def _wait_up(self, deadline: float) -> None:
        timeout_s = self.startup_timeout_s
        while self.session is None:
            if self.proc.poll() is not None:
                self._fail(f"`aero up` exited with code {self.proc.returncode} during start-up")
            self.session = open_session(make_config(None, self.endpoint, mode="client"), max_wait_s=0.5)
            if time.monotonic() > deadline:
                self._fail(f"router at {self.endpoint} not reachable within {timeout_s:.0f} s")
        missing = list(self.services)
        while missing:
            missing = [s for s in missing if not self.alive(s)]
            if not missing:
                break
            if self.proc.poll() is not None:
                self._fail(f"`aero up` exited with code {self.proc.returncode} during start-up")
            if time.monotonic() > deadline:
                self._fail(f"no liveliness token from {', '.join(missing)} within {timeout_s:.0f} s")
            time.sleep(0.1)

    def wait_flight_ready(self, timeout_s: float, mission_ready: Callable[[MissionStatus], bool] | None = None) -> None:
        """Ready to fly within timeout_s: fmu hears the vehicle (state/vehicle connected), has streamed
        the planner's setpoints long enough for OFFBOARD, and the mission publishes its status
        (matching `mission_ready`, e.g. its restore done); checks of services not in the stack are
        skipped. StackStartError (with the logs) naming the first check that did not pass."""
        deadline = time.monotonic() + timeout_s
        checks = [("state/vehicle connected (fmu <-> vehicle MAVLink)",
                   lambda: self.latest("state/vehicle", VehicleState, 1.0, lambda m: m.connected))]
        if {"fmu", "planner"} <= set(self.services):
            checks.append(("planner setpoints streaming through fmu",
                           lambda: int(self.latest_diag("fmu").values.get("setpoints_sent", 0)) > 100))
        if "mission" in self.services:
            checks.append(("mission/status", lambda: self.latest("mission/status", MissionStatus, 1.5, mission_ready)))
        for what, ready in checks:
            if not poll_until(ready, max(1.0, deadline - time.monotonic()), 0.2):
                self._fail(f"stack not ready: no {what} within {timeout_s:.0f} s")

    def _fail(self, why: str) -> None:
        raise StackStartError(f"{why}\n{self.describe()}")

    def restart(self) -> None:
        self.stop()
        self.start()

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """Close the session, SIGINT `aero up` (which stops its children), kill it if it hangs
        (and then any child it left behind, by the pid it recorded in pids.json)."""
        code = stop_up(self.session, self.proc, self.pids(), timeout_s)
        self.session = None
        return code

    def describe(self) -> str:
        """aero up's output and every service log, for failure messages."""
        parts = [f"--- aero up output ({self._stdout_path}):\n{self.up_output()[-4000:]}"]
        for name in self.services:
            parts.append(f"--- {name}.log:\n{self.service_log(name)[-4000:]}")
        return "\n".join(parts)

    # -------------------------------------------------------- processes and logs

    def alive(self, name: str, vehicle: str = "default", timeout_s: float = 1.0) -> bool:
        """Whether the liveliness token aero/alive/<vehicle>/<name> exists right now."""
        assert self.session is not None
        return token_alive(self.session, name, vehicle, timeout_s)

    def service_log(self, name: str) -> str:
        p = self.run_dir / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def up_output(self) -> str:
        return self._stdout_path.read_text(errors="replace") if self._stdout_path.exists() else ""

    def pids(self) -> dict[str, int]:
        """{service: pid} from <run-dir>/pids.json as `aero up` last wrote it ({} if absent)."""
        try:
            return json.loads((self.run_dir / "pids.json").read_text())
        except (OSError, ValueError, AttributeError):
            return {}

    def pid(self, name: str) -> int | None:
        """The pid of service `name` if that process is still it, else None."""
        pid = self.pids().get(name)
        return pid if pid is not None and is_service_process(pid, name) else None

    def aero(self, *args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess:
        """Run an `aero` command against this stack (AERO_CONNECT set to its router)."""
        return aero(*args, endpoint=self.endpoint, timeout_s=timeout_s)

    # -------------------------------------------------------- keys

    def latest(self, key: str, cls: type, timeout_s: float = 3.0, pred: Callable[[Any], bool] | None = None):
        """The next message on `key` (matching pred) within timeout_s, else None."""
        return latest(self.session, key, cls, timeout_s, pred)

    def latest_diag(self, name: str, timeout_s: float = 3.0) -> DiagnosticStatus:
        """diagnostics/<name>, or an empty status (no values) when none came within timeout_s."""
        return self.latest(f"diagnostics/{name}", DiagnosticStatus, timeout_s) or DiagnosticStatus(name=name)

    def diag(self, name: str, timeout_s: float = 3.0) -> DiagnosticStatus:
        """diagnostics/<name>; AssertionError when none came within timeout_s."""
        return diag(self.session, name, timeout_s)

    def truth(self, timeout_s: float = 3.0) -> VehicleState:
        """The simulator's ground truth (sim/truth/state); AssertionError when none came."""
        t = self.latest("sim/truth/state", VehicleState, timeout_s)
        assert t is not None, f"no sim/truth/state within {timeout_s:g} s"
        return t

    def mission_state(self, timeout_s: float = 3.0) -> str:
        """The mission's state, "?" when no mission/status came within timeout_s."""
        s = self.latest("mission/status", MissionStatus, timeout_s)
        return s.state if s else "?"

    def capture(self, **keys: tuple[str, type]) -> Capture:
        """A Capture of `name=(key, schema)` on this stack's session (the caller closes it)."""
        return Capture(self.session, keys)

    def call(self, key: str, request, reply_cls: type, timeout_s: float = 10.0):
        return call(self.session, key, request, reply_cls, timeout_s)

    def command(self, cmd: str, timeout_s: float = 15.0) -> Reply:
        """A MissionCommand; no reply (CallError) comes back as a failed Reply saying why."""
        try:
            return self.call("mission/srv/command", MissionCommand(command=cmd), Reply, timeout_s)
        except CallError as e:
            return Reply(success=False, message=str(e))

    # -------------------------------------------------------- flying

    def landed(self, below_m: float = 0.2) -> bool:
        """On the ground (truth z below `below_m`) and disarmed; False without a sample. PX4 (the px4
        profile, no sim truth): by its land detector (state/vehicle landed), as its local z on the
        ground is not 0 (EKF2's height origin is taken at boot and drifts with the baro: 0.55 m seen)."""
        if self.profile == "px4":
            s = self.latest("state/vehicle", VehicleState, 2.0)
            return s is not None and not s.armed and s.landed
        t = self.latest("sim/truth/state", VehicleState, 3.0)
        return t is not None and t.position_m.z < below_m and not t.armed

    def ensure_landed(self, timeout_s: float = 60.0, fc_fallback: bool = False) -> None:
        """Landed, disarmed (judged by `landed`), mission IDLE: LAND through the mission if needed
        (through fmu's LAND mode if the mission refuses and `fc_fallback`). AssertionError if not."""
        if not self.landed():
            state, refused = self.mission_state(), ""
            if state not in ("LAND", "IDLE"):
                r = self.command("LAND")
                refused = "" if r.success else f"LAND refused: {r.message}"
            elif state == "IDLE" and fc_fallback:
                refused = "mission IDLE in the air"
            if refused and fc_fallback:
                try:
                    self.call("fmu/srv/set_mode", SetModeRequest(mode="LAND"), SetModeReply, 8.0)
                except CallError:
                    pass
            else:
                assert not refused, refused
            wait_until(self.landed, timeout_s, "vehicle landed and disarmed", 0.5)
        wait_until(lambda: self.mission_state(1.0) == "IDLE", 15, "mission IDLE", 0.2)

    def ensure_ground(self, timeout_s: float = 60.0) -> bool:
        """`ensure_landed` for a harness that restarts the stack when that fails: True or False."""
        try:
            self.ensure_landed(timeout_s, fc_fallback=True)
            return True
        except AssertionError:
            return False

    def start_mission(self, mission_json: str, timeout_s: float = 40.0) -> str | None:
        """Load, TAKEOFF, START; None once EXECUTING, else why not."""
        try:
            r = self.call("mission/srv/load", LoadMissionRequest(mission_json=mission_json), LoadMissionReply, 10.0)
        except CallError as e:
            return f"load: {e}"
        if not r.success:
            return f"load refused: {r.message}"
        for cmd in ("TAKEOFF", "START"):
            r = self.command(cmd)
            if not r.success:
                return f"{cmd} refused: {r.message}"
        if not poll_until(lambda: self.mission_state() == "EXECUTING", timeout_s, 0.2):
            return f"mission not EXECUTING within {timeout_s:.0f} s (state {self.mission_state()})"
        return None


class StackFactory:
    """Stacks under one base directory (stack0, stack1, ...), all stopped by `close`."""

    def __init__(self, base_dir: Callable[[], Path]):
        self._base_dir = base_dir
        self.stacks: list[Stack] = []

    def __call__(self, services: Iterable[str] = ("diagnostics",), extra_args: Iterable[str] = (),
                 profile: str = "sim", timeout_s: float = STARTUP_TIMEOUT_S) -> Stack:
        log_dir = self._base_dir() / f"stack{len(self.stacks)}"
        st = Stack(log_dir, list(services), extra_args, profile, timeout_s)
        self.stacks.append(st)
        return st

    def close(self) -> None:
        for st in reversed(self.stacks):
            st.stop()
