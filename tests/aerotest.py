"""Test helpers shared by every test module (the fixtures in conftest.py are built on them).

    from aerotest import free_port, zenoh_client, wait_until, wait_for_message, aero, Stack

    free_port() -> int                     a free TCP port on 127.0.0.1
    zenoh_client(endpoint) -> Session      a client session connected to `endpoint` (caller closes)
    wait_until(pred, timeout_s, what)      poll pred() until truthy, return it; AssertionError naming `what`
    wait_for_message(session, key, cls, pred=None, timeout_s=10)
                                           the first decoded `cls` on `key` that satisfies pred
    aero(*args, endpoint=None, timeout_s=30)
                                           run the `aero` CLI to completion -> CompletedProcess (text)
    aero_argv(), clean_env(endpoint)       argv prefix and environment to Popen `aero` yourself
    is_service_process(pid, name)          whether pid is still service `name` (before killing it)
    Stack(log_dir, services, extra_args, profile, timeout_s)
                                           a running `aero up` (see the `stack` fixture)

Everything runs on 127.0.0.1 with ports picked by the OS; every wait is bounded; every process
is stopped through its own handle (never by name).
"""
from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterable

import zenoh

from aeroperception.services.runtime.node import LIVELINESS_ROOT
from aeroperception.services.runtime.session import make_config, open_session
from aeroperception.tools.cmd_chaos import free_port, is_service_process, stop_up  # noqa: F401 - one home (aero chaos)

STARTUP_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 8.0


# ---------------------------------------------------------------- helpers


def zenoh_client(endpoint: str, max_wait_s: float = 5.0) -> zenoh.Session:
    """A client session (the project's zenoh.json5, connect replaced by `endpoint`).
    The caller closes it."""
    session = open_session(make_config(None, endpoint, mode="client"), max_wait_s=max_wait_s)
    if session is None:
        raise RuntimeError(f"no Zenoh router reachable at {endpoint} within {max_wait_s} s")
    return session


def wait_until(pred: Callable[[], Any], timeout_s: float = 10.0, what: str = "condition",
               interval_s: float = 0.05) -> Any:
    """Poll `pred()` until it returns something truthy (returned), or fail after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout_s:.1f} s waiting for {what}")
        time.sleep(interval_s)


def wait_for_message(session: zenoh.Session, key: str, cls: type, pred: Callable[[Any], bool] | None = None,
                     timeout_s: float = 10.0) -> Any:
    """Subscribe to `key`, return the first message that decodes as `cls` (and satisfies
    `pred`), or fail after `timeout_s`. Payloads that do not decode are ignored."""
    from aeroperception.schemas import SchemaError, decode

    got: list[Any] = []
    cond = threading.Condition()

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), cls)
        except SchemaError:
            return
        if pred is None or pred(msg):
            with cond:
                got.append(msg)
                cond.notify_all()

    sub = session.declare_subscriber(key, on_sample)
    try:
        with cond:
            if not cond.wait_for(lambda: got, timeout_s):
                raise AssertionError(f"no matching {cls.__name__} on {key} within {timeout_s:.1f} s")
            return got[0]
    finally:
        sub.undeclare()


def sample_stream(session: zenoh.Session, key: str, cls: type, min_count: int, window_s: float,
                  timeout_s: float = 10.0) -> tuple[list[Any], float]:
    """Messages on `key` decoded as `cls`: wait for `min_count` (else fail after `timeout_s`), then
    count for `window_s`. Returns every message received and the rate over the window (Hz)."""
    from aeroperception.schemas import decode

    msgs: list[Any] = []
    sub = session.declare_subscriber(key, lambda sample: msgs.append(decode(sample.payload.to_bytes(), cls)))
    try:
        wait_until(lambda: len(msgs) >= min_count, timeout_s, f"{min_count} {cls.__name__} on {key}")
        n0, t0 = len(msgs), time.monotonic()
        time.sleep(window_s)
        rate_hz = (len(msgs) - n0) / (time.monotonic() - t0)
    finally:
        sub.undeclare()
    return list(msgs), rate_hz


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


@contextmanager
def standalone_fc(fcu_port: int, log: Path):
    """The simulated PX4 run alone (MAVLink only, no Zenoh), as a PX4 SITL would be: it sends to
    127.0.0.1:`fcu_port`, where fmu listens (`--fcu-url udpin:127.0.0.1:PORT`). Stopped on exit."""
    from aeroperception.services.runtime.supervision import terminate

    with open(log, "wb") as err:
        fc = subprocess.Popen([sys.executable, "-m", "aeroperception.services.sim.vehicle", "--target",
                               f"127.0.0.1:{fcu_port}", "--bind", f"127.0.0.1:{free_port()}", "--status-every", "0"],
                              stdout=subprocess.DEVNULL, stderr=err)
    try:
        yield fc
    finally:
        terminate([fc], 5.0)


def validate_foxglove_export(path: Path, per_channel: int) -> dict[str, int]:
    """Every channel of an `aero mcap export --foxglove` file: JSON messages that validate against
    the file's own (Foxglove) JSON schemas, `per_channel` sampled each. Message counts per topic."""
    import jsonschema
    from mcap.reader import make_reader

    validators, counts = {}, {}
    with open(path, "rb") as f:
        for s, ch, m in make_reader(f).iter_messages():
            assert ch.message_encoding == "json", ch.topic
            v = validators.get(s.id) or validators.setdefault(s.id, jsonschema.Draft202012Validator(json.loads(s.data)))
            if counts.get(ch.topic, 0) < per_channel:
                v.validate(json.loads(m.data))
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
    return counts


def clean_env(endpoint: str | None = None) -> dict[str, str]:
    """The test process's environment without AERO_* settings a developer may have exported."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AERO_")}
    env["PYTHONUNBUFFERED"] = "1"
    if endpoint:
        env["AERO_CONNECT"] = endpoint
    return env


def token_alive(session: zenoh.Session, service: str, vehicle: str = "default", timeout_s: float = 1.0) -> bool:
    """Whether the liveliness token aero/alive/<vehicle>/<service> exists right now."""
    replies = session.liveliness().get(f"{LIVELINESS_ROOT}/{vehicle}/{service}", timeout=timeout_s)
    return any(r.ok is not None for r in replies)


@contextmanager
def diagnostics_service(endpoint: str, log: Path, **popen: Any):
    """`aero run diagnostics` on `endpoint` (stderr into `log`; `popen` e.g. cwd, preexec_fn),
    yielded as (process, client session) once its liveliness token is seen; killed at exit if
    still running. The smallest real service, for tests of the runtime every service shares."""
    watcher = zenoh_client(endpoint)
    with open(log, "wb") as f:
        proc = subprocess.Popen(aero_argv() + ["run", "diagnostics"], stdout=subprocess.DEVNULL, stderr=f,
                                stdin=subprocess.DEVNULL, env=clean_env(endpoint), **popen)
    try:
        wait_until(lambda: token_alive(watcher, "diagnostics") or proc.poll() is not None, 20,
                   "the service's liveliness token")
        assert proc.poll() is None, log.read_text()
        yield proc, watcher
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        watcher.close()


def signal_other_thread(pid: int, sig: int) -> None:
    """Deliver `sig` to one of the process's threads other than the main one (tgkill), as the kernel
    may do with any process-directed signal: the Python handler still runs only on the main thread.
    A zenoh runtime thread (rx-/tx-/net-/app-) if there is one, else the oldest: long-lived either way,
    so the signal is not lost with a thread that exits."""
    tids = sorted(int(t) for t in os.listdir(f"/proc/{pid}/task") if int(t) != pid)
    assert tids, "the process has no other threads"
    named = [t for t in tids if Path(f"/proc/{pid}/task/{t}/comm").read_text().startswith(("rx-", "tx-", "net-", "app-"))]
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.tgkill(pid, (named or tids)[0], int(sig)) != 0:
        raise OSError(ctypes.get_errno(), "tgkill failed")


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


# ---------------------------------------------------------------- aero up


class StackStartError(AssertionError):
    """`aero up` did not bring its services up in time; the message carries their logs."""


class Stack:
    """A running `aero up` (router + services as child processes) and a client session on it."""

    def __init__(self, log_dir: Path, services: list[str], extra_args: Iterable[str] = (),
                 profile: str = "sim", timeout_s: float = STARTUP_TIMEOUT_S):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.services = list(services)
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session: zenoh.Session | None = None
        argv = aero_argv() + ["up", "--profile", profile, "--only", ",".join(self.services),
                              "--listen", self.endpoint, "--log-dir", str(self.log_dir),
                              *map(str, extra_args)]
        self._stdout_path = self.log_dir / "aero-up.out"
        with open(self._stdout_path, "wb") as out:
            # Each stack persists mission state in its own folder (never the user's ~/.aero).
            env = dict(clean_env(), AERO_STATE_DIR=str(self.log_dir / "state"))
            self.proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, env=env)
        try:
            self._wait_up(timeout_s)
        except BaseException:
            self.stop()
            raise

    def _wait_up(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
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

    def _fail(self, why: str) -> None:
        raise StackStartError(f"{why}\n{self.describe()}")

    def describe(self) -> str:
        """aero up's output and every service log, for failure messages."""
        parts = [f"--- aero up output ({self._stdout_path}):\n{self.up_output()[-4000:]}"]
        for name in self.services:
            parts.append(f"--- {name}.log:\n{self.service_log(name)[-4000:]}")
        return "\n".join(parts)

    # -------------------------------------------------------- queries

    def alive(self, name: str, vehicle: str = "default", timeout_s: float = 1.0) -> bool:
        """Whether the liveliness token aero/alive/<vehicle>/<name> exists right now."""
        assert self.session is not None
        return token_alive(self.session, name, vehicle, timeout_s)

    def service_log(self, name: str) -> str:
        p = self.log_dir / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def up_output(self) -> str:
        return self._stdout_path.read_text(errors="replace") if self._stdout_path.exists() else ""

    def pids(self) -> dict[str, int]:
        """{service: pid} from <log-dir>/pids.json as `aero up` last wrote it ({} if absent)."""
        p = self.log_dir / "pids.json"
        try:
            return json.loads(p.read_text())
        except (OSError, ValueError):
            return {}

    def aero(self, *args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess:
        """Run an `aero` command against this stack (AERO_CONNECT set to its router)."""
        return aero(*args, endpoint=self.endpoint, timeout_s=timeout_s)

    # -------------------------------------------------------- teardown

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int:
        """Close the session, SIGINT `aero up` (which stops its children), kill it if it hangs
        (and then any child it left behind, by the pid it recorded in pids.json)."""
        code = stop_up(self.session, self.proc, self.pids(), timeout_s)
        self.session = None
        return code


class StackFactory:
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
