"""The foundation end to end: the real `aero up` (router + the real diagnostics service process),
the `aero` CLI against it, live parameters, a flood of garbage, signals and restarts.
Everything over real Zenoh on 127.0.0.1."""
from __future__ import annotations

import json
import os
import random
import re
import signal
import subprocess
import time

import msgpack
import pytest
import zenoh

from aerotest import (
    StackStartError, aero, aero_argv, clean_env, diagnostics_service, free_port, is_service_process,
    signal_other_thread, token_alive, wait_for_message, wait_until,
)

from aeroperception.schemas import Clock as ClockMsg, DiagnosticArray, DiagnosticStatus, decode
from aeroperception.services.runtime.node import LIVELINESS_ROOT

TOKEN = f"{LIVELINESS_ROOT}/default/diagnostics"


@pytest.fixture(scope="module")
def diag(stack_module):
    """One `aero up --only diagnostics` shared by the read-mostly CLI tests of this module."""
    return stack_module(["diagnostics"])


def assert_one_clean_line(err: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one error line, got:\n{err}"
    assert "Traceback" not in err


# ---------------------------------------------------------------- the stack is up


@pytest.mark.timeout(60)
def test_service_alive_and_diagnostics_published(diag):
    assert diag.alive("diagnostics")
    st = wait_for_message(diag.session, "diagnostics/diagnostics", DiagnosticStatus, timeout_s=10)
    assert st.name == "diagnostics" and st.hardware_id == "default"
    assert st.level == DiagnosticStatus.OK and st.values["invalid_msgs"] == "0"
    # Its first roll-ups may predate its own first 1 Hz report ("alive but no diagnostics received yet")
    agg = wait_for_message(diag.session, "diagnostics/agg", DiagnosticArray,
                           lambda a: any(s.name == "diagnostics" and s.level != DiagnosticStatus.STALE
                                         for s in a.status), timeout_s=10)
    mine = next(s for s in agg.status if s.name == "diagnostics")
    assert mine.level == DiagnosticStatus.OK
    assert diag.pids().keys() == {"diagnostics"}
    assert '"event":"started"' in diag.service_log("diagnostics")


# ---------------------------------------------------------------- CLI


@pytest.mark.timeout(60)
def test_cli_node_list(diag):
    r = diag.aero("node", "list")
    assert r.returncode == 0, r.stderr
    row = next(ln for ln in r.stdout.splitlines() if "diagnostics" in ln)
    assert row.split()[:3] == ["default", "diagnostics", "OK"]


@pytest.mark.timeout(60)
def test_cli_topic_list(diag):
    r = diag.aero("topic", "list", "--duration", "2.5")
    assert r.returncode == 0, r.stderr
    rows = {ln.split()[0]: ln.split() for ln in r.stdout.splitlines()[1:]}
    assert rows["diagnostics/diagnostics"][-1] == "DiagnosticStatus@1"
    assert rows["diagnostics/agg"][-1] == "DiagnosticArray@1"
    assert 0.3 <= float(rows["diagnostics/agg"][1]) <= 2.0


@pytest.mark.timeout(60)
def test_cli_topic_echo_json(diag):
    r = diag.aero("topic", "echo", "diagnostics/agg", "-n", "1", "--json", "--timeout", "10")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 1
    obj = json.loads(lines[0])
    assert obj["key"] == "diagnostics/agg" and obj["schema"] == "DiagnosticArray@1"
    assert "diagnostics" in [s["name"] for s in obj["data"]["status"]]


@pytest.mark.timeout(60)
def test_cli_topic_hz(diag):
    r = diag.aero("topic", "hz", "diagnostics/diagnostics", "--duration", "3")
    assert r.returncode == 0, r.stdout + r.stderr
    rates = [float(m) for m in re.findall(r"rate ([0-9.]+) Hz", r.stdout)]
    assert rates and 0.6 <= rates[-1] <= 1.5, r.stdout


@pytest.mark.timeout(60)
def test_cli_topic_pub_valid_and_invalid(diag):
    got: list[ClockMsg] = []
    sub = diag.session.declare_subscriber(
        "test/cli_pub", lambda s: got.append(decode(s.payload.to_bytes(), ClockMsg)))
    try:
        time.sleep(0.3)  # let the router learn about the subscriber
        r = diag.aero("topic", "pub", "test/cli_pub", "{speed_factor: 2.5, header: {frame_id: map}}", "-t", "Clock")
        assert r.returncode == 0, r.stderr
        assert "published 1 x Clock@1" in r.stderr
        wait_until(lambda: got, 5, "the published message")
        assert got[0].speed_factor == 2.5 and got[0].header.frame_id == "map"
        assert got[0].header.stamp_ns > 0  # stamped by the CLI
        n = len(got)
        bad = diag.aero("topic", "pub", "test/cli_pub", "{speed_factor: fast}", "-t", "Clock")
        assert bad.returncode == 2
        assert_one_clean_line(bad.stderr)
        assert bad.stderr.startswith("aero: ") and "speed_factor" in bad.stderr
        unknown = diag.aero("topic", "pub", "test/cli_pub", "{}", "-t", "NoSuchType")
        assert unknown.returncode == 2 and "unknown schema" in unknown.stderr
        assert_one_clean_line(unknown.stderr)
        time.sleep(0.3)
        assert len(got) == n  # nothing invalid was sent
    finally:
        sub.undeclare()


@pytest.mark.timeout(60)
def test_cli_service_call_params(diag):
    r = diag.aero("service", "call", "config/diagnostics/@params", "--json")
    assert r.returncode == 0, r.stderr
    obj = json.loads(r.stdout)
    assert obj["schema"] == "ParamList@1" and obj["reply"]["service"] == "diagnostics"
    names = {p["name"]: p for p in obj["reply"]["params"]}
    assert names["stale_after_s"]["unit"] == "s" and names["stale_after_s"]["max"] == 60.0
    missing = diag.aero("service", "call", "config/nobody/@params", "--timeout", "2")
    assert missing.returncode == 2 and "no service answered" in missing.stderr
    assert_one_clean_line(missing.stderr)


@pytest.mark.timeout(90)
def test_cli_param_set_get_and_reject(diag):
    r = diag.aero("param", "set", "diagnostics", "stale_after_s", "5")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "stale_after_s = 5.0"
    g = diag.aero("param", "get", "diagnostics", "stale_after_s")
    assert g.returncode == 0 and g.stdout.strip() == "5.0"
    bad = diag.aero("param", "set", "diagnostics", "stale_after_s", "500")
    assert bad.returncode != 0
    assert_one_clean_line(bad.stderr)
    assert "rejected" in bad.stderr and "above the maximum 60.0 s" in bad.stderr
    word = diag.aero("param", "set", "diagnostics", "stale_after_s", "soon")
    assert word.returncode != 0 and "finite number" in word.stderr
    assert diag.aero("param", "get", "diagnostics", "stale_after_s").stdout.strip() == "5.0"
    lst = diag.aero("param", "list", "diagnostics")
    assert lst.returncode == 0 and "publish_rate_hz" in lst.stdout
    st = wait_for_message(diag.session, "diagnostics/diagnostics", DiagnosticStatus,
                          lambda s: s.values.get("params_rejected") == "2", timeout_s=5)
    assert st.name == "diagnostics"
    log = diag.service_log("diagnostics")
    assert '"event":"param_set"' in log and '"event":"param_rejected"' in log


@pytest.mark.timeout(60)
@pytest.mark.parametrize("argv", [["node", "list"], ["topic", "echo", "diagnostics/agg", "-n", "1"],
                                  ["param", "get", "diagnostics", "stale_after_s"]])
def test_cli_connect_to_dead_port(argv):
    dead = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    r = aero(*argv, "--connect", dead, timeout_s=30)
    assert r.returncode != 0
    assert_one_clean_line(r.stderr)
    assert "no Zenoh router reachable" in r.stderr and dead in r.stderr
    assert time.monotonic() - t0 < 15


# ---------------------------------------------------------------- bad input


def garbage_payloads(n: int, seed: int = 7) -> list[bytes]:
    """Random bytes and well-formed msgpack of the wrong shape or types."""
    rng = random.Random(seed)
    wrong = [
        msgpack.packb({"level": "high", "name": 5}),
        msgpack.packb({"header": {"stamp_ns": "yesterday"}}),
        msgpack.packb({"values": [1, 2, 3]}),
        msgpack.packb({"value": {"nested": True}}),
        msgpack.packb({"name": 7, "value": 1.0}),
        msgpack.packb([1, 2, 3]),
        msgpack.packb("a string"),
        msgpack.packb(None),
        msgpack.packb(1.5),
        b"",
        b"\xc1",
        b"\x81",  # a map announcing one entry that never comes
    ]
    out = []
    for i in range(n):
        if i % 3 == 0:
            out.append(wrong[(i // 3) % len(wrong)])
        else:
            out.append(bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 64))))
    return out


@pytest.mark.timeout(120)
def test_garbage_flood_service_survives_and_reports(stack):
    st = stack(["diagnostics"])
    pid = st.pids()["diagnostics"]
    keys = ["diagnostics/garbage_a", "diagnostics/garbage_b", "config/diagnostics/stale_after_s"]
    payloads = garbage_payloads(1000)
    pubs = {k: st.session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
            for k in keys}
    time.sleep(0.3)
    t0 = time.monotonic()
    for i, p in enumerate(payloads):  # spread over ~2 s so the once-per-second log limit shows
        pubs[keys[i % len(keys)]].put(p)
        if i % 10 == 9:
            time.sleep(0.02)
    flood_s = time.monotonic() - t0
    for p in pubs.values():
        p.undeclare()

    def warned(s: DiagnosticStatus) -> bool:
        return s.level == DiagnosticStatus.WARN and int(s.values.get("invalid_msgs", "0")) > 0

    status = wait_for_message(st.session, "diagnostics/diagnostics", DiagnosticStatus, warned, timeout_s=10)
    invalid = int(status.values["invalid_msgs"])
    assert invalid > 0 and "dropped invalid input" in status.message
    assert invalid >= 500, f"only {invalid} of 1000 garbage payloads counted"
    per_key = {k: int(v) for k, v in status.values.items() if k.startswith("invalid_msgs[")}
    assert f"invalid_msgs[{keys[0]}]" in per_key and f"invalid_msgs[{keys[2]}]" in per_key

    # Still the same process, still alive and doing its job.
    assert st.alive("diagnostics") and st.pids()["diagnostics"] == pid and st.proc.poll() is None
    wait_for_message(st.session, "diagnostics/agg", DiagnosticArray, timeout_s=5)
    g = st.aero("param", "get", "diagnostics", "stale_after_s")
    assert g.returncode == 0 and g.stdout.strip() == "3.0"  # no garbage changed the parameter
    # The aggregate shows the service as WARN too.
    agg = wait_for_message(st.session, "diagnostics/agg", DiagnosticArray,
                           lambda a: any(s.name == "diagnostics" and s.level == DiagnosticStatus.WARN
                                         for s in a.status), timeout_s=5)
    assert agg.status

    # Logged at most once per key per second.
    recs = [json.loads(ln) for ln in st.service_log("diagnostics").splitlines() if ln.startswith("{")]
    drops = [r for r in recs if r["event"] == "invalid_payload_dropped"]
    assert drops, "no invalid_payload_dropped log line"
    by_key: dict[str, list[float]] = {}
    for r in drops:
        by_key.setdefault(r["key"], []).append(r["ts"])
    for k, stamps in by_key.items():
        assert len(stamps) <= flood_s + 3, f"{k}: {len(stamps)} lines for a {flood_s:.1f} s flood"
        gaps = [b - a for a, b in zip(stamps, stamps[1:])]
        assert all(g >= 0.95 for g in gaps), f"{k}: logged more than once per second: {gaps}"
    if flood_s > 1.5:  # the limit is per second, not once forever
        assert max(len(v) for v in by_key.values()) >= 2, by_key


# ---------------------------------------------------------------- process lifecycle


@pytest.mark.timeout(60)
@pytest.mark.parametrize("sig,to_thread", [(signal.SIGTERM, False), (signal.SIGINT, False), (signal.SIGINT, True)],
                         ids=["SIGTERM", "SIGINT", "SIGINT-to-a-zenoh-thread"])
def test_aero_run_stops_on_signal_within_2s(zenoh_router, sig, to_thread, tmp_path):
    """A CI run once hung here: SIGINT landed on a zenoh thread while the main thread sat in an
    untimed Event.wait(), so the Python handler never ran (services/runtime/signals.py)."""
    log = tmp_path / "diagnostics.log"
    with diagnostics_service(zenoh_router, log) as (proc, watcher):
        t0 = time.monotonic()
        if to_thread:
            signal_other_thread(proc.pid, sig)
        else:
            proc.send_signal(sig)
        try:
            code = proc.wait(10)
        except subprocess.TimeoutExpired:
            pytest.fail(f"still running 10 s after {sig.name}; its log:\n{log.read_text()[-2000:]}")
        elapsed = time.monotonic() - t0
        assert elapsed < 2.0, f"took {elapsed:.2f} s to stop"
        assert code == 0, log.read_text()
        events = [json.loads(ln)["event"] for ln in log.read_text().splitlines() if ln.startswith("{")]
        assert events[-2:] == ["signal", "stopped"]
        wait_until(lambda: not token_alive(watcher, "diagnostics"), 5, "the token to be gone")


@pytest.mark.timeout(60)
def test_sigusr1_dumps_every_thread_stack_into_the_log_and_the_service_keeps_running(zenoh_router, tmp_path):
    log = tmp_path / "diagnostics.log"
    with diagnostics_service(zenoh_router, log) as (proc, watcher):
        proc.send_signal(signal.SIGUSR1)
        # the current (main) thread comes last, in run() (starting the service, or waiting to stop)
        wait_until(lambda: "runtime/service.py\", line" in log.read_text(), 10, "a whole stack dump in the log")
        text = log.read_text()
        assert text.count("Thread 0x") >= 3, text[-3000:]          # the main thread, loops, forwarder
        assert "Current thread 0x" in text and "in _forward" in text, text[-3000:]
        time.sleep(0.5)
        assert proc.poll() is None and token_alive(watcher, "diagnostics")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0


@pytest.mark.timeout(60)
def test_aero_router_stops_on_sigint_to_a_zenoh_thread(tmp_path):
    """`aero router` waits on its main thread as services do: a signal the kernel hands to one of
    zenoh's threads still stops it within 2 s."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "router.log"
    with open(log, "wb") as f:
        proc = subprocess.Popen(aero_argv() + ["router", "--listen", endpoint], stdout=subprocess.DEVNULL,
                                stderr=f, stdin=subprocess.DEVNULL, env=clean_env())
    try:
        wait_until(lambda: "listening on" in log.read_text() or proc.poll() is not None, 20, "the router")
        assert proc.poll() is None, log.read_text()
        t0 = time.monotonic()
        signal_other_thread(proc.pid, signal.SIGINT)
        assert proc.wait(10) == 0, log.read_text()
        assert time.monotonic() - t0 < 2.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


@pytest.mark.timeout(60)
def test_aero_run_stops_on_signal_while_waiting_for_router(tmp_path):
    """No router yet: the service retries (reporting STALE in its log) and still stops at once."""
    dead = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "diagnostics.log"
    with open(log, "wb") as f:
        proc = subprocess.Popen(aero_argv() + ["run", "diagnostics", "--connect", dead],
                                stdout=subprocess.DEVNULL, stderr=f, stdin=subprocess.DEVNULL, env=clean_env())
    try:
        wait_until(lambda: "waiting_for_router" in log.read_text() or proc.poll() is not None, 20,
                   "the service to wait for its router")
        assert proc.poll() is None, log.read_text()
        assert '"status":"STALE"' in log.read_text()
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(10)
        assert time.monotonic() - t0 < 2.0
        assert code == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


@pytest.mark.timeout(90)
def test_aero_up_restarts_crashed_service_and_stops_cleanly(stack):
    st = stack(["diagnostics"])
    events: list[tuple[str, float]] = []
    sub = st.session.liveliness().declare_subscriber(
        TOKEN, lambda s: events.append((str(s.kind).rsplit(".", 1)[-1], time.monotonic())))
    old = st.pids()["diagnostics"]
    assert is_service_process(old, "diagnostics")  # guard against a reused pid before killing it
    time.sleep(0.3)
    os.kill(old, signal.SIGKILL)
    wait_until(lambda: any(k == "DELETE" for k, _ in events), 10, "the token to go away")
    new = wait_until(lambda: (p := st.pids().get("diagnostics")) and p != old and p, 15, "a restarted process")
    assert is_service_process(new, "diagnostics")
    t_del = next(t for k, t in events if k == "DELETE")
    wait_until(lambda: any(k == "PUT" and t > t_del for k, t in events), 20, "the token to come back")
    assert st.alive("diagnostics")
    assert "diagnostics exited with code -9; restarting" in st.up_output()
    wait_for_message(st.session, "diagnostics/diagnostics", DiagnosticStatus, timeout_s=10)
    sub.undeclare()

    # Ctrl-C on aero up stops the children and exits 0.
    t0 = time.monotonic()
    assert st.stop() == 0, st.describe()
    assert time.monotonic() - t0 < 6.0
    assert not is_service_process(new, "diagnostics")
    assert "aero up: stopping" in st.up_output()
    assert not (st.log_dir / "pids.json").exists()
    events_log = [json.loads(ln)["event"] for ln in st.service_log("diagnostics").splitlines()
                  if ln.startswith("{")]
    assert events_log[-1] == "stopped"


# ---------------------------------------------------------------- the fixture's own failure path


@pytest.mark.timeout(60)
def test_stack_start_failure_reports_service_logs(stack):
    """A service that cannot start (a parameter outside its range) makes the fixture fail with
    that service's log in the message, not a bare timeout."""
    with pytest.raises(StackStartError) as e:
        stack(["diagnostics"], extra_args=["--arg", "diagnostics:--param=stale_after_s=999"], timeout_s=4)
    text = str(e.value)
    assert "no liveliness token from diagnostics" in text
    assert "stale_after_s: 999.0 is above the maximum 60.0" in text  # from diagnostics.log
    assert "diagnostics exited with code 2" in text                  # from aero up's output
    with pytest.raises(StackStartError, match="not in profile"):
        stack(["no_such_service"])
