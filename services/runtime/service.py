"""The thin shell every service process shares: parse the common flags, open the Node, start
the service's logic, wait for SIGINT/SIGTERM, stop cleanly within 2 s.

A service is a subclass of `Service` declaring NAME, PARAMS (and optionally extra CLI flags);
its module's `main()` is `run(MyService)`. One that declares CONTRACT (its contract module) is
wired from it before start(): `self.io[key]` is each output's publisher and each input is
delivered to its handler (wiring.py); one that declares CONFIG gets `self.cfg` built from its
parameters and one `on_config(cfg)` on a live change (config.py). `aero run NAME` and `python -m
aeroperception.services.NAME` both end up here.

Stack dumps: a crash in native code (SIGSEGV/SIGABRT in zenoh, OpenCV, Open3D, ONNX Runtime...)
writes every thread's Python stack to the service's log, and `kill -USR1 <pid>` does the same on
demand for a service that looks stuck — it keeps running.
"""
from __future__ import annotations

import argparse
import faulthandler
import importlib
import os
import signal
import sys
from typing import Any, ClassVar, Iterable, Sequence

from .config import build, check_covers
from .node import Health, Node
from .params import Param, ParamError, parse_overrides
from .session import ZenohConfigError
from .signals import ShutdownFlag
from .supervision import EXIT_DUPLICATE, DuplicateInstanceError, bind_to_supervisor


SWITCH_INTERVAL_S = 0.0005


class Service:
    """Base of every service. Subclasses declare the contract and implement start()/stop()."""

    NAME: ClassVar[str] = ""
    PARAMS: ClassVar[list[Param]] = []
    # % of one core this service should stay within (cpu.py: WARN when the 10 s mean exceeds it);
    # None: the CPU_BUDGET_PCT of the contract.py beside the service's module, if it declares one.
    CPU_BUDGET_PCT: ClassVar[float | None] = None
    # The contract module (NAME, INPUTS, OUTPUTS, SERVICES): wired by `wire()` before start().
    CONTRACT: ClassVar[Any] = None
    # A config dataclass whose fields reference PARAMS (config.param): `self.cfg`, `on_config`.
    CONFIG: ClassVar[type | None] = None

    def __init__(self, node: Node, args: argparse.Namespace):
        self.node = node
        self.args = args
        self.params = node.params
        self.log = node.log
        self.cfg: Any = None
        self.io: Any = None
        self._configured = False

    def wire(self) -> None:
        """Before start(), holding node.lock (so no input is delivered before start() is done):
        the config built from the parameters, then the contract's keys declared and bound.
        Raises (config.ConfigError, wiring.WiringError) when code and contract disagree."""
        if self.CONFIG is not None:
            check_covers(self.CONFIG, self.PARAMS, self.NAME)
            self.cfg = build(self.CONFIG, self.params)
            self.params.on_change(self._reconfigure)
        if self.CONTRACT is not None:
            self.io = self.node.bind(self.CONTRACT, self.handlers(), **self.bind_selection())

    def launch(self) -> None:
        """wire() then start(), holding node.lock: what `run` does, for a caller that owns the
        Node and its lifetime (`aero record`, a test)."""
        with self.node.lock:
            self.wire()
            self.start()
            self._configured = True

    def bind_selection(self) -> dict[str, Any]:
        """Which of the contract's keys this run binds (inputs=, outputs=, services=: key lists);
        {} = all of them. For keys only some modes use (the simulator's --follow)."""
        return {}

    def handlers(self) -> Any:
        """What the contract's inputs and queryables are delivered to: this service (its
        on_<key> methods), or a {handler name: callable} mapping for a service whose inputs all go
        through one table (viz's adapters, ros2bridge's topics): every name must be a declared
        input's or queryable's handler name, and every bound one must be in it."""
        return self

    def bind_inputs(self, keys: Iterable[str]) -> None:
        """Subscribe more of the contract's inputs after start, with their handlers: inputs the
        selection left out that a live change turns on (a viz rate raised from 0)."""
        self.node.bind(self.CONTRACT, self.handlers(), inputs=keys, outputs=(), services=())

    def _reconfigure(self, _name: str, _value: Any) -> None:
        """A parameter changed: the whole config anew, one on_config (after start; during start()
        the config is only rebuilt). A ParamError from on_config, or a ValueError from a field's
        conversion, refuses the change."""
        assert self.CONFIG is not None   # registered only when there is a config
        try:
            cfg: Any = build(self.CONFIG, self.params)
        except ValueError as e:     # a field's conversion refused the value (a polygon that does not parse)
            raise ParamError(str(e)) from None
        if cfg == self.cfg:
            return
        if self._configured:
            self.on_config(cfg)
        self.cfg = cfg

    def on_config(self, cfg: Any) -> None:
        """The config changed live (self.cfg is still the old one while this runs): take it, or
        raise ParamError to refuse it."""

    @classmethod
    def add_arguments(cls, parser: argparse.ArgumentParser) -> None:
        """Service-specific command-line flags (beyond the common ones)."""

    def start(self) -> None:
        """Declare subscriptions, publishers, queryables and loops."""

    def health(self) -> Health:
        """Called once a second for diagnostics/<service>."""
        return Health()

    def stop(self) -> None:
        """Release resources (files, sockets); called once, before the session closes."""


def cpu_budget(service_cls: type[Service]) -> float | None:
    """The service's CPU budget: its class's, else its package's contract.CPU_BUDGET_PCT."""
    if service_cls.CPU_BUDGET_PCT is not None:
        return service_cls.CPU_BUDGET_PCT
    package = service_cls.__module__.rpartition(".")[0]
    try:
        contract = importlib.import_module(f"{package}.contract") if package else None
    except ModuleNotFoundError as e:
        if e.name != f"{package}.contract":
            raise
        return None
    return getattr(contract, "CPU_BUDGET_PCT", None)


def common_parser(prog: str, description: str = "") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=description)
    add_common_arguments(p)
    return p


def add_common_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("stack")
    g.add_argument("--connect", default=None, metavar="ENDPOINT",
                   help="Zenoh router to connect to, e.g. tcp/10.0.0.2:7447 (env AERO_CONNECT)")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="Zenoh json5 config (env AERO_ZENOH_CONFIG; default ./zenoh.json5)")
    g.add_argument("--vehicle", default=os.environ.get("AERO_VEHICLE", ""),
                   help="key prefix so several vehicles share one network (env AERO_VEHICLE)")
    g.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="override a parameter (repeatable)")
    g.add_argument("--params", default=os.environ.get("AERO_PARAMS"), metavar="FILE",
                   help="YAML parameter file ({service: {name: value}} or flat)")
    g.add_argument("--sim-time", action="store_true", default=os.environ.get("AERO_SIM_TIME") == "1",
                   help="follow sim/clock instead of wall time (env AERO_SIM_TIME=1)")
    g.add_argument("--log-level", default=os.environ.get("AERO_LOG_LEVEL", "info"),
                   choices=["debug", "info", "warn", "error"])


def run(service_cls: type[Service], argv: Sequence[str] | None = None) -> int:
    """Run one service in the foreground until SIGINT/SIGTERM. Returns the exit code."""
    parser = common_parser(f"aero run {service_cls.NAME}", (service_cls.__doc__ or "").strip().split("\n")[0])
    service_cls.add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        node = Node(service_cls.NAME, params=service_cls.PARAMS, vehicle=args.vehicle,
                    zenoh_config=args.zenoh_config, connect=args.connect,
                    log_level=args.log_level, sim_time=args.sim_time,
                    cpu_budget_pct=cpu_budget(service_cls))
        if args.params:
            node.params.load_file(args.params, service_cls.NAME)
        node.params.update(parse_overrides(args.param))
    except (ParamError, ZenohConfigError) as e:
        print(f"aero run {service_cls.NAME}: {e}", file=sys.stderr)
        return 2

    # The handler only records the signal (see signals.py): logging or Event.set() in a
    # handler can deadlock against the main thread.
    shutdown = ShutdownFlag(node.stop_event).install()
    faulthandler.enable(all_threads=True)
    faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)
    # Started by `aero up`: stop when it dies (kill -9 included) instead of lingering unsupervised.
    binding = bind_to_supervisor(node.stop_event.set)
    if binding.orphaned:
        node.log.warn("supervisor_gone", note=binding.note)

    # A thread that becomes runnable waits up to the GIL switch interval (5 ms by default) while
    # another thread computes: that was the p99 of the state -> setpoint hot path. 0.5 ms keeps
    # callbacks responsive at a small throughput cost.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        if not node.connect(exclusive=True):
            node.close()
            return 0
    except DuplicateInstanceError as e:
        print(f"aero run {service_cls.NAME}: {e}", file=sys.stderr, flush=True)
        return EXIT_DUPLICATE
    service = service_cls(node, args)
    node.set_health(service.health)
    code = 0
    try:
        service.launch()
        shutdown.wait()
        if shutdown.signal_name:
            node.log.info("signal", signal=shutdown.signal_name)
    except Exception as e:  # noqa: BLE001 - report a start-up failure as one clear line
        node.log.error("fatal", error=f"{type(e).__name__}: {e}")
        code = 1
    finally:
        try:
            service.stop()
        except Exception as e:  # noqa: BLE001
            node.log.error("stop_failed", error=str(e))
        node.close()
    return code
