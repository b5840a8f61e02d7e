"""Zenoh configuration and session opening, shared by every service and `aero` command.

Precedence: --zenoh-config FILE > $AERO_ZENOH_CONFIG > ./zenoh.json5 > the default shipped in
this package (services/runtime/zenoh.json5; the repository root's zenoh.json5 is a symlink to
it, so an installed wheel and a checkout read the same file); then --connect / $AERO_CONNECT
replaces connect/endpoints. Zenoh's own defaults (peer mode, multicast scouting) are never used:
they would find no router and wait in silence.
A client opened before its router exists fails at once, so `open_session` retries with
back-off until connected or told to stop. An open client session reconnects by itself when its
router restarts (Zenoh re-declares its tokens, subscribers and queryables); RECONNECT makes it
try every 0.2-1 s instead of Zenoh's 1-4 s, unless the config file sets connect/retry.

$AERO_LINKS=direct (set by `aero up` for the services it starts on one host) makes a service's
session with no explicit mode a peer that connects to the router and listens on loopback: the
router introduces co-located peers to each other (gossip) and their samples take the direct link,
one hop instead of two (`aero bench pubsub --peers`, "peers+router"). The router stays the way in
for other hosts, the CLI and its ACLs. Unset or `router`: a client of the router.
"""
from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import zenoh

DEFAULT_CONFIG = Path(__file__).resolve().with_name("zenoh.json5")
RECONNECT = {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 1.5}
LINKS_ENV = "AERO_LINKS"
LINKS = ("router", "direct")
DIRECT_LISTEN = ["tcp/127.0.0.1:0"]   # loopback only: a direct link never leaves the host


class ZenohConfigError(RuntimeError):
    """The Zenoh configuration cannot be read or applied; the message says which part."""


def find_config_file(explicit: str | None = None) -> Path:
    for candidate in (explicit, os.environ.get("AERO_ZENOH_CONFIG")):
        if candidate:
            p = Path(candidate)
            if not p.is_file():
                raise ZenohConfigError(f"Zenoh config file {p} does not exist")
            return p
    for p in (Path.cwd() / "zenoh.json5", DEFAULT_CONFIG):
        if p.is_file():
            return p
    raise ZenohConfigError(f"the default Zenoh config {DEFAULT_CONFIG} is missing from the installation: "
                           "reinstall aeroperception, or pass --zenoh-config FILE")


def _split_endpoints(connect: str | list[str]) -> list[str]:
    items = connect.split(",") if isinstance(connect, str) else list(connect)
    out = []
    for ep in (e.strip() for e in items):
        if not ep:
            continue
        if "/" not in ep:  # "host:port" is the common shorthand
            ep = f"tcp/{ep}"
        out.append(ep)
    return out


def links_from_env() -> str:
    links = os.environ.get(LINKS_ENV) or "router"
    if links not in LINKS:
        raise ZenohConfigError(f"${LINKS_ENV}={links!r}: expected one of {', '.join(LINKS)}")
    return links


def make_config(zenoh_config: str | None = None, connect: str | list[str] | None = None,
                mode: str | None = None, listen: list[str] | None = None, service: bool = False) -> zenoh.Config:
    """`service`: a service's session, to which $AERO_LINKS applies (a CLI stays a client)."""
    path = find_config_file(zenoh_config)
    try:
        conf = zenoh.Config.from_file(str(path))
    except zenoh.ZError as e:
        raise ZenohConfigError(f"{path}: {e}") from None
    connect = connect or os.environ.get("AERO_CONNECT")
    if service and mode is None and listen is None and links_from_env() == "direct":
        mode, listen = "peer", DIRECT_LISTEN
    try:
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(_split_endpoints(connect)))
        if mode:
            conf.insert_json5("mode", json.dumps(mode))
        if listen is not None:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
        if conf.get_json("connect/retry") == "null":
            conf.insert_json5("connect/retry", json.dumps(RECONNECT))
    except zenoh.ZError as e:
        raise ZenohConfigError(f"invalid Zenoh setting: {e}") from None
    return conf


def open_session(conf: zenoh.Config, stop: threading.Event | None = None,
                 on_wait=None, max_wait_s: float | None = None) -> zenoh.Session | None:
    """Open a session, retrying with back-off (0.1 s .. 2 s) while no router answers.

    Returns None if `stop` is set or `max_wait_s` passes first. `on_wait(error, attempt)` is
    called before each retry so the caller can log / report STALE.
    """
    delay = 0.1
    t0 = time.monotonic()
    attempt = 0
    while True:
        attempt += 1
        try:
            return zenoh.open(conf)
        except zenoh.ZError as e:
            if max_wait_s is not None and time.monotonic() - t0 + delay > max_wait_s:
                if max_wait_s == 0:
                    raise
                return None
            if on_wait:
                on_wait(e, attempt)
            if stop is not None:
                if stop.wait(delay):
                    return None
            else:
                time.sleep(delay)
            delay = min(delay * 2, 2.0)
