"""The `aero` CLI as a user meets it: argument order, pipes into `head`,
silent keys, type checks against the contracts, `aero up` refusing what would crash-loop, the
installed (non-editable) package finding its Zenoh config, number parsing and rates.
Real `aero up` stacks, real routers, real pipes, on 127.0.0.1."""
from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import site as site_module
import threading
import time
import zipfile
from pathlib import Path

import pytest

from aerotest import (
    aero, aero_argv, clean_env, diagnostics_service, free_port, wait_for_message, zenoh_client,
)

from aeroperception.schemas import DiagnosticStatus, MissionCommand, VehicleState, encode
from aeroperception.services.runtime.node import encoding_for
from aeroperception.tools.cli.up import MESSAGE_COL, Child, format_table, last_error_line

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def st(stack_module):
    """One `aero up --only diagnostics,planner` for the read-mostly tests of this module."""
    return stack_module(["diagnostics", "planner"])


def one_clean_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, f"expected one error line, got:\n{err}"
    return lines[0]


class Publisher:
    """A client session publishing VehicleState on `key` at `rate_hz` until stopped."""

    def __init__(self, endpoint: str, key: str, rate_hz: float = 100.0):
        self.session = zenoh_client(endpoint)
        self.pub = self.session.declare_publisher(key, encoding=encoding_for(VehicleState))
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(1.0 / rate_hz,), daemon=True)
        self.thread.start()

    def _run(self, period: float) -> None:
        payload = encode(VehicleState())
        while not self.stop_event.wait(period):
            self.pub.put(payload)

    def close(self) -> None:
        self.stop_event.set()
        self.thread.join(2.0)
        self.pub.undeclare()
        self.session.close()


@pytest.fixture
def fast_key(st):
    key = f"test/fast_{free_port()}"
    pub = Publisher(st.endpoint, key)
    yield key
    pub.close()


# ---------------------------------------------------------------- 9: DATA after --type


@pytest.mark.timeout(60)
@pytest.mark.parametrize("order", ["data_after_type", "data_before_type"])
def test_topic_pub_accepts_data_before_or_after_type(st, order):
    args = (["--type", "MissionCommand", "{command: HOLD}"] if order == "data_after_type"
            else ["{command: HOLD}", "--type", "MissionCommand"])
    got: list = []

    def publish():
        time.sleep(0.5)  # the subscriber below is declared by then
        got.append(st.aero("topic", "pub", "mission/command", *args))

    t = threading.Thread(target=publish)
    t.start()
    msg = wait_for_message(st.session, "mission/command", MissionCommand, timeout_s=20)
    t.join(30)
    assert got[0].returncode == 0, got[0].stderr
    assert msg.command == "HOLD"
    assert "warning" not in got[0].stderr  # the declared schema of mission/command


@pytest.mark.timeout(60)
def test_service_call_accepts_type_before_data(st):
    r = st.aero("service", "call", "config/planner/@set", "--type", "ParamSet", "{name: kp, value: 1.5}")
    assert r.returncode == 0, r.stderr
    assert "success: true" in r.stdout
    assert st.aero("param", "get", "planner", "kp").stdout.strip() == "1.5"


# ---------------------------------------------------------------- 10: | head -1


def piped_into_head(cmd: list[str], endpoint: str, timeout_s: float = 10.0) -> tuple[int, str, str, float]:
    """Run `aero CMD | head -1` with real pipes: (aero's exit code, head's line, aero's stderr, seconds)."""
    t0 = time.monotonic()
    producer = subprocess.Popen(aero_argv() + cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                env=clean_env(endpoint), stdin=subprocess.DEVNULL)
    head = subprocess.Popen(["head", "-1"], stdin=producer.stdout, stdout=subprocess.PIPE, text=True)
    producer.stdout.close()  # head holds the only read end: when it exits, the pipe is broken
    try:
        line, _ = head.communicate(timeout=timeout_s)
        code = producer.wait(timeout=max(0.5, timeout_s - (time.monotonic() - t0)))
    finally:
        for p in (producer, head):
            if p.poll() is None:
                p.kill()
                p.wait(5)
    err = producer.stderr.read().decode()
    producer.stderr.close()
    return code, line, err, time.monotonic() - t0


@pytest.mark.timeout(60)
def test_echo_into_head_exits_quietly_and_promptly(st, fast_key):
    code, line, err, took = piped_into_head(["topic", "echo", fast_key], st.endpoint)
    assert line.startswith(f"# {fast_key} [VehicleState@")
    assert code == 141, err          # 128 + SIGPIPE, like `yes | head -1`
    assert "Traceback" not in err and "BrokenPipe" not in err, err
    assert took < 8.0


@pytest.mark.timeout(60)
def test_echo_count_into_head_exits(st, fast_key):
    code, line, err, took = piped_into_head(["topic", "echo", fast_key, "-n", "5"], st.endpoint)
    assert line.startswith("# ")
    assert code in (0, 141) and "Traceback" not in err, err  # 0 when all 5 fit in the pipe before head left
    assert took < 8.0


@pytest.mark.timeout(60)
def test_hz_into_head_exits_quietly(st, fast_key):
    # hz prints from the main thread once a second: the second print meets the closed pipe.
    code, line, err, took = piped_into_head(["topic", "hz", fast_key, "--window", "1"], st.endpoint)
    assert fast_key in line and "Hz" in line
    assert code == 141 and "Traceback" not in err, err
    assert took < 8.0


# ---------------------------------------------------------------- 11: silent keys, declared types


@pytest.mark.timeout(60)
def test_echo_of_misspelt_key_suggests_close_keys(st):
    t0 = time.monotonic()
    r = st.aero("topic", "echo", "state/vehical", "--timeout", "5")
    took = time.monotonic() - t0
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    hint = next(ln for ln in r.stderr.splitlines() if "nothing published" in ln)
    assert "state/vehicle" in hint and "no service declares it" in hint
    assert took < 10


@pytest.mark.timeout(60)
def test_echo_of_declared_but_silent_key_says_publisher_not_running(st):
    r = st.aero("topic", "echo", "mission/status", "--timeout", "4")  # mission is not in this stack
    assert r.returncode == 1
    assert "its publisher is not running" in r.stderr


@pytest.mark.timeout(60)
def test_echo_suggests_live_keys_too(st, fast_key):
    r = st.aero("topic", "echo", fast_key[:-1] + "x", "--timeout", "4")
    assert fast_key in r.stderr


@pytest.mark.timeout(60)
def test_pub_with_other_type_than_declared_warns(st):
    r = st.aero("topic", "pub", "mission/command", "--type", "Clock", "{speed_factor: 2}")
    assert r.returncode == 0
    assert "warning: mission/command is declared as MissionCommand (mission reads it), not Clock" in r.stderr


@pytest.mark.timeout(60)
@pytest.mark.parametrize("cmd", [["topic", "pub", "mission/command", "--type", "MisionCommand", "{command: HOLD}"],
                                 ["service", "call", "fmu/srv/arm", "{arm: true}", "--type", "armrequest"],
                                 ["schema", "show", "VehicleStat"]])
def test_unknown_schema_name_suggests_close_matches(cmd):
    r = aero(*cmd, endpoint=f"tcp/127.0.0.1:{free_port()}")
    assert r.returncode != 0
    line = one_clean_line(r.stderr)
    assert "did you mean" in line
    assert {"topic": "MissionCommand", "service": "ArmRequest", "schema": "VehicleState"}[cmd[0]] in line


# ---------------------------------------------------------------- 12: aero up validates first


@pytest.mark.timeout(60)
@pytest.mark.parametrize("flags,expected", [
    (["--scenario", "vilage"], "did you mean village"),
    (["--speed", "0"], "--speed 0: must be a number > 0"),
    (["--speed", "-2"], "must be a number > 0"),
    (["--only", "sim,plannr"], "did you mean planner"),
    (["--except", "gc"], "did you mean gcs"),
    (["--profile", "vehicel"], "did you mean vehicle"),
    (["--fcu-url", "udpin:127.0.0.1"], "expected udpin:HOST:PORT"),
    (["--arg", "plan:--param=kp=1"], "did you mean planner"),
    (["--links", "direct", "--listen", "tls/127.0.0.1:7999"], "would bypass its ACL"),
])
def test_up_refuses_bad_arguments_before_starting_anything(tmp_path, flags, expected):
    port = free_port()
    t0 = time.monotonic()
    r = aero("up", "--listen", f"tcp/127.0.0.1:{port}", "--log-dir", str(tmp_path), *flags, timeout_s=30)
    assert r.returncode == 2
    assert expected in one_clean_line(r.stderr)
    assert time.monotonic() - t0 < 10
    assert not any(tmp_path.glob("*.log")), "a service was started"


@pytest.mark.timeout(90)
def test_up_status_table_names_why_a_child_exited(tmp_path):
    port = free_port()
    proc = subprocess.Popen(aero_argv() + ["up", "--only", "diagnostics", "--listen", f"tcp/127.0.0.1:{port}",
                                           "--log-dir", str(tmp_path), "--status-interval", "0.5",
                                           "--arg", "diagnostics:--param=stale_after_s=999"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=clean_env(), stdin=subprocess.DEVNULL)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not any("above the maximum 60.0 s" in ln and ln.startswith(
                "diagnostics ") for ln in list(lines)):
            time.sleep(0.2)
    finally:
        proc.send_signal(2)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        reader.join(5)
    rows = [ln for ln in lines if ln.startswith("diagnostics ")]
    assert any("exit 2: aero run diagnostics: stale_after_s: 999.0 is above the maximum 60.0 s" in ln
               for ln in rows), "".join(lines[-20:])


def test_last_error_line_from_json_log_and_traceback(tmp_path):
    log = tmp_path / "sim.log"
    log.write_text('{"ts":1,"service":"sim","level":"info","event":"start"}\n'
                   '{"ts":2,"service":"sim","level":"error","event":"fatal","error":"RuntimeError: unknown scenario"}\n'
                   '{"ts":3,"service":"sim","level":"info","event":"closed"}\n')
    assert last_error_line(log) == "fatal: RuntimeError: unknown scenario"
    log.write_text("Traceback (most recent call last):\n  File x\nValueError: bad thing\n")
    assert last_error_line(log) == "ValueError: bad thing"
    assert last_error_line(tmp_path / "missing.log") == ""


def test_a_native_crash_dumps_the_stacks_and_aero_up_names_it(zenoh_router, tmp_path):
    """faulthandler in every service: a SIGSEGV (here sent, as a crashing C library would raise it)
    leaves every thread's stack in the log, and the supervisor's one-line cause is the headline."""
    log = tmp_path / "diagnostics.log"
    no_core = lambda: resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # noqa: E731 - no core file
    with diagnostics_service(zenoh_router, log, cwd=tmp_path, preexec_fn=no_core) as (proc, _watcher):
        proc.send_signal(signal.SIGSEGV)
        assert proc.wait(10) == -signal.SIGSEGV
    text = log.read_text()
    assert "Fatal Python error: Segmentation fault" in text and "runtime/service.py" in text, text[-2000:]
    assert last_error_line(log) == "Fatal Python error: Segmentation fault"


def test_status_table_wraps_on_word_boundaries():
    c = Child("fmu", [], Path("/dev/null"), alive=True,
              health={"level": 2, "message": "flight controller link stale (3.2 s) on udpin:127.0.0.1:14540 "
                                             "after 12 heartbeats"})
    table = format_table([c], width=80)
    assert "udpin:127.0.0.1:14540" in table  # never cut inside a word
    words = set(c.health["message"].split())
    for row in table.splitlines()[1:]:
        assert len(row) <= 80
        tail = row[MESSAGE_COL:].split()
        assert set(tail) <= words, row
    long = Child("sim", [], Path("/dev/null"), last_exit=1, last_error="word " * 100)
    rows = format_table([long], width=80).splitlines()
    assert len(rows) == 4 and rows[-1].endswith(" ...")


# ---------------------------------------------------------------- 13: the installed package


@pytest.fixture(scope="module")
def installed_wheel(tmp_path_factory):
    """The repository built into a wheel (`pip wheel`, from a copy of the tracked files, so the
    checkout gets no build/ folder) and unpacked as a site directory."""
    base = tmp_path_factory.mktemp("wheel")
    src = base / "src"
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    for rel in filter(None, files.decode().split("\0")):
        s, d = REPO / rel, src / rel
        if not (s.exists() or s.is_symlink()):
            continue  # deleted in the working tree
        d.parent.mkdir(parents=True, exist_ok=True)
        if s.is_symlink():
            os.symlink(os.readlink(s), d)
        else:
            shutil.copy2(s, d)
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(base / "dist"), str(src)],
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    wheel = next((base / "dist").glob("aeroperception-*.whl"))
    site = base / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    return wheel, site


def test_wheel_ships_the_default_zenoh_config(installed_wheel):
    wheel, site = installed_wheel
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
    assert "aeroperception/services/runtime/zenoh.json5" in names
    shipped = (site / "aeroperception/services/runtime/zenoh.json5").read_text()
    assert shipped == (REPO / "zenoh.json5").read_text()  # the root copy is the same file
    assert (REPO / "zenoh.json5").resolve() == (REPO / "services/runtime/zenoh.json5").resolve()
    assert 'mode: "client"' in shipped


@pytest.mark.timeout(120)
@pytest.mark.parametrize("argv", [["node", "list"], ["topic", "echo", "state/vehicle"]])
def test_installed_package_fails_fast_without_router_from_another_cwd(installed_wheel, tmp_path, argv):
    _wheel, site = installed_wheel
    # -S: no site-packages processing, so the editable install of this checkout is not on the path;
    # the unpacked wheel comes first, the venv's site-packages only for the dependencies.
    deps = os.pathsep.join(site_module.getsitepackages())
    code = ("import os, sys; sys.path[:0] = [sys.argv.pop(1), *sys.argv.pop(1).split(os.pathsep)]; "
            "import aeroperception.tools.cli as c; "
            "assert c.__file__.startswith(sys.path[0]), c.__file__; sys.exit(c.main())")
    dead = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-S", "-c", code, str(site), deps, *argv, "--connect", dead],
                       cwd=tmp_path, env=clean_env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, (r.stdout, r.stderr)
    line = one_clean_line(r.stderr)
    assert "no Zenoh router reachable" in line and dead in line
    assert time.monotonic() - t0 < 10


# ---------------------------------------------------------------- 14: numbers and rates


@pytest.mark.timeout(60)
def test_param_set_exponent_is_a_number_with_its_limit(st):
    r = st.aero("param", "set", "planner", "kp", "1e9")
    assert r.returncode == 1
    assert "1000000000.0 is above the maximum 5.0 1/s" in one_clean_line(r.stderr)
    ok = st.aero("param", "set", "planner", "kp", "2e0")
    assert ok.returncode == 0 and ok.stdout.strip() == "kp = 2.0"


@pytest.mark.timeout(60)
def test_topic_list_rate_of_1hz_diagnostics(st):
    r = st.aero("topic", "list", "diagnostics/*", "--duration", "3.5")
    assert r.returncode == 0, r.stderr
    row = next(ln.split() for ln in r.stdout.splitlines() if ln.startswith("diagnostics/diagnostics "))
    assert 0.8 <= float(row[1]) <= 1.25, r.stdout


@pytest.mark.timeout(90)
def test_up_piped_into_head_keeps_supervising(tmp_path):
    """`aero up | head -1`: the reader leaves after one line; the stack must not die or orphan
    its services because of that (no traceback), and Ctrl-C still stops everything."""
    port = free_port()
    up = subprocess.Popen(aero_argv() + ["up", "--only", "diagnostics", "--listen", f"tcp/127.0.0.1:{port}",
                                         "--log-dir", str(tmp_path), "--status-interval", "0.3"],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=clean_env(), stdin=subprocess.DEVNULL)
    head = subprocess.Popen(["head", "-1"], stdin=up.stdout, stdout=subprocess.PIPE, text=True)
    up.stdout.close()
    try:
        first, _ = head.communicate(timeout=20)
        assert first.startswith("aero up: profile sim")
        session = zenoh_client(f"tcp/127.0.0.1:{port}")
        try:
            wait_for_message(session, "diagnostics/diagnostics", DiagnosticStatus, timeout_s=20)
            time.sleep(1.5)   # several status tables written into the closed pipe meanwhile
            assert up.poll() is None, "aero up died when its stdout reader left"
            pid = int(json.loads((tmp_path / "pids.json").read_text())["diagnostics"])
        finally:
            session.close()
        up.send_signal(2)
        assert up.wait(10) == 141
        err = up.stderr.read().decode()
        assert "Traceback" not in err, err
        time.sleep(0.5)
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)   # the child was stopped, not orphaned
    finally:
        for p in (up, head):
            if p.poll() is None:
                p.kill()
                p.wait(5)
        up.stderr.close()
