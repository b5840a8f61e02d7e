"""Node over a real in-process Zenoh router (no mocks): typed pub/sub, encodings, liveliness,
diagnostics, request/response and live parameters."""
from __future__ import annotations

import time

import msgpack
import pytest
import zenoh

from aerotest import wait_until, zenoh_client

from aeroperception.schemas import (
    ArmReply, ArmRequest, Clock as ClockMsg, DiagnosticStatus, Empty, Header,
    ParamList, ParamSet as ParamSetMsg, ParamSetReply, encode, decode,
)
from aeroperception.services.runtime import (
    CallError, Health, Param,
)
from aeroperception.services.runtime.node import LIVELINESS_ROOT, encoding_for


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
