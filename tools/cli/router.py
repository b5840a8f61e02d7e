"""`aero router`: the stack's Zenoh router, a Python session in router mode.

`aero up` runs it as a supervised child (so a dead router is noticed and restarted); started
that way it also exits when `aero up` dies, like every service.
Its config: --zenoh-config FILE, else $AERO_ROUTER_CONFIG, else the clients' ($AERO_ZENOH_CONFIG,
zenoh.json5). AERO_ROUTER_CONFIG lets one environment hold both sides of a secured stack:
`AERO_ROUTER_CONFIG=certs/router.json5 AERO_ZENOH_CONFIG=certs/vehicle.json5 aero up --listen tls/0.0.0.0:7447`
(docs/deploy.md, "Secured links").

Several machines: each host runs its own router; `--connect tcp/OTHER_HOST:7447` makes this one
join another host's router (router to router), so every client on either host sees every key.
The link is retried for ever (every 0.2-1 s), so either host may start first and a link that
drops comes back by itself.

A thin link (radio, 20 Mbit/s): `--thin-link IFACE` lets each bulk stream (images, scans:
services/sim/qos.py BULK_STREAMS) leave through that interface at most `--thin-link-hz` times a
second (zenoh downsampling, egress). Without it a ground subscriber to 20 Hz raw images fills the
link and the kernel's send buffer (up to 4 MB) with frames: DATA_HIGH state/vehicle then waited
behind them and reached the ground 2.6 s late (tests/integration/test_multihost.py). Clients on
other interfaces (this host's services on lo) are not affected."""
from __future__ import annotations

import argparse
import json
import os
import socket
import sys

import zenoh

from aeroperception.services.runtime.session import ZenohConfigError, make_config
from aeroperception.services.runtime.signals import ShutdownFlag
from aeroperception.services.runtime.supervision import bind_to_supervisor

from aeroperception.tools.common import CliError

THIN_LINK_HZ = 1.0   # per bulk stream through a thin link: one raw 640x480 frame a second is 7.4 Mbit/s


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run the Zenoh router (listening per zenoh.json5)")
    p.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="router config (default: env AERO_ROUTER_CONFIG, else the clients' zenoh.json5)")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="listen endpoint, e.g. tcp/0.0.0.0:7447 (repeatable; default from zenoh.json5)")
    p.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="another host's router to join, e.g. tcp/10.0.0.2:7447 (repeatable)")
    p.add_argument("--thin-link", action="append", default=None, metavar="IFACE",
                   help="network interface of a slow link (e.g. wlan0): bulk streams leave through it "
                        "downsampled (repeatable)")
    p.add_argument("--thin-link-hz", type=float, default=THIN_LINK_HZ, metavar="HZ",
                   help=f"per bulk stream through --thin-link (default {THIN_LINK_HZ:g})")
    p.set_defaults(func=run)


def thin_link_downsampling(interfaces: list[str], hz: float) -> list[dict]:
    """zenoh `downsampling` config: every bulk stream (with or without a vehicle prefix) at most
    `hz` per key through `interfaces`, egress only."""
    from aeroperception.services.sim.qos import BULK_STREAMS

    if not hz > 0:
        raise CliError(f"--thin-link-hz must be > 0, not {hz:g}")
    known = {name for _i, name in socket.if_nameindex()}
    for iface in interfaces:
        if iface not in known:
            raise CliError(f"--thin-link: no network interface {iface!r} on this host ({', '.join(sorted(known))})")
    return [{"id": "thin_link", "interfaces": list(interfaces), "messages": ["put"], "flows": ["egress"],
             "rules": [{"key_expr": f"**/{k}", "freq": hz} for k in BULK_STREAMS]}] if interfaces else []


def open_router(zenoh_config: str | None, listen: list[str] | None,
                connect: list[str] | None = None, thin_links: list[str] | None = None,
                thin_link_hz: float = THIN_LINK_HZ) -> zenoh.Session:
    """A router session; `connect`: other routers (other hosts) it links to, retried for ever;
    `thin_links`: interfaces whose bulk streams are downsampled to `thin_link_hz`."""
    downsampling = thin_link_downsampling(thin_links or [], thin_link_hz)
    try:
        conf = make_config(zenoh_config, mode="router", listen=listen)
        conf.insert_json5("scouting/delay", "0")
        if downsampling:
            conf.insert_json5("downsampling", json.dumps(json.loads(conf.get_json("downsampling")) + downsampling))
        conf.insert_json5("connect/endpoints", json.dumps(list(connect or [])))
        if connect:
            # zenoh.json5's connect timeout 0 (right for clients: the runtime retries) makes a
            # router try its connect endpoints once and never again (seen with zenoh 1.10): a
            # ground router started before the vehicle's would stay alone. Any non-zero timeout
            # puts the endpoints on zenoh's own retry (connect/retry), also after a link drops.
            conf.insert_json5("connect/timeout_ms", json.dumps({"router": 1, "peer": 0, "client": 0}))
    except (ZenohConfigError, zenoh.ZError) as e:
        raise CliError(str(e)) from None
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise CliError(f"cannot start the router ({str(e).split(' at ')[0]}): is another router "
                       "already listening on that port? (`aero node list` to check)") from None


def run(args) -> int:
    shutdown = ShutdownFlag().install()
    stop = shutdown.event
    bind_to_supervisor(stop.set)
    router = open_router(args.zenoh_config or os.environ.get("AERO_ROUTER_CONFIG") or None, args.listen, args.connect,
                         args.thin_link, args.thin_link_hz)
    joins = f", joining {', '.join(args.connect)}" if args.connect else ""
    if args.thin_link:
        joins += f", bulk streams via {', '.join(args.thin_link)} at {args.thin_link_hz:g} Hz"
    print(f"aero router: zid {router.zid()} listening on {', '.join(args.listen or ['zenoh.json5 endpoints'])}"
          f"{joins}", file=sys.stderr, flush=True)
    shutdown.wait()
    router.close()
    return 0
