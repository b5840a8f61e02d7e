"""`aero viz`: the Rerun live view in the foreground (the viz service with flags for its outputs).

    aero viz                      native viewer on this machine (needs a display)
    aero viz --web 9090           web viewer + gRPC served here: open the printed URL in a browser
    aero viz --viewer rerun+http://laptop:9876/proxy    stream to a viewer running elsewhere
    aero viz --save flight.rrd    record to a file (combine with any of the above)

`--connect` keeps its meaning of every aero command (the Zenoh router); the Rerun viewer to
stream to is `--viewer`.
"""
from __future__ import annotations

import argparse
import shutil

from aeroperception.services.runtime.service import add_common_arguments

from aeroperception.tools.common import CliError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("viz", help="Rerun live view: native viewer, --web PORT (browser), --viewer URL, --save FILE")
    g = p.add_argument_group("viewer")
    g.add_argument("--web", type=int, default=None, metavar="PORT", help="serve the web viewer (and gRPC) on this port")
    g.add_argument("--grpc-port", type=int, default=None, metavar="PORT", help="gRPC port served with --web (default 9876)")
    g.add_argument("--bind", default=None, metavar="IP", help="address the gRPC server listens on (default 0.0.0.0)")
    g.add_argument("--viewer", default=None, metavar="URL", help="stream to a running viewer: rerun+http://HOST:9876/proxy")
    g.add_argument("--save", default=None, metavar="FILE", help="write a .rrd recording")
    g.add_argument("--no-truth", action="store_true", help="sim: hide the ground truth (pose, track, boxes)")
    add_common_arguments(p)
    p.set_defaults(func=run)


def viz_argv(args: argparse.Namespace) -> list[str]:
    """The viz service's command line for these flags (one-line errors for the wrong ones)."""
    if args.connect and args.connect.startswith("rerun"):
        raise CliError(f"--connect {args.connect}: --connect is the Zenoh router; "
                       "stream to a Rerun viewer with --viewer URL")
    if args.web is not None and not 0 < args.web < 65536:
        raise CliError(f"--web {args.web}: a TCP port 1-65535")
    params = [f"web_port={args.web or 0}"]
    if args.grpc_port is not None:
        params.append(f"grpc_port={args.grpc_port}")
    if args.bind:
        params.append(f"bind_ip={args.bind}")
    if args.viewer:
        params.append(f"viewer_url={args.viewer}")
    if args.save:
        params.append(f"save_path={args.save}")
    if args.no_truth:
        params.append("show_truth=false")
    if not (args.web or args.viewer or args.save):
        if shutil.which("rerun") is None:
            raise CliError("no native Rerun viewer here (`rerun` not on PATH, from the rerun-sdk package): "
                           "use --web PORT and a browser, --viewer URL, or --save FILE")
        params.append("spawn=true")
    argv: list[str] = []
    for flag in ("connect", "zenoh_config", "vehicle", "params"):
        value = getattr(args, flag)
        if value:
            argv += [f"--{flag.replace('_', '-')}", value]
    if args.sim_time:
        argv.append("--sim-time")
    argv += ["--log-level", args.log_level]
    for p in [*params, *args.param]:
        argv += ["--param", p]
    return argv


def run(args: argparse.Namespace) -> int:
    from aeroperception.services.runtime import run as run_service
    from aeroperception.services.viz.main import VizService

    return run_service(VizService, viz_argv(args))
