"""The shared runtime: parameters, rate loop, logger, clock, and Node / actions over a real
in-process Zenoh router (no mocks of Zenoh)."""
from __future__ import annotations

import io
import json
import math
import threading
import time

import msgpack
import pytest
import zenoh

from aerotest import wait_until, zenoh_client

from aeroperception.schemas import (
    ArmReply, ArmRequest, Clock as ClockMsg, DiagnosticStatus, Empty, GoalReply, GoalStatus, Header,
    ParamList, ParamSet as ParamSetMsg, ParamSetReply, ResultRequest, ActionResult, TakeoffFeedback,
    TakeoffGoal, TakeoffResult, CancelReply, encode, decode,
)
from aeroperception.services.runtime import (
    ActionClient, ActionServer, CallError, Clock, Health, Logger, Param, ParamError, ParamSet,
    RateLoop,
)
from aeroperception.services.runtime.node import LIVELINESS_ROOT, call, encoding_for
from aeroperception.services.runtime.params import parse_overrides, start_only_but


# ================================================================ parameters

DECL = [
    Param("max_velocity_mps", 2.0, "m/s", 0.1, 15.0, description="cruise speed"),
    Param("retries", 3, "", 0, 10),
    Param("enabled", True),
    Param("mode", "fast", choices=("fast", "safe")),
    Param("label", "x"),
]


def params() -> ParamSet:
    return ParamSet.from_declarations(DECL)


def test_params_declared_defaults_units_and_access():
    ps = params()
    assert ps.values == {"max_velocity_mps": 2.0, "retries": 3, "enabled": True, "mode": "fast", "label": "x"}
    assert ps["retries"] == 3 and ps.max_velocity_mps == 2.0
    p = ps.declared["max_velocity_mps"]
    assert (p.type, p.unit, p.min, p.max, p.description) == (float, "m/s", 0.1, 15.0, "cruise speed")
    with pytest.raises(AttributeError):
        ps.not_a_param  # noqa: B018


@pytest.mark.parametrize("name,given,expected", [
    ("max_velocity_mps", "1.5", 1.5),     # CLI strings are parsed
    ("max_velocity_mps", 3, 3.0),         # int -> float
    ("retries", "4", 4),
    ("retries", 5.0, 5),                  # integral float -> int
    ("enabled", "false", False),
    ("enabled", "true", True),
    ("mode", "safe", "safe"),
    ("label", "123", "123"),              # a str parameter keeps strings as strings
])
def test_params_type_coercion(name, given, expected):
    ps = params()
    assert ps.set(name, given) == expected
    assert ps[name] == expected and type(ps[name]) is type(expected)


@pytest.mark.parametrize("name,bad,words", [
    ("max_velocity_mps", "fast", "finite number"),
    ("max_velocity_mps", float("nan"), "finite number"),
    ("max_velocity_mps", math.inf, "finite number"),
    ("max_velocity_mps", True, "finite number"),
    ("max_velocity_mps", 0.01, "below the minimum 0.1 m/s"),
    ("max_velocity_mps", 20, "above the maximum 15.0 m/s"),
    ("retries", 2.5, "integer"),
    ("retries", True, "integer"),
    ("retries", -1, "below the minimum"),
    ("enabled", 1, "true/false"),
    ("enabled", "1", "true/false"),
    ("mode", "reckless", "not one of ['fast', 'safe']"),
    ("label", 5, "string"),
    ("nope", 1, "unknown parameter 'nope'"),
])
def test_params_invalid_values_rejected_and_old_value_kept(name, bad, words):
    ps = params()
    before = dict(ps.values)
    with pytest.raises(ParamError) as e:
        ps.set(name, bad)
    assert words in str(e.value)
    assert ps.values == before


def test_params_update_is_atomic_and_notifies():
    ps = params()
    seen = []
    ps.on_change(lambda n, v: seen.append((n, v)))
    with pytest.raises(ParamError):
        ps.update({"retries": 5, "max_velocity_mps": 99})
    assert ps["retries"] == 3 and seen == []
    ps.update({"retries": 5, "mode": "safe"})
    assert ps["retries"] == 5 and ps["mode"] == "safe"
    assert sorted(seen) == [("mode", "safe"), ("retries", 5)]


def test_params_live_set_refused_by_apply_callback_keeps_what_runs():
    """An apply callback that refuses a valid value (raises ParamError): the old value stays,
    and callbacks that had already taken the new one get the old one back."""
    ps = params()
    applied = []
    ps.on_change(lambda n, v: applied.append(v))

    def refuse_large(name, value):
        if value > 5:
            raise ParamError(f"{name}: the motors cannot do {value}")

    ps.on_change(refuse_large)
    with pytest.raises(ParamError, match="cannot do 9"):
        ps.apply("max_velocity_mps", 9)
    assert ps["max_velocity_mps"] == 2.0 and applied == [9.0, 2.0]
    assert ps.apply("max_velocity_mps", 4) == 4.0 and ps["max_velocity_mps"] == 4.0
    ps.on_change(lambda n, v: 1 / 0 if v == 3 else None)        # a callback that fails: not applied either
    with pytest.raises(ZeroDivisionError):
        ps.apply("max_velocity_mps", 3)
    assert ps["max_velocity_mps"] == 4.0


def test_params_start_only_refused_live_naming_that():
    ps = ParamSet.from_declarations([Param("strategy", "a", start_only=True), Param("gain", 1.0)])
    ps.update({"strategy": "b"})                   # start-up values (file, --param) are taken
    with pytest.raises(ParamError, match="strategy is read at start only.*still 'b'"):
        ps.apply("strategy", "c")
    assert ps["strategy"] == "b" and ps.apply("gain", 2.0) == 2.0


def test_start_only_but_marks_every_parameter_but_the_live_ones():
    marked = start_only_but(DECL, live=("retries",))
    assert [p.name for p in marked if not p.start_only] == ["retries"]
    assert [p.default for p in marked] == [p.default for p in DECL] and not any(p.start_only for p in DECL)


def test_params_load_flat_file(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("max_velocity_mps: 4.5\nretries: 7\n")
    ps = params()
    ps.load_file(f, "planner")
    assert ps["max_velocity_mps"] == 4.5 and ps["retries"] == 7


def test_params_load_per_service_file(tmp_path):
    f = tmp_path / "stack.yaml"
    f.write_text("planner:\n  max_velocity_mps: 5.0\nmission:\n  retries: 9\n")
    ps = params()
    ps.load_file(f, "planner")
    assert ps["max_velocity_mps"] == 5.0 and ps["retries"] == 3
    other = params()
    other.load_file(f, "vio")  # a stack file without a section for this service: defaults stay
    assert other.values == params().values


@pytest.mark.parametrize("content,words", [
    (None, "cannot read parameter file"),
    ("a: [1, 2\n", "not valid YAML"),
    ("- 1\n- 2\n", "expected a mapping"),
    ("retries: lots\n", "retries: expected an integer"),
    ("planner:\n  max_velocity_mps: 99\n", "above the maximum"),
    ("bogus: 1\n", "unknown parameter 'bogus'"),
])
def test_params_bad_file_errors_name_the_file(tmp_path, content, words):
    f = tmp_path / "bad.yaml"
    if content is not None:
        f.write_text(content)
    ps = params()
    with pytest.raises(ParamError) as e:
        ps.load_file(f, "planner")
    assert str(f) in str(e.value) and words in str(e.value)
    assert ps.values == params().values


def test_params_load_empty_file_keeps_defaults(tmp_path):
    f = tmp_path / "empty.yaml"
    f.write_text("")
    ps = params()
    ps.load_file(f, "planner")
    assert ps.values == params().values


def test_parse_overrides():
    assert parse_overrides(["a=1", " b = x ", "c=k=v", "d="]) == {"a": "1", "b": "x", "c": "k=v", "d": ""}
    for bad in ("novalue", "=3"):
        with pytest.raises(ParamError, match="expected NAME=VALUE"):
            parse_overrides([bad])


# ================================================================ rate loop


@pytest.mark.timeout(30)
def test_rate_loop_keeps_period_by_deadline_with_heavy_body():
    """A body taking 60% of the period: a sleep(period) loop would run at 1.6x the period;
    a deadline loop keeps the mean period."""
    period = 0.025
    stamps: list[float] = []

    def body():
        stamps.append(time.perf_counter())
        time.sleep(0.6 * period)

    loop = RateLoop(1 / period, body, name="t").start()
    time.sleep(1.5)
    loop.stop()
    assert len(stamps) > 20
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    mean = sum(gaps) / len(gaps)
    assert 0.9 * period < mean < 1.2 * period, f"mean period {mean * 1e3:.1f} ms, want {period * 1e3:.0f} ms"
    s = loop.stats.summary()
    assert s["ticks"] == len(stamps)
    assert {"period_error_p50_ms", "period_error_p99_ms", "work_p50_ms", "work_p99_ms"} <= set(s)
    assert s["work_p50_ms"] >= 0.5 * 0.6 * period * 1e3
    # Jitter is reported: the median period error is small against the period.
    assert s["period_error_p50_ms"] < 0.5 * period * 1e3


@pytest.mark.timeout(30)
def test_rate_loop_counts_overruns_and_does_not_burst():
    period = 0.02
    stamps: list[float] = []
    slow = threading.Event()
    slow.set()

    def body():
        stamps.append(time.perf_counter())
        if slow.is_set() and len(stamps) <= 5:
            time.sleep(3 * period)  # falls more than one period behind

    loop = RateLoop(1 / period, body).start()
    wait_until(lambda: len(stamps) >= 15, 10, "15 ticks")
    loop.stop()
    assert loop.stats.overruns >= 1
    # After the slow ticks the loop skips ahead instead of firing a burst of catch-up ticks.
    gaps = [b - a for a, b in zip(stamps[4:], stamps[5:])]
    assert min(gaps) > 0.5 * period, f"burst after overrun: gaps {[round(g * 1e3, 1) for g in gaps]} ms"


def test_rate_loop_survives_exceptions_and_stops_fast():
    errors: list[BaseException] = []
    n = [0]

    def body():
        n[0] += 1
        raise RuntimeError("boom")

    loop = RateLoop(100, body, on_error=errors.append).start()
    wait_until(lambda: n[0] >= 5, 5, "5 ticks")
    t0 = time.monotonic()
    loop.stop()
    assert time.monotonic() - t0 < 0.5
    assert len(errors) >= 5 and all(isinstance(e, RuntimeError) for e in errors)
    count = n[0]
    time.sleep(0.05)
    assert n[0] == count  # really stopped


def test_rate_loop_stop_interrupts_long_wait_and_set_rate():
    loop = RateLoop(0.2, lambda: None).start()  # 5 s period
    time.sleep(0.05)
    t0 = time.monotonic()
    loop.stop()
    assert time.monotonic() - t0 < 0.5
    loop.set_rate(50)
    assert loop.period_s == pytest.approx(0.02)
    with pytest.raises(ValueError):
        RateLoop(0, lambda: None)


# ================================================================ logger


def lines(buf: io.StringIO) -> list[dict]:
    return [json.loads(line) for line in buf.getvalue().splitlines()]


def test_logger_writes_json_lines_with_fields():
    buf = io.StringIO()
    log = Logger("planner", "info", stream=buf)
    log.info("started", rate_hz=50, where={"x": 1.0}, obj=object())
    log.debug("hidden")
    log.warn("slow", ms=12.5)
    log.error("failed", error="x")
    recs = lines(buf)
    assert [r["event"] for r in recs] == ["started", "slow", "failed"]
    assert [r["level"] for r in recs] == ["info", "warn", "error"]
    first = recs[0]
    assert first["service"] == "planner" and first["rate_hz"] == 50 and first["where"] == {"x": 1.0}
    assert isinstance(first["obj"], str)  # not JSON-serializable: str()
    assert abs(first["ts"] - time.time()) < 5


def test_logger_levels_threshold():
    buf = io.StringIO()
    log = Logger("s", "warn", stream=buf)
    log.info("no")
    log.warn("yes")
    assert [r["event"] for r in lines(buf)] == ["yes"]
    buf = io.StringIO()
    Logger("s", "debug", stream=buf).debug("dbg")
    assert lines(buf)[0]["level"] == "debug"


def test_logger_throttles_per_key():
    buf = io.StringIO()
    log = Logger("s", stream=buf)
    logged = [log.throttled("warn", "bad:a", "invalid", period_s=0.2, n=i) for i in range(100)]
    assert logged.count(True) == 1
    assert log.throttled("warn", "bad:b", "invalid", period_s=0.2)  # another key logs
    time.sleep(0.25)
    assert log.throttled("warn", "bad:a", "invalid", period_s=0.2)  # period over: logs again
    recs = lines(buf)
    assert [r["key"] for r in recs] == ["bad:a", "bad:b", "bad:a"]
    assert recs[0]["n"] == 0


def test_logger_reentrant_call_does_not_deadlock():
    """A signal handler runs on the main thread, possibly inside log(): logging from it must not
    deadlock (simulated by a stream whose write logs again)."""

    class Reentrant(io.StringIO):
        inner = False

        def write(self, s):
            if not self.inner:
                self.inner = True
                log.info("inner")
            return super().write(s)

    buf = Reentrant()
    log = Logger("s", stream=buf)
    t = threading.Thread(target=log.info, args=("outer",), daemon=True)
    t.start()
    t.join(2.0)
    assert not t.is_alive(), "Logger deadlocked on a re-entrant call"
    assert [r["event"] for r in lines(buf)] == ["inner", "outer"]


def test_logger_survives_closed_stream():
    buf = io.StringIO()
    log = Logger("s", stream=buf)
    buf.close()
    log.error("after_close")  # must not raise


# ================================================================ clock


def test_clock_wall():
    c = Clock()
    assert not c.is_sim
    assert abs(c.now_ns() - time.time_ns()) < 50_000_000


class _FakeNode:
    """Only what Clock needs from a Node: subscribe()."""

    def __init__(self):
        self.subs = {}

    def subscribe(self, key, cls, cb):
        self.subs[key] = (cls, cb)


def test_clock_sim_follows_ticks_and_extrapolates_monotonic():
    node = _FakeNode()
    c = Clock(node)
    assert c.is_sim and "sim/clock" in node.subs and node.subs["sim/clock"][0] is ClockMsg
    assert c.now_ns() == 0  # no tick heard: time has not started
    c._on_tick(ClockMsg(header=Header(stamp_ns=10_000_000_000), speed_factor=10.0))
    t1 = c.now_ns()
    assert 10_000_000_000 <= t1 < 10_500_000_000
    time.sleep(0.05)
    t2 = c.now_ns()
    assert t2 - t1 >= 0.4e9  # 50 ms wall at 10x is >= 0.4 s sim (allowing for timer slack)
    # A tick slightly behind the extrapolation does not make time go backwards.
    c._on_tick(ClockMsg(header=Header(stamp_ns=t2 - 1_000_000), speed_factor=10.0))
    assert c.now_ns() >= t2
    t0 = time.monotonic()
    c.sleep(0.5)  # half a sim second at 10x
    assert time.monotonic() - t0 < 0.3


@pytest.mark.timeout(30)
def test_clock_sim_through_a_real_node(make_node):
    follower = make_node("clockuser", sim_time=True)
    sim = make_node("fakesim")
    pub = sim.publisher("sim/clock", ClockMsg)
    assert follower.now_ns() == 0
    stamp = 123_000_000_000

    def ticked():
        pub.publish(ClockMsg(header=Header(stamp_ns=stamp), speed_factor=1.0))
        return follower.now_ns() >= stamp

    wait_until(ticked, 10, "the node to follow sim/clock")
    assert follower.now_ns() < stamp + 5_000_000_000
    assert follower.header().stamp_ns >= stamp
    wall = make_node("walluser")
    assert abs(wall.now_ns() - time.time_ns()) < 1e9


# ================================================================ Node over a real router


@pytest.mark.timeout(60)
def test_node_typed_pub_sub_round_trip(make_node):
    a, b = make_node("talker"), make_node("listener")
    got: list[ClockMsg] = []
    b.subscribe("test/clock", ClockMsg, got.append)
    pub = a.publisher("test/clock", ClockMsg)

    def received():
        pub.publish(ClockMsg(header=Header(stamp_ns=42, frame_id="map"), speed_factor=2.5))
        return got

    wait_until(received, 10, "a message through the router")
    msg = got[0]
    assert isinstance(msg, ClockMsg)
    assert (msg.header.stamp_ns, msg.header.frame_id, msg.speed_factor) == (42, "map", 2.5)
    assert pub.count >= 1
    assert not b.bad_input and not b.callback_errors


@pytest.mark.timeout(60)
def test_node_publisher_sets_msgpack_encoding_with_schema(make_node, zenoh_router):
    a = make_node("enc")
    s = zenoh_client(zenoh_router)
    try:
        samples: list[zenoh.Sample] = []
        sub = s.declare_subscriber("test/enc", samples.append)
        pub = a.publisher("test/enc", ClockMsg)
        wait_until(lambda: pub.publish(ClockMsg()) or samples, 10, "a sample")
        assert str(samples[0].encoding) == "application/msgpack;Clock@1"
        # Plain msgpack: any msgpack library reads it.
        assert msgpack.unpackb(samples[0].payload.to_bytes())["speed_factor"] == 1.0
        sub.undeclare()
    finally:
        s.close()


@pytest.mark.timeout(60)
def test_node_callback_error_is_counted_not_fatal(make_node):
    a, b = make_node("talker"), make_node("fragile")
    good: list[ClockMsg] = []

    def cb(msg: ClockMsg) -> None:
        if msg.speed_factor < 0:
            raise ValueError("negative speed")
        good.append(msg)

    b.subscribe("test/cb", ClockMsg, cb)
    pub = a.publisher("test/cb", ClockMsg)
    wait_until(lambda: pub.publish(ClockMsg(speed_factor=-1.0)) or b.callback_errors["test/cb"],
               10, "the callback error to be counted")
    wait_until(lambda: pub.publish(ClockMsg(speed_factor=1.0)) or good, 10, "later messages still delivered")
    d = b.diagnostics()
    assert int(d.values["callback_errors"]) >= 1
    assert d.level == DiagnosticStatus.WARN


@pytest.mark.timeout(60)
def test_node_garbage_payloads_counted_and_in_diagnostics(make_node, zenoh_router):
    b = make_node("victim")
    got: list[ClockMsg] = []
    b.subscribe("test/garbage", ClockMsg, got.append)
    raw = zenoh_client(zenoh_router)
    try:
        garbage = [b"\xc1\xff\x00", b"not msgpack", msgpack.packb({"speed_factor": "fast"}),
                   msgpack.packb([1, 2, 3]), msgpack.packb({"header": {"stamp_ns": "x"}})]

        def flood():
            for g in garbage:
                raw.put("test/garbage", g)
            return b.bad_input["test/garbage"] >= len(garbage)

        wait_until(flood, 10, "garbage to be counted")
        # The service goes on: a valid message still gets through.
        wait_until(lambda: raw.put("test/garbage", encode(ClockMsg(speed_factor=3.0)),
                                   encoding=encoding_for(ClockMsg)) or got, 10, "a valid message")
        assert got[0].speed_factor == 3.0
        d = b.diagnostics()
        assert int(d.values["invalid_msgs"]) >= len(garbage)
        assert int(d.values["invalid_msgs[test/garbage]"]) >= len(garbage)
        assert d.level == DiagnosticStatus.WARN and "dropped invalid input" in d.message
    finally:
        raw.close()


@pytest.mark.timeout(60)
def test_node_other_schema_under_key_is_skipped(make_node, zenoh_router):
    b = make_node("picky")
    got: list[ClockMsg] = []
    b.subscribe("test/other/*", ClockMsg, got.append)
    raw = zenoh_client(zenoh_router)
    try:
        def sent():
            raw.put("test/other/a", b"\x00\x01", encoding=encoding_for(DiagnosticStatus))
            raw.put("test/other/b", encode(ClockMsg()), encoding=encoding_for(ClockMsg))
            return got

        wait_until(sent, 10, "the Clock message")
        assert b.bad_input["test/other/a"] == 0
    finally:
        raw.close()


@pytest.mark.timeout(60)
def test_node_liveliness_diagnostics_and_clean_close(make_node, zenoh_router):
    a = make_node("lively", vehicle="uav7")
    assert a.key("state/vehicle") == "uav7/state/vehicle"
    watcher = zenoh_client(zenoh_router)
    try:
        token = f"{LIVELINESS_ROOT}/uav7/lively"

        def alive() -> bool:
            return any(r.ok is not None for r in watcher.liveliness().get(token, timeout=1.0))

        wait_until(alive, 10, "the liveliness token")
        diags: list[DiagnosticStatus] = []
        sub = watcher.declare_subscriber("uav7/diagnostics/lively",
                                         lambda s: diags.append(decode(s.payload.to_bytes(), DiagnosticStatus)))
        a.set_health(lambda: Health(DiagnosticStatus.OK, "fine", {"answer": 42}))
        wait_until(lambda: diags, 5, "diagnostics at 1 Hz")
        d = diags[-1]
        assert d.name == "lively" and d.hardware_id == "uav7" and d.level == DiagnosticStatus.OK
        assert d.values["answer"] == "42" and d.values["invalid_msgs"] == "0"
        sub.undeclare()
        t0 = time.monotonic()
        a.close()
        assert time.monotonic() - t0 < 2.0
        wait_until(lambda: not alive(), 5, "the token to disappear after close")
        a.close()  # idempotent
    finally:
        watcher.close()


@pytest.mark.timeout(60)
def test_node_timer_error_counted(make_node):
    a = make_node("timed")
    n = [0]

    def tick():
        n[0] += 1
        raise RuntimeError("tick failed")

    a.every(0.02, tick, name="work")
    wait_until(lambda: a.callback_errors["timer:work"] >= 3, 5, "timer errors")
    vals = a.diagnostics().values
    assert int(vals["callback_errors"]) >= 3 and int(vals["loop[work].ticks"]) >= 3


# ---------------------------------------------------------------- request / response


def _arm_handler(req: ArmRequest) -> ArmReply:
    if req.force:
        raise RuntimeError("handler bug")
    return ArmReply(success=True, message="armed" if req.arm else "disarmed", armed=req.arm)


@pytest.mark.timeout(60)
def test_serve_call_round_trip_and_failures(make_node):
    srv, cli = make_node("fmu_fake"), make_node("client")
    srv.serve("test/srv/arm", ArmRequest, ArmReply, _arm_handler)

    def answered():
        try:
            return cli.call("test/srv/arm", ArmRequest(arm=True), ArmReply, timeout_s=2.0)
        except CallError:
            return None

    reply = wait_until(answered, 10, "the queryable to answer")
    assert reply.success and reply.armed and reply.message == "armed"
    # Invalid request (missing the required `arm` field): a failure reply, counted as bad input.
    bad = cli.call("test/srv/arm", Empty(), ArmReply)
    assert not bad.success and "invalid request" in bad.message
    assert srv.bad_input["test/srv/arm"] == 1
    # Raw garbage too.
    garbage = list(cli.session.get("test/srv/arm", payload=b"\xc1junk", timeout=2.0))
    assert len(garbage) == 1 and not decode(garbage[0].ok.payload.to_bytes(), ArmReply).success
    # A handler that raises: failure reply, counted as a callback error, service goes on.
    crash = cli.call("test/srv/arm", ArmRequest(arm=True, force=True), ArmReply)
    assert not crash.success and "internal error" in crash.message
    assert srv.callback_errors["test/srv/arm"] == 1
    assert cli.call("test/srv/arm", ArmRequest(arm=False), ArmReply).message == "disarmed"


@pytest.mark.timeout(30)
def test_call_missing_key_says_no_service(make_node):
    cli = make_node("lonely")
    t0 = time.monotonic()
    with pytest.raises(CallError, match="no service"):
        cli.call("test/srv/nobody_home", Empty(), ArmReply, timeout_s=3.0)
    assert time.monotonic() - t0 < 2.5  # known at once, not by timeout


@pytest.mark.timeout(30)
def test_call_async_delivers_reply_and_error(make_node):
    srv, cli = make_node("srv"), make_node("cli")
    srv.serve("test/srv/arm", ArmRequest, ArmReply, _arm_handler)
    wait_until(lambda: _try_call(cli), 10, "the queryable")
    got = []
    fut = cli.call_async("test/srv/arm", ArmRequest(arm=True), ArmReply, got.append)
    assert fut.result(5).armed and got and got[0].armed
    fut = cli.call_async("test/srv/missing", Empty(), ArmReply)
    assert isinstance(fut.result(5), CallError)


def _try_call(cli) -> bool:
    try:
        return cli.call("test/srv/arm", ArmRequest(arm=True), ArmReply, 1.0).success
    except CallError:
        return False


# ---------------------------------------------------------------- live parameters


@pytest.mark.timeout(60)
def test_live_params_set_list_put_and_reject(make_node, zenoh_router):
    svc = make_node("tuned", params=[Param("gain", 1.0, "", 0.0, 5.0), Param("name", "a"),
                                     Param("mode", "x", start_only=True)])
    cli = make_node("operator")
    changes = []
    svc.params.on_change(lambda n, v: changes.append((n, v)))

    def listed():
        try:
            return cli.call("config/tuned/@params", None, ParamList, 1.0)
        except CallError:
            return None

    plist = wait_until(listed, 10, "config/tuned/@params")
    assert plist.service == "tuned"
    gain = {p.name: p for p in plist.params}["gain"]
    assert (gain.value, gain.default, gain.min, gain.max, gain.type) == (1.0, 1.0, 0.0, 5.0, "float")

    ok = cli.call("config/tuned/@set", ParamSetMsg(name="gain", value=2.5), ParamSetReply)
    assert ok.success and ok.value == 2.5 and svc.params["gain"] == 2.5
    bad = cli.call("config/tuned/@set", ParamSetMsg(name="gain", value=50), ParamSetReply)
    assert not bad.success and "above the maximum" in bad.message and bad.value == 2.5
    assert svc.params["gain"] == 2.5 and svc.params_rejected == 1
    unknown = cli.call("config/tuned/@set", ParamSetMsg(name="nope", value=1), ParamSetReply)
    assert not unknown.success and "unknown parameter" in unknown.message
    start_only = cli.call("config/tuned/@set", ParamSetMsg(name="mode", value="y"), ParamSetReply)
    assert not start_only.success and "read at start only" in start_only.message and start_only.value == "x"
    assert {p.name: p.start_only for p in listed().params} == {"gain": False, "name": False, "mode": True}
    assert svc.diagnostics().values["params_rejected"] == "3"

    # Fire-and-forget put on config/<service>/<name> (the name comes from the key).
    raw = zenoh_client(zenoh_router)
    try:
        wait_until(lambda: raw.put("config/tuned/gain", encode(ParamSetMsg(value=4.0)),
                                   encoding=encoding_for(ParamSetMsg)) or svc.params["gain"] == 4.0,
                   10, "the put to apply")
        wait_until(lambda: raw.put("config/tuned/gain", b"\xc1garbage") or svc.bad_input["config/tuned/gain"],
                   10, "garbage on the config key to be counted")
        assert svc.params["gain"] == 4.0
    finally:
        raw.close()
    assert ("gain", 2.5) in changes and ("gain", 4.0) in changes


# ================================================================ actions


class _Takeoff:
    """A tiny action server: rejects goals above 100 m, records accepted goals."""

    def __init__(self, node):
        self.handles = []
        self.cancel_asked = []
        self.server = ActionServer(node, "test/action/takeoff", TakeoffGoal, TakeoffResult,
                                   self.on_goal, self.on_cancel)

    def on_goal(self, h):
        if h.goal.target_altitude_m > 100:
            return "target altitude above the 100 m ceiling"
        self.handles.append(h)
        return None

    def on_cancel(self, h):
        self.cancel_asked.append(h.goal_id)
        return True


def _action_pair(make_node):
    srv_node, cli_node = make_node("mission_fake"), make_node("gcs_fake")
    server = _Takeoff(srv_node)
    client = ActionClient(cli_node.session, "test/action/takeoff", TakeoffGoal)

    def ready():
        try:
            call(cli_node.session, "test/action/takeoff/result", ResultRequest(goal_id="x"), ActionResult, 1.0)
            return True
        except CallError:
            return False

    wait_until(ready, 10, "the action server's queryables")
    return srv_node, server, client


def _feed_until(handle, got, fb, what="feedback"):
    wait_until(lambda: handle.feedback(fb) or got, 10, what)


@pytest.mark.timeout(60)
def test_action_goal_feedback_result(make_node):
    srv_node, server, client = _action_pair(make_node)
    feedback = []
    reply = client.send_goal(TakeoffGoal(target_altitude_m=10.0), feedback.append)
    assert isinstance(reply, GoalReply) and reply.accepted and reply.goal_id
    assert reply.status == GoalStatus.ACCEPTED
    h = server.handles[0]
    assert h.goal_id == reply.goal_id and h.goal.target_altitude_m == 10.0
    _feed_until(h, feedback, TakeoffFeedback(current_altitude_m=4.0, progress_percent=40.0))
    fb = feedback[0]
    assert fb.goal_id == reply.goal_id and fb.action == "takeoff" and fb.status == GoalStatus.EXECUTING
    assert fb.unwrap().current_altitude_m == 4.0
    h.succeed(TakeoffResult(success=True, message="reached", final_altitude_m=10.1))
    res = client.result(reply.goal_id, timeout_s=5.0)
    assert res.status == GoalStatus.SUCCEEDED and res.success and res.message == "reached"
    assert res.unwrap().final_altitude_m == 10.1 and isinstance(res.unwrap(), TakeoffResult)
    assert not h.active and server.server.active_goals() == []
    h.abort(TakeoffResult(message="late"))  # finishing twice is ignored
    assert server.server.results[reply.goal_id].status == GoalStatus.SUCCEEDED
    client.close()


@pytest.mark.timeout(60)
def test_action_rejected_and_invalid_goals(make_node):
    srv_node, server, client = _action_pair(make_node)
    reply = client.send_goal(TakeoffGoal(target_altitude_m=500.0))
    assert not reply.accepted and reply.status == GoalStatus.REJECTED
    assert "ceiling" in reply.message and reply.goal_id == ""
    assert server.handles == []
    # A goal that fails validation (negative altitude, sent as a raw map) is refused, not fatal.
    bad = list(client.session.get("test/action/takeoff/goal",
                                  payload=msgpack.packb({"target_altitude_m": -3.0}), timeout=2.0))
    r = decode(bad[0].ok.payload.to_bytes(), GoalReply)
    assert not r.success and "invalid request" in r.message
    assert srv_node.bad_input["test/action/takeoff/goal"] == 1
    client.close()


@pytest.mark.timeout(60)
def test_action_cancel(make_node):
    srv_node, server, client = _action_pair(make_node)
    feedback = []
    reply = client.send_goal(TakeoffGoal(target_altitude_m=20.0), feedback.append)
    h = server.handles[0]
    c = client.cancel(reply.goal_id)
    assert isinstance(c, CancelReply) and c.success and c.status == GoalStatus.CANCELING
    assert server.cancel_asked == [reply.goal_id] and h.cancel_requested
    _feed_until(h, feedback, TakeoffFeedback(current_altitude_m=2.0))
    assert feedback[-1].status == GoalStatus.CANCELING
    h.canceled(TakeoffResult(success=False, message="cancelled by operator", final_altitude_m=2.0))
    res = client.result(reply.goal_id, timeout_s=5.0)
    assert res.status == GoalStatus.CANCELED and not res.success
    again = client.cancel(reply.goal_id)
    assert not again.success and "already finished" in again.message
    unknown = client.cancel("no-such-goal")
    assert not unknown.success and "unknown goal" in unknown.message
    client.close()


@pytest.mark.timeout(60)
def test_action_cancel_refused_by_server(make_node):
    srv_node, server, client = _action_pair(make_node)
    server.server.on_cancel = lambda h: False
    reply = client.send_goal(TakeoffGoal(target_altitude_m=20.0))
    c = client.cancel(reply.goal_id)
    assert not c.success and "cannot be cancelled" in c.message
    assert server.handles[0].active
    client.close()


@pytest.mark.timeout(60)
def test_action_result_queried_after_the_fact(make_node):
    srv_node, server, client = _action_pair(make_node)
    reply = client.send_goal(TakeoffGoal(target_altitude_m=5.0))
    client.close()  # nobody listens while the goal finishes
    running = call(srv_node.session, "test/action/takeoff/result", ResultRequest(goal_id=reply.goal_id),
                   ActionResult)
    assert not running.success and running.status == GoalStatus.ACCEPTED and "still running" in running.message
    server.handles[0].abort(TakeoffResult(success=False, message="motor fault"))
    late = ActionClient(make_node("late_gcs").session, "test/action/takeoff")
    t0 = time.monotonic()
    res = late.result(reply.goal_id, timeout_s=5.0)  # missed the publication: falls back to the query
    assert time.monotonic() - t0 < 3.0
    assert res.status == GoalStatus.ABORTED and res.message == "motor fault"
    unknown = call(srv_node.session, "test/action/takeoff/result", ResultRequest(goal_id="nope"), ActionResult)
    assert unknown.status == GoalStatus.UNKNOWN and "unknown goal" in unknown.message
    with pytest.raises(CallError, match="no result"):
        late.result("nope", timeout_s=1.0)
    late.close()


# ================================================================ supervision (one instance, parent death, priority)

import os  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

from aeroperception.services.runtime import Node  # noqa: E402
from aeroperception.services.runtime.supervision import (  # noqa: E402
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
