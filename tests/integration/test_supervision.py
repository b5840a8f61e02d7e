"""Supervision (ARCHITECTURE §8) with the real `aero up`, real services,
the sim vehicle on MAVLink: one instance per service per vehicle, no service outlives `aero up`,
and a dead router is restarted with every service reconnecting by itself."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh

from aerotest import (
    aero_argv, clean_env, free_udp_port, is_service_process, Stack, wait_for_message, wait_until, zenoh_client,
)

from aeroperception.schemas import TrajectorySetpoint, VehicleState
from aeroperception.services.runtime.node import LIVELINESS_ROOT
from aeroperception.services.runtime.supervision import EXIT_DUPLICATE, INSTANCE_ROOT, Instance

VEHICLE = ["sim", "fmu", "planner", "diagnostics"]


def vehicle_args(fcu: int, sim_bind: int) -> list[str]:
    """sim <-> fmu MAVLink on the given UDP ports, no sensors: the planner streams setpoints."""
    return ["--fcu-url", f"udpin:127.0.0.1:{fcu}", "--arg", f"sim:--target=127.0.0.1:{fcu}",
            "--arg", f"sim:--bind=127.0.0.1:{sim_bind}", "--arg", "sim:--sensors=none"]


def wait_connected(st: Stack, timeout_s: float = 20.0) -> None:
    try:
        wait_for_message(st.session, "state/vehicle", VehicleState, lambda m: m.connected, timeout_s)
    except AssertionError:
        print(st.describe())
        raise


class RateCounter:
    """Counts samples on a key with their arrival times (a raw subscriber, no decoding)."""

    def __init__(self, session: zenoh.Session, key: str):
        self.t: list[float] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, _s) -> None:
        with self._lock:
            self.t.append(time.monotonic())

    def rate_hz(self, t0: float, t1: float) -> float:
        with self._lock:
            n = sum(t0 <= t < t1 for t in self.t)
        return n / (t1 - t0)

    def close(self) -> None:
        self._sub.undeclare()


def router_pid(st: Stack) -> int | None:
    try:
        return int((st.log_dir / "router.pid").read_text())
    except (OSError, ValueError):
        return None


def gone(pid: int) -> bool:
    """The process has exited (a zombie not yet reaped by its parent counts as gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    except OSError:
        return True


def instances(session: zenoh.Session, name: str, vehicle: str = "default") -> list[Instance]:
    replies = session.get(f"{INSTANCE_ROOT}/{vehicle}/{name}", target=zenoh.QueryTarget.ALL,
                          consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0)
    return [i for r in replies if r.ok is not None and (i := Instance.from_json(r.ok.payload.to_bytes()))]


# ---------------------------------------------------------------- one instance per vehicle


@pytest.mark.timeout(120)
def test_second_planner_refused_setpoints_stay_50hz_another_vehicle_allowed(stack):
    st = stack(VEHICLE, extra_args=vehicle_args(free_udp_port(), free_udp_port()), timeout_s=30)
    wait_connected(st)
    planner_pid = st.pids()["planner"]
    rate = RateCounter(st.session, "fmu/in/trajectory_setpoint")
    try:
        time.sleep(2.0)
        t0 = time.monotonic()
        second = st.aero("run", "planner", timeout_s=30)
        t1 = time.monotonic()
        assert second.returncode == EXIT_DUPLICATE, (second.returncode, second.stderr)
        assert t1 - t0 < 10.0, f"took {t1 - t0:.1f} s to refuse"
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1, second.stderr  # one line, no traceback, no JSON log lines
        assert lines[0].startswith("aero run planner: planner is already running for vehicle 'default' "
                                   f"(pid {planner_pid} on host {socket.gethostname()}, up "), lines[0]
        assert "stop that one first, or run this one for another vehicle with --vehicle NAME" in lines[0]
        time.sleep(1.0)
        during = rate.rate_hz(t0, time.monotonic())
        assert 45 <= during <= 55, f"setpoints at {during:.1f} Hz while a second planner tried to start"
        assert is_service_process(planner_pid, "planner") and st.pids()["planner"] == planner_pid

        # Another vehicle prefix is another slot: it runs, and the default vehicle's rate is unchanged.
        env = clean_env(st.endpoint)
        other = subprocess.Popen(aero_argv() + ["run", "planner", "--vehicle", "uav2"], env=env,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                 stdin=subprocess.DEVNULL)
        try:
            wait_until(lambda: st.alive("planner", vehicle="uav2") or other.poll() is not None, 20,
                       "planner for vehicle uav2")
            assert other.poll() is None, other.stderr.read()
            t2 = time.monotonic()
            time.sleep(2.0)
            assert 45 <= rate.rate_hz(t2, time.monotonic()) <= 55
            assert [i.pid for i in instances(st.session, "planner")] == [planner_pid]
            assert [i.pid for i in instances(st.session, "planner", "uav2")] == [other.pid]
        finally:
            other.send_signal(signal.SIGINT)
            assert other.wait(10) == 0
    finally:
        rate.close()


@pytest.mark.timeout(120)
def test_aero_up_shows_a_duplicate_and_waits_for_it_instead_of_crash_looping(stack):
    st = stack(["diagnostics"])
    old = st.pids()["diagnostics"]
    # Another instance of diagnostics for this vehicle, e.g. started by hand on another machine.
    fake = Instance("diagnostics", "default", 424242, "groundstation", time.time_ns(), "f" * 32)
    key = f"{INSTANCE_ROOT}/default/diagnostics"
    other = zenoh_client(st.endpoint)
    token = other.liveliness().declare_token(f"{LIVELINESS_ROOT}/default/diagnostics")
    q = other.declare_queryable(key, lambda query: (query.reply(key, fake.to_json()), query.drop()))
    try:
        assert is_service_process(old, "diagnostics")
        os.kill(old, signal.SIGKILL)   # aero up restarts it after 1 s: now the slot is taken
        wait_until(lambda: "diagnostics   duplicate" in st.up_output().replace("diagnostics  duplicate",
                                                                           "diagnostics   duplicate"),
                   15, "a 'duplicate' row in aero up's table")
        log = st.service_log("diagnostics")
        assert ("aero run diagnostics: diagnostics is already running for vehicle 'default' "
                "(pid 424242 on host groundstation") in log
        wait_until(lambda: "diagnostics not started: the same service is already running" in st.up_output(),
                   5, "aero up to say why it does not restart diagnostics")
        # No crash loop: while the other instance lives, aero up does not start it again.
        time.sleep(5.0)
        assert st.up_output().count(f"diagnostics exited with code {EXIT_DUPLICATE}") == 1, st.up_output()
        assert "diagnostics" not in st.pids()
    finally:
        q.undeclare()
        token.undeclare()
    # The other instance stops: aero up starts its own within a few seconds.
    new = wait_until(lambda: st.pids().get("diagnostics"), 10, "aero up to start diagnostics again")
    assert new != old and is_service_process(new, "diagnostics")
    wait_until(lambda: st.alive("diagnostics") and [i.pid for i in instances(st.session, "diagnostics")] == [new],
               15, "diagnostics alive again, ours")
    other.close()


# ---------------------------------------------------------------- nothing outlives aero up


@pytest.mark.timeout(150)
def test_kill_9_of_aero_up_takes_every_child_along_and_a_new_aero_up_works(stack):
    fcu, sim_bind = free_udp_port(), free_udp_port()
    first = stack(VEHICLE, extra_args=vehicle_args(fcu, sim_bind), timeout_s=30)
    wait_connected(first)
    pids = dict(first.pids(), router=router_pid(first))
    assert set(pids) == {*VEHICLE, "router"} and all(pids.values()), pids
    first.proc.kill()                # kill -9 aero up: no chance to stop its children
    first.proc.wait(5)
    t0 = time.monotonic()
    wait_until(lambda: all(gone(p) for p in pids.values()), 5,
               f"every child of the killed aero up to exit: {pids}")
    exited_s = time.monotonic() - t0
    for name in VEHICLE:
        assert '"event":"signal"' in first.service_log(name) or '"event":"stopped"' in first.service_log(name), \
            f"{name} did not stop cleanly:\n{first.service_log(name)[-2000:]}"
    # A new aero up on the same MAVLink ports: one sim, one fmu, and the vehicle is connected again.
    second = stack(VEHICLE, extra_args=vehicle_args(fcu, sim_bind), timeout_s=30)
    wait_connected(second)
    assert [i.pid for i in instances(second.session, "fmu")] == [second.pids()["fmu"]]
    print(f"children exited {exited_s:.2f} s after kill -9 of aero up")


# ---------------------------------------------------------------- router restart


@pytest.mark.timeout(120)
def test_killed_router_is_restarted_and_every_service_reconnects(stack):
    st = stack(VEHICLE, extra_args=vehicle_args(free_udp_port(), free_udp_port()), timeout_s=30)
    wait_connected(st)
    old_router, services = router_pid(st), st.pids()
    assert old_router
    seen: list[float] = []
    watcher = zenoh_client(st.endpoint)
    watcher.declare_subscriber("state/vehicle", lambda _s: seen.append(time.monotonic()))
    try:
        os.kill(old_router, signal.SIGKILL)
        t_kill = time.monotonic()
        new_router = wait_until(lambda: (p := router_pid(st)) != old_router and p and not gone(p) and p, 3,
                                "a new router process")
        probe = zenoh_client(st.endpoint, max_wait_s=3.0)   # it accepts connections
        probe.close()
        restarted_s = time.monotonic() - t_kill
        assert restarted_s < 2.5, f"router back after {restarted_s:.2f} s"
        wait_until(lambda: all(st.alive(n) for n in VEHICLE), 10, "every service's liveliness token again")
        wait_until(lambda: any(t > t_kill + restarted_s for t in seen), 10, "state/vehicle flowing again")
        reconnected_s = min(t for t in seen if t > t_kill + restarted_s) - t_kill
        wait_for_message(st.session, "fmu/in/trajectory_setpoint", TrajectorySetpoint, timeout_s=5)
        # The services reconnected; none of them was restarted.
        assert st.pids() == services and all(is_service_process(p, n) for n, p in services.items())
        assert new_router != old_router
        assert "router exited with code -9; restarting" in st.up_output()
        print(f"router restarted {restarted_s:.2f} s, state/vehicle flowing again {reconnected_s:.2f} s after kill")
    finally:
        watcher.close()
