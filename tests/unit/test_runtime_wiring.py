"""Node.bind over a real in-process Zenoh router (no mocks): the contract declares every
subscriber, publisher and queryable with its QoS and strictness, and a disagreement between code
and contract is refused at start in one line. Also the configs built from parameters
(runtime/config.py) and their one on_config."""
from __future__ import annotations

import functools
import time
import types
from dataclasses import dataclass

import msgpack
import pytest
import zenoh

from aerotest import wait_until, zenoh_client

from aeroperception.schemas import ArmReply, ArmRequest, Clock as ClockMsg, encode
from aeroperception.services.runtime import (
    BULK, EXPRESS, SMALL, ConfigError, Param, ParamError, Queries, Query, Service, Topic, Topics, WiringError,
    param, section,
)
from aeroperception.services.runtime.config import build, check_covers
from aeroperception.services.runtime.keys import handler_name
from aeroperception.services.runtime.node import encoding_for
from aeroperception.services.runtime.params import ParamSet
from aeroperception.services.runtime.wiring import check_handlers


def contract(**kw) -> types.SimpleNamespace:
    base = dict(NAME="demo", INPUTS=Topics(), OUTPUTS=Topics(), SERVICES=Queries())
    return types.SimpleNamespace(**{**base, **kw})


DEMO = contract(
    INPUTS=Topics(Topic("test/clock", ClockMsg), Topic("test/command", ClockMsg, strict=True, handler="take_command")),
    OUTPUTS=Topics(Topic("test/fast", ClockMsg, qos=SMALL), Topic("test/frames", ClockMsg, qos=BULK),
                   Topic("test/setpoint", ClockMsg, qos=EXPRESS), Topic("test/plain", ClockMsg)),
    SERVICES=Queries(Query("test/srv/arm", ArmRequest, ArmReply)),
)


class Demo:
    def __init__(self):
        self.clocks: list[ClockMsg] = []
        self.commands: list[ClockMsg] = []

    def on_test_clock(self, msg: ClockMsg) -> None:
        self.clocks.append(msg)

    def take_command(self, msg: ClockMsg) -> None:
        self.commands.append(msg)

    def on_test_arm(self, req: ArmRequest) -> ArmReply:
        return ArmReply(success=True, message=f"arm={req.arm}")


def test_handler_names_derive_from_the_key():
    assert handler_name("state/vehicle") == "on_state_vehicle"
    assert handler_name("planner/srv/select_plugin") == "on_planner_select_plugin"
    assert handler_name("diagnostics/*") == "on_diagnostics"
    assert handler_name("sensors/camera/<side>/image") == "on_sensors_camera_image"


def test_an_input_without_a_handler_is_refused_naming_the_method():
    class NoClock(Demo):
        on_test_clock = None

    with pytest.raises(WiringError, match=r"^demo: INPUTS 'test/clock' has no handler: define on_test_clock\(msg\)"):
        check_handlers(DEMO, NoClock())


def test_a_queryable_without_a_handler_is_refused():
    with pytest.raises(WiringError, match="SERVICES 'test/srv/arm' has no handler: define on_test_arm"):
        check_handlers(DEMO, {"on_test_clock": print, "take_command": print})


def test_a_handler_no_declared_key_feeds_is_refused():
    class Extra(Demo):
        def on_test_gone(self, msg) -> None:
            pass

    with pytest.raises(WiringError, match="handler on_test_gone matches no input or service"):
        check_handlers(DEMO, Extra())


def test_a_selected_key_the_contract_lacks_is_refused():
    with pytest.raises(WiringError, match="test/nope not in its contract's INPUTS"):
        check_handlers(DEMO, Demo(), inputs=["test/nope"])


@pytest.mark.timeout(60)
def test_bind_declares_inputs_outputs_and_queryables_from_the_contract(make_node):
    svc, other = Demo(), make_node("other")
    node = make_node("demo")
    io = node.bind(DEMO, svc)
    assert set(io) == set(DEMO.OUTPUTS)
    with pytest.raises(WiringError, match="demo: no publisher for 'test/undeclared': its contract's OUTPUTS lacks it"):
        io["test/undeclared"]
    pub = other.publisher("test/clock", ClockMsg)
    wait_until(lambda: pub.publish(ClockMsg(speed_factor=2.0)) or svc.clocks, 10, "the input at its handler")
    reply = other.call("test/srv/arm", ArmRequest(arm=True), ArmReply, timeout_s=5.0)
    assert reply.success and reply.message == "arm=True"


@pytest.mark.timeout(60)
def test_qos_declared_on_the_topic_is_what_subscribers_see(make_node, zenoh_router):
    node = make_node("demo")
    io = node.bind(DEMO, Demo())
    raw = zenoh_client(zenoh_router)
    try:
        seen: dict[str, zenoh.Sample] = {}
        sub = raw.declare_subscriber("test/*", lambda s: seen.setdefault(str(s.key_expr), s))

        def all_seen():
            for key in DEMO.OUTPUTS:
                io[key].publish(ClockMsg())
            return len(seen) == len(DEMO.OUTPUTS)

        wait_until(all_seen, 10, "a sample of every output")
        got = {k: (s.priority, s.express) for k, s in seen.items()}
        assert got == {"test/fast": (zenoh.Priority.DATA_HIGH, True), "test/frames": (zenoh.Priority.DATA_LOW, False),
                       "test/setpoint": (zenoh.Priority.DATA, True), "test/plain": (zenoh.Priority.DATA, False)}
        assert all(s.congestion_control == zenoh.CongestionControl.DROP for s in seen.values())
        sub.undeclare()
    finally:
        raw.close()


@pytest.mark.timeout(60)
def test_a_strict_input_refuses_unknown_fields_a_lenient_one_takes_them(make_node, zenoh_router):
    svc, node = Demo(), make_node("demo")
    node.bind(DEMO, svc)
    raw = zenoh_client(zenoh_router)
    try:
        extra = msgpack.packb({"speed_factor": 2.0, "from_the_future": 1})

        def sent():
            raw.put("test/command", extra, encoding=encoding_for(ClockMsg))
            raw.put("test/clock", extra, encoding=encoding_for(ClockMsg))
            return svc.clocks and node.bad_input["test/command"]

        wait_until(sent, 10, "the lenient input delivered and the strict one refused")
        assert not svc.commands
        wait_until(lambda: raw.put("test/command", encode(ClockMsg(speed_factor=3.0)),
                                   encoding=encoding_for(ClockMsg)) or svc.commands, 10, "a valid command")
    finally:
        raw.close()


class Tabled(Service):
    """Inputs delivered through one table ({handler name: callable}), bound in two steps: the
    selection at start, one more input when a live change turns it on."""

    NAME, CONTRACT = "demo", DEMO

    def start(self) -> None:
        self.got: list[tuple[str, ClockMsg]] = []

    def handlers(self):
        return {DEMO.INPUTS.declared[k].handler_name: functools.partial(self._on_input, k) for k in DEMO.INPUTS}

    def bind_selection(self):
        return {"inputs": ["test/clock"], "services": []}

    def _on_input(self, key: str, msg: ClockMsg) -> None:
        self.got.append((key, msg))


def test_a_table_of_handlers_is_checked_like_methods():
    table = Tabled.handlers(object.__new__(Tabled))
    assert set(check_handlers(DEMO, table, services=[])) == {("INPUTS", "test/clock"), ("INPUTS", "test/command")}
    with pytest.raises(WiringError, match="handler on_test_gone matches no input"):
        check_handlers(DEMO, {**table, "on_test_gone": print}, services=[])
    with pytest.raises(WiringError, match="SERVICES 'test/srv/arm' has no handler"):
        check_handlers(DEMO, table)


@pytest.mark.timeout(60)
def test_a_service_binds_its_table_at_start_and_more_inputs_later(make_node):
    other = make_node("other")
    svc = Tabled(make_node("demo"), None)
    svc.launch()
    assert set(svc.io) == set(DEMO.OUTPUTS)
    clock, command = other.publisher("test/clock", ClockMsg), other.publisher("test/command", ClockMsg)
    wait_until(lambda: clock.publish(ClockMsg(speed_factor=2.0)) or svc.got, 10, "the selected input at its handler")
    command.publish(ClockMsg(speed_factor=3.0))
    time.sleep(0.3)
    assert {k for k, _ in svc.got} == {"test/clock"}        # not selected: not subscribed
    svc.bind_inputs(["test/command"])
    wait_until(lambda: command.publish(ClockMsg(speed_factor=3.0)) or any(k == "test/command" for k, _ in svc.got),
               10, "the input bound later at its handler")


# ---------------------------------------------------------------- configs from parameters

PARAMS = [Param("speed_mps", 2.0, "m/s", 0.1, 5.0), Param("gain", 0.5), Param("mode", "a", choices=("a", "b"))]


@dataclass(frozen=True)
class Inner:
    gain: float = param("gain")
    fixed: float = 4.0


@dataclass(frozen=True)
class Cfg:
    inner: Inner = section(Inner)
    speed_mps: float = param("speed_mps")
    mode: str = param("mode")


def test_a_config_is_built_from_the_declared_defaults_and_overrides():
    assert build(Cfg, PARAMS) == Cfg(Inner(0.5), 2.0, "a")
    assert build(Cfg, PARAMS, mode="b").mode == "b"
    with pytest.raises(ConfigError, match="has no field nope"):
        build(Cfg, PARAMS, nope=1)


def test_a_parameter_no_config_field_references_is_refused():
    check_covers(Cfg, PARAMS)
    with pytest.raises(ConfigError, match="parameter extra_m is declared but no field of Cfg references it"):
        check_covers(Cfg, [*PARAMS, Param("extra_m", 1.0)], "demo")
    with pytest.raises(ConfigError, match="references parameter gain, which the contract does not declare"):
        check_covers(Cfg, PARAMS[:1] + PARAMS[2:])


class Configured(Service):
    NAME, PARAMS, CONFIG = "demo", PARAMS, Cfg

    def start(self) -> None:
        self.seen: list[Cfg] = []

    def on_config(self, cfg: Cfg) -> None:
        if cfg.mode == "b" and cfg.speed_mps > 3.0:
            raise ParamError("mode b only up to 3 m/s")
        self.seen.append(cfg)


def _started() -> Configured:
    node = types.SimpleNamespace(params=ParamSet.from_declarations(PARAMS), log=None)
    svc = Configured(node, None)
    svc.wire()
    svc.start()
    svc._configured = True
    return svc


def test_a_live_change_rebuilds_the_config_and_calls_on_config_once():
    svc = _started()
    svc.params.apply("gain", 0.7)
    assert svc.seen == [Cfg(Inner(0.7), 2.0, "a")] and svc.cfg == svc.seen[0]


def test_on_config_refusing_keeps_the_old_value_and_config():
    svc = _started()
    svc.params.apply("speed_mps", 4.0)
    with pytest.raises(ParamError, match="only up to 3"):
        svc.params.apply("mode", "b")
    assert svc.params.mode == "a" and svc.cfg.mode == "a"


def _positive_name(text: str) -> str:
    if not text.strip():
        raise ValueError("name: must not be empty")
    return text.strip()


@dataclass(frozen=True)
class Named:
    name: str = param("name", _positive_name)


class NamedService(Service):
    NAME, PARAMS, CONFIG = "demo", [Param("name", "x")], Named


def test_a_value_a_field_conversion_refuses_is_refused_as_a_parameter_error():
    node = types.SimpleNamespace(params=ParamSet.from_declarations(NamedService.PARAMS), log=None)
    svc = NamedService(node, None)
    svc.wire()
    svc._configured = True
    with pytest.raises(ParamError, match="must not be empty"):
        svc.params.apply("name", "  ")
    assert svc.params.name == "x" and svc.cfg == Named("x")
