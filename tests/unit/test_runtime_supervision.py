"""Supervision: one instance per service, death with the parent, scheduling priority."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from aerotest import wait_until

from aeroperception.services.runtime import Node
from aeroperception.services.runtime.node import LIVELINESS_ROOT
from aeroperception.services.runtime.supervision import (
    EXIT_DUPLICATE, SUPERVISOR_ENV, DuplicateInstanceError, Instance, Priority, apply_priority,
    bind_to_supervisor,
    duplicate_message, winner,
)


@pytest.mark.parametrize("spec,expected", [
    (None, Priority()),
    ({"realtime": 20, "nice": -10}, Priority(20, -10)),
    ({"nice": 10}, Priority(None, 10)),
    (5, Priority(None, 5)),
])
def test_priority_parse(spec, expected):
    assert Priority.parse("fmu", spec) == expected


@pytest.mark.parametrize("spec,words", [
    ({"realtime": 0}, "1..99"), ({"realtime": 100}, "1..99"), ({"nice": -21}, "-20..19"),
    ({"nice": 20}, "-20..19"), ({"nice": "low"}, "-20..19"), ({"rt": 5}, "expected"), ("high", "expected"),
    ({"realtime": True}, "1..99"),
])
def test_priority_parse_refuses_with_the_service_named(spec, words):
    with pytest.raises(ValueError, match=words) as e:
        Priority.parse("planner", spec)
    assert "planner" in str(e.value)


def test_apply_priority_to_a_child_process_realtime_or_says_not_permitted():
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        got = apply_priority(proc.pid, Priority(realtime=20, nice=-5))
        if got.startswith("SCHED_RR"):
            assert got == "SCHED_RR 20"
            assert os.sched_getscheduler(proc.pid) == os.SCHED_RR
            assert os.sched_getparam(proc.pid).sched_priority == 20
        else:  # unprivileged: SCHED_RR and a negative nice are refused, and it says so
            assert "SCHED_RR 20" in got and "not permitted" in got
            assert os.sched_getscheduler(proc.pid) == os.SCHED_OTHER
        got = apply_priority(proc.pid, Priority(nice=7))  # lowering is always permitted
        if os.sched_getscheduler(proc.pid) == os.SCHED_OTHER:
            assert got == "nice 7" and os.getpriority(os.PRIO_PROCESS, proc.pid) == 7
    finally:
        proc.kill()
        proc.wait(5)


def test_lower_own_priority_drops_an_inherited_realtime_policy():
    """The sim's render processes inherit SCHED_RR from a realtime sim; they must drop it."""
    code = ("import os\n"
            "try:\n    os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(10))\nexcept PermissionError:\n    pass\n"
            "from aeroperception.services.runtime.supervision import lower_own_priority\n"
            "print(lower_own_priority(10), os.sched_getscheduler(0) == os.SCHED_OTHER)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert out.stdout.split() == ["nice", "10", "True"], out.stderr


def test_duplicate_message_names_the_instance_and_what_to_do():
    other = Instance("planner", "default", 4242, "box7", 1_000_000_000_000, "z1")
    msg = duplicate_message("planner", "default", other, now_ns=1_012_000_000_000)
    assert msg == ("planner is already running for vehicle 'default' (pid 4242 on host box7, up 12 s); "
                   "stop that one first, or run this one for another vehicle with --vehicle NAME")
    assert "--vehicle uav2" in duplicate_message("planner", "uav2", other)
    assert "does not say which" in duplicate_message("planner", "default", None)
    assert str(DuplicateInstanceError("planner", "default", other)).startswith("planner is already running")


def test_instance_json_round_trip_and_winner_is_earliest_start():
    a = Instance("fmu", "default", 1, "h", 200, "b")
    b = Instance("fmu", "default", 2, "h", 100, "c")
    c = Instance("fmu", "default", 3, "h", 100, "a")
    assert Instance.from_json(a.to_json()) == a
    assert Instance.from_json(b"{}") is None and Instance.from_json(b"\xff") is None
    assert winner([a, b, c]) is c and winner([a, b]) is b and winner([]) is None


def _exclusive(name: str, endpoint: str, vehicle: str = "") -> Node:
    node = Node(name, connect=endpoint, vehicle=vehicle, log_level="error")
    assert node.connect(max_wait_s=5.0, exclusive=True)
    return node


def test_exclusive_node_refuses_a_second_instance_for_the_same_vehicle(zenoh_router):
    first = _exclusive("planner", zenoh_router)
    others: list[Node] = []
    try:
        second = Node("planner", connect=zenoh_router, log_level="error")
        with pytest.raises(DuplicateInstanceError) as e:
            second.connect(max_wait_s=5.0, exclusive=True)
        assert f"pid {os.getpid()} on host " in str(e.value) and "vehicle 'default'" in str(e.value)
        assert e.value.other.zid == str(first.session.zid())
        second.close()  # nothing left to close, must not raise
        others.append(_exclusive("planner", zenoh_router, vehicle="uav2"))   # another vehicle: fine
        others.append(_exclusive("mission", zenoh_router))                   # another service: fine
        # Non-exclusive nodes (tools, benches) are never refused.
        tool = Node("planner", connect=zenoh_router, log_level="error")
        assert tool.connect(max_wait_s=5.0)
        others.append(tool)
    finally:
        first.close()
    # Once the first is gone, the slot is free again (the tool node holds no instance).
    wait_until(lambda: not any(r.ok for r in others[0].session.liveliness().get(
        f"{LIVELINESS_ROOT}/default/planner", timeout=1.0)) or True, 2, "")
    tool.close()
    others.remove(tool)
    again = _exclusive("planner", zenoh_router)
    for n in [again, *others]:
        n.close()


def test_exclusive_simultaneous_starts_leave_exactly_one(zenoh_router):
    results: list[object] = []
    nodes = [Node("mission", connect=zenoh_router, log_level="error") for _ in range(3)]
    barrier = threading.Barrier(len(nodes))

    def start(n: Node) -> None:
        barrier.wait()
        try:
            results.append(n.connect(max_wait_s=5.0, exclusive=True))
        except DuplicateInstanceError as e:
            results.append(e)

    threads = [threading.Thread(target=start, args=(n,)) for n in nodes]
    for t in threads:
        t.start()
    for t in threads:
        t.join(15)
    try:
        assert len(results) == 3
        assert sum(r is True for r in results) == 1, results
    finally:
        for n in nodes:
            n.close()


def test_bind_to_supervisor_ignores_a_variable_inherited_from_further_up():
    assert not bind_to_supervisor(lambda: None, env={}).bound
    b = bind_to_supervisor(lambda: None, env={SUPERVISOR_ENV: "1"})  # pid 1 lives, is not our parent
    assert (b.bound, b.orphaned) == (False, False) and "not the supervisor" in b.note


CHILD = """
import sys, threading, time
from aeroperception.services.runtime.signals import ShutdownFlag
from aeroperception.services.runtime.supervision import bind_to_supervisor
done = ShutdownFlag().install().event   # as every service: SIGTERM is a clean stop
b = bind_to_supervisor(done.set)
print("bound", b.bound, b.pdeathsig, flush=True)
done.wait(30)
print("stopping", flush=True)
sys.exit(0)
"""
PARENT = """
import os, subprocess, sys, time
env = dict(os.environ, AERO_SUPERVISOR_PID=str(os.getpid()))
child = subprocess.Popen([sys.executable, "-c", sys.argv[1]], env=env, stdout=open(sys.argv[2], "w"),
                         start_new_session=True)
print(child.pid, flush=True)
time.sleep(60)
"""


def test_supervised_process_stops_when_its_supervisor_is_killed(tmp_path):
    out = tmp_path / "child.out"
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, str(out)], stdout=subprocess.PIPE, text=True)
    child_pid = int(parent.stdout.readline())
    try:
        wait_until(lambda: "bound" in (out.read_text() if out.exists() else ""), 15, "the child to bind")
        assert out.read_text().split()[:2] == ["bound", "True"]
        parent.kill()
        parent.wait(5)
        t0 = time.monotonic()
        wait_until(lambda: not os.path.exists(f"/proc/{child_pid}") or
                   open(f"/proc/{child_pid}/stat").read().split()[2] == "Z", 5, "the orphan to exit")
        assert time.monotonic() - t0 < 3.0
        assert "stopping" in out.read_text()  # a clean stop (SIGTERM or watchdog), not a kill
    finally:
        if parent.poll() is None:
            parent.kill()
        try:
            os.kill(child_pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_profiles_give_the_hot_path_realtime_and_rendering_less(monkeypatch):
    from aeroperception.tools.cli.up import PRIORITIES_ENV, load_priorities

    monkeypatch.delenv(PRIORITIES_ENV, raising=False)
    prio = load_priorities()
    for hot in ("router", "fmu", "planner"):
        assert prio[hot].realtime and prio[hot].nice < 0
    assert prio["sim"].realtime < prio["fmu"].realtime
    assert all(prio[p].realtime is None and prio[p].nice > 0 for p in ("vio", "lidar", "detector"))
    monkeypatch.setenv(PRIORITIES_ENV, "off")
    assert load_priorities() == {}


def test_supervisor_holds_a_duplicate_until_the_other_instance_is_gone(tmp_path, capsys):
    from aeroperception.tools.cli.up import Child

    c = Child("planner", ["true"], tmp_path / "planner.log")
    c.last_exit, c.token = 1, True
    assert not c.held_elsewhere(0.0)           # an ordinary crash: restart as usual
    c.last_exit = EXIT_DUPLICATE
    assert c.status() == "duplicate"
    assert c.held_elsewhere(1.0) and c.held_elsewhere(2.0)
    assert capsys.readouterr().out.count("planner not started: the same service is already running") == 1
    c.token = False                             # the other instance stopped
    assert not c.held_elsewhere(3.0) and c.waiting_since is None


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to drop to an unprivileged user")
def test_apply_priority_unprivileged_falls_back_and_says_so():
    """Imports first, then drop to `nobody` with no realtime or nice limits: what a user gets."""
    code = ("import os, resource\n"
            "from aeroperception.services.runtime.supervision import Priority, apply_priority\n"
            "resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))\n"
            "resource.setrlimit(resource.RLIMIT_NICE, (0, 0))\n"
            "os.setgid(65534); os.setuid(65534)\n"
            "print(apply_priority(0, Priority(realtime=20, nice=-10)))\n"
            "print(apply_priority(0, Priority(nice=5)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert out.stdout.splitlines() == ["nice 0 (SCHED_RR 20, nice -10 not permitted)", "nice 5"], out.stderr


def test_wait_polling_times_out_and_sees_a_set_from_another_thread():
    from aeroperception.services.runtime.signals import wait_polling

    ev = threading.Event()
    t0 = time.monotonic()
    assert wait_polling(ev, 0.25, poll_s=0.1) is False
    assert 0.24 <= time.monotonic() - t0 < 1.0
    threading.Timer(0.15, ev.set).start()
    assert wait_polling(ev, 5.0, poll_s=0.1) is True
    assert time.monotonic() - t0 < 1.5
    flag = [False]
    assert wait_polling(threading.Event(), 2.0, poll_s=0.05, done=lambda: flag.__setitem__(0, True) or True)
    assert flag[0]


def test_shutdown_flag_wait_turns_a_recorded_signal_into_the_event():
    """What the main thread does after a handler ran: the event is set without the forwarder."""
    from aeroperception.services.runtime.signals import ShutdownFlag

    flag = ShutdownFlag(main_poll_s=0.05)   # not installed: no handlers, no forwarder thread
    assert flag.wait(0.1) is False and not flag
    flag.signal_name = "SIGINT"
    assert flag.wait(1.0) is True and flag.event.is_set()
