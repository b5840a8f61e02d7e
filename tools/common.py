"""Shared pieces of the `aero` commands: one error type printed as one line, the client
session, and YAML/JSON helpers for showing and entering messages."""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from typing import Any

import yaml
import zenoh

from aeroperception.schemas import NDArray, SchemaError, to_builtins
from aeroperception.services.runtime.session import ZenohConfigError, make_config, open_session


class CliError(Exception):
    """A user-facing failure: printed as `aero: <message>` with exit code 2, no traceback."""


class TrailingPositionalParser(argparse.ArgumentParser):
    """A parser whose optional positionals (`DATA` in `topic pub KEY [DATA]`) may also come after
    the options: `topic pub KEY --type T DATA` as well as `topic pub KEY DATA --type T`.

    argparse fills positionals in one pass over the first run of bare words, so a word that
    follows an option is otherwise "unrecognized"; and `parse_intermixed_args` cannot be used
    under sub-commands. Leftover bare words fill the still-unset `?` positionals in order.
    """

    def parse_known_args(self, args=None, namespace=None):
        ns, extras = super().parse_known_args(args, namespace)
        for action in self._positionals._group_actions:
            if action.nargs != "?" or getattr(ns, action.dest, None) is not action.default:
                continue
            word = next((w for w in extras if not w.startswith("-") or w == "-"), None)
            if word is None:
                break
            extras.remove(word)
            setattr(ns, action.dest, word)
        return ns, extras


# ---------------------------------------------------------------- stdout that may close

_stdout_lock = threading.Lock()
stdout_closed = threading.Event()
"""Set once the reader of stdout went away (`aero ... | head -1`): stop producing output."""

EXIT_BROKEN_PIPE = 141
"""Exit code when stdout's reader went away: 128 + SIGPIPE, what `yes | head` reports."""


def emit(text: str) -> bool:
    """Print `text` (a newline is added) and flush, from any thread. False once stdout's reader
    has gone; stdout is then pointed at /dev/null so nothing (not even interpreter shutdown's
    final flush) raises BrokenPipeError again."""
    with _stdout_lock:
        if stdout_closed.is_set():
            return False
        try:
            sys.stdout.write(text + "\n")
            sys.stdout.flush()
            return True
        except BrokenPipeError:
            silence_stdout()
            return False


def silence_stdout() -> None:
    """The reader of stdout is gone: redirect the fd to /dev/null and remember it."""
    stdout_closed.set()
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def add_session_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", default=None, metavar="ENDPOINT",
                   help="router endpoint, e.g. tcp/10.0.0.2:7447 (env AERO_CONNECT)")
    p.add_argument("--zenoh-config", default=None, metavar="FILE", help="Zenoh json5 config")
    p.add_argument("--vehicle", default=os.environ.get("AERO_VEHICLE", ""),
                   help="vehicle key prefix (env AERO_VEHICLE)")


def open_client(args: argparse.Namespace, wait_s: float = 3.0) -> zenoh.Session:
    try:
        conf = make_config(args.zenoh_config, args.connect)
    except ZenohConfigError as e:
        raise CliError(str(e)) from None
    session = open_session(conf, max_wait_s=wait_s)
    if session is None:
        where = conf.get_json("connect/endpoints")
        if "tls/" in where:  # a secured router refuses a client it cannot authenticate: same symptom
            raise CliError(f"no Zenoh router reachable at {where}, or it refused this client: check the "
                           "router runs and that AERO_ZENOH_CONFIG/--zenoh-config is your role's config "
                           "(its CA, certificate and password; `aero certs` writes them)")
        raise CliError(f"no Zenoh router reachable at {where}: start the stack with `aero up` "
                       "(or `aero router`), or point --connect at a running router")
    return session


def full_key(args: argparse.Namespace, key: str) -> str:
    key = key.strip("/")
    return f"{args.vehicle}/{key}" if getattr(args, "vehicle", "") and not key.startswith(args.vehicle + "/") else key


def parse_data(text: str) -> Any:
    """YAML or JSON (JSON is YAML) from the command line."""
    try:
        return yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as e:
        raise CliError(f"cannot parse {text!r} as YAML/JSON: {str(e).splitlines()[0]}") from None


def summarize(obj: Any) -> Any:
    """Plain data for display: arrays become a one-line summary instead of raw bytes."""
    if isinstance(obj, NDArray):
        obj = to_builtins(obj)
    if isinstance(obj, dict):
        if set(obj) == {"dtype", "shape", "data"}:
            return _summarize_array(obj)
        return {k: summarize(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [summarize(v) for v in obj]
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return f"<{len(obj)} bytes>"
    return obj


def _summarize_array(d: dict) -> Any:
    import numpy as np

    try:
        a = np.frombuffer(bytes(d["data"]), dtype=d["dtype"]).reshape(d["shape"])
    except (TypeError, ValueError):
        return f"<array {d['dtype']} {d['shape']} (inconsistent)>"
    if a.size <= 36:
        return a.tolist()
    if a.size and np.issubdtype(a.dtype, np.number):
        return f"<array {a.dtype} {list(a.shape)} min={a.min():.4g} max={a.max():.4g} mean={a.mean():.4g}>"
    return f"<array {a.dtype} {list(a.shape)}>"


def dump(obj: Any, as_json: bool) -> str:
    if as_json:
        return json.dumps(obj, default=str)
    return yaml.safe_dump(obj, sort_keys=False, default_flow_style=None, width=120).rstrip() + "\n---"


__all__ = ["CliError", "SchemaError", "TrailingPositionalParser", "emit", "silence_stdout", "stdout_closed",
           "EXIT_BROKEN_PIPE", "add_session_arguments", "open_client", "full_key",
           "parse_data", "summarize", "dump", "FlightWatch"]


class FlightWatch:
    """One flight per sim truth: armed above 0.5 m, then disarmed below 0.2 m
    (`aero eval vio|detector --live --until-landed`)."""

    def __init__(self):
        self.flew = threading.Event()
        self.down = threading.Event()

    def update(self, armed: bool, z_m: float) -> None:
        if armed and z_m > 0.5:
            self.flew.set()
        elif self.flew.is_set() and not armed and z_m < 0.2:
            self.down.set()

    def wait(self, duration_s: float, until_landed: bool) -> None:
        """Block for `duration_s`, or (`until_landed`) until the flight is down, whichever is first."""
        end = time.monotonic() + duration_s
        while time.monotonic() < end and not (until_landed and self.down.is_set()):
            time.sleep(0.1)

    def on_sample(self, sample) -> None:
        """Subscriber callback for sim/truth/state (payloads that do not decode are skipped)."""
        from aeroperception.schemas import VehicleState, decode

        try:
            m = decode(sample.payload.to_bytes(), VehicleState)
        except SchemaError:
            return
        self.update(m.armed, m.position_m.z)
