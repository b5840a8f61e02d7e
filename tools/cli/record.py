"""`aero record`, `aero replay`, `aero mcap info|recover|export`: keep a flight in MCAP, play it
back into a live stack, and hand it to other tools (Foxglove)."""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import zenoh

from aeroperception.tools.common import CliError, add_session_arguments, full_key, open_client


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record keys to MCAP in the foreground (Ctrl-C closes the file)")
    add_session_arguments(p)
    p.add_argument("--preset", default="essentials", choices=["essentials", "all", "none"],
                   help="key set (essentials: requirement LOG-1's list; none: only the KEYEXPRs given)")
    p.add_argument("--images", action="store_true", help="also record camera images")
    p.add_argument("-o", "--output-dir", default="", help="directory (default $AERO_RECORD_DIR or ~/.aero/recordings)")
    p.add_argument("--max-bag-size", type=int, default=None, help="bytes per file before a split (default 1 GiB)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after T seconds (0: until Ctrl-C)")
    p.add_argument("--sim-time", action="store_true", default=os.environ.get("AERO_SIM_TIME") == "1",
                   help="log times from sim/clock, as the stack's services do after `aero up --speed X` "
                        "(env AERO_SIM_TIME=1); without it a slowed sim is recorded on wall time")
    p.add_argument("keys", nargs="*", metavar="KEYEXPR", help="extra key expressions, e.g. sensors/imu planner/**")
    p.set_defaults(func=record)

    p = sub.add_parser("replay", help="republish a recording with its original timing (and sim/clock)")
    add_session_arguments(p)
    p.add_argument("file")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C)")
    p.add_argument("--keys", nargs="+", default=None, metavar="KEYEXPR", help="only keys matching these")
    p.add_argument("--start", type=float, default=0.0, help="seconds into the recording to start at")
    p.add_argument("--end", type=float, default=None, help="seconds into the recording to stop at")
    p.add_argument("--no-clock", action="store_true", help="do not publish sim/clock")
    p.set_defaults(func=replay)

    mcap = sub.add_parser("mcap", help="inspect, repair and convert MCAP recordings")
    msub = mcap.add_subparsers(dest="mcap_cmd", required=True)
    p = msub.add_parser("info", help="channels, counts, rates, duration and metadata")
    p.add_argument("file")
    p.add_argument("--metadata", action="store_true", help="also print every metadata record")
    p.set_defaults(func=mcap_info)
    p = msub.add_parser("recover", help="rebuild a readable, indexed file from one cut short")
    p.add_argument("file")
    p.add_argument("-o", "--output", default=None, help="default: FILE with .recovered.mcap")
    p.set_defaults(func=mcap_recover)
    p = msub.add_parser("export", help="convert for other tools")
    p.add_argument("file")
    p.add_argument("--foxglove", action="store_true", required=True,
                   help="JSON messages with Foxglove's well-known schemas (poses, images, clouds, grids, logs)")
    p.add_argument("-o", "--output", default=None, help="default: FILE with .foxglove.mcap")
    p.set_defaults(func=mcap_export)


# ---------------------------------------------------------------- record


def record(args) -> int:
    from aeroperception.services.recorder import contract
    from aeroperception.services.recorder.main import RecorderService
    from aeroperception.services.runtime import Node, ParamError
    from aeroperception.services.runtime.session import ZenohConfigError
    from aeroperception.services.runtime.signals import ShutdownFlag

    try:
        # Its own name: `aero record` runs beside the profile's recorder service.
        node = Node("record", params=contract.PARAMS, vehicle=args.vehicle, zenoh_config=args.zenoh_config,
                    connect=args.connect, sim_time=args.sim_time)
        values = {"preset": args.preset, "record_images": args.images, "keys": ",".join(args.keys),
                  "output_dir": args.output_dir}
        if args.max_bag_size is not None:
            values["max_bag_size"] = args.max_bag_size
        node.params.update(values)
    except (ParamError, ZenohConfigError) as e:
        raise CliError(str(e)) from None
    shutdown = ShutdownFlag(node.stop_event).install()
    if not node.connect(max_wait_s=3.0):
        node.close()
        raise CliError("no Zenoh router reachable: start the stack with `aero up`, or point --connect at one")
    svc = RecorderService(node, argparse.Namespace(scenario=""))
    node.set_health(svc.health)
    try:
        svc.launch()
    except ParamError as e:
        node.close()
        raise CliError(str(e)) from None
    print(f"recording {', '.join(svc.exprs)} (Ctrl-C to stop)", flush=True)
    t0 = time.monotonic()
    try:
        while not shutdown.wait(2.0 if not args.duration else min(2.0, args.duration)):
            h = svc.health()
            v = h.values
            print(f"  {v['messages']} msgs  {v['mbytes']} MB  dropped {v['dropped']}  {v['file']}"
                  + (f"  ERROR: {h.message}" if h.level >= 2 else ""), flush=True)
            if args.duration and time.monotonic() - t0 >= args.duration:
                break
    finally:
        svc.stop()
        node.close()
    sink = svc.recording.sink
    for f in sink.stats.files:
        print(f"wrote {f}")
    if sink.error:
        raise CliError(f"recording stopped: {sink.error} (the file so far is kept; `aero mcap recover` indexes it)")
    _ = shutdown
    return 0


# ---------------------------------------------------------------- replay


def replay(args) -> int:
    from aeroperception.services.recorder.files import RecordingError, info, messages
    from aeroperception.services.recorder.replay import CLOCK_KEY, Recorded, Replayer
    from aeroperception.services.runtime.signals import ShutdownFlag

    try:
        fi = info(args.file)
    except RecordingError as e:
        raise CliError(str(e)) from None
    if not fi.indexed:
        raise CliError(f"{args.file}: has no index (cut short?): run `aero mcap recover {args.file}` first")
    topics = [c.topic for c in fi.channels if c.count]
    if args.keys:
        exprs = [zenoh.KeyExpr(full_key(args, k)) for k in args.keys]
        topics = [t for t in topics if any(e.includes(t) for e in exprs)]
        if not topics:
            raise CliError(f"no recorded key matches {' '.join(args.keys)} (`aero mcap info {args.file}` lists them)")
    start_ns = fi.start_ns + int(args.start * 1e9)
    end_ns = fi.start_ns + int(args.end * 1e9) if args.end is not None else None
    session = open_client(args)
    stop = ShutdownFlag().install()
    pubs: dict[tuple[str, str], zenoh.Publisher] = {}

    def publish(key: str, payload: bytes, encoding: str) -> None:
        pub = pubs.get((key, encoding))
        if pub is None:
            pub = pubs[(key, encoding)] = session.declare_publisher(key, encoding=zenoh.Encoding(encoding))
        pub.put(payload)

    try:
        total = 0
        while True:
            r = Replayer(publish, rate=args.rate, clock=not args.no_clock, clock_key=full_key(args, CLOCK_KEY),
                         stop=lambda: bool(stop))
            try:
                stats = r.run(Recorded(ch.topic, ch.metadata.get("zenoh_encoding") or ch.message_encoding,
                                       m.data, m.log_time) for ch, m in messages(args.file, topics, start_ns, end_ns))
            except RecordingError as e:
                raise CliError(str(e)) from None
            total += stats.messages
            if not args.loop or stop:
                break
        print(f"replayed {total} messages from {args.file} (latest {stats.late_max_s * 1e3:.1f} ms behind)")
    finally:
        for p in pubs.values():
            p.undeclare()
        session.close()
    return 0


# ---------------------------------------------------------------- mcap


def _info(path: str):
    from aeroperception.services.recorder.files import RecordingError, info

    try:
        return info(path)
    except RecordingError as e:
        raise CliError(str(e)) from None


def mcap_info(args) -> int:
    fi = _info(args.file)
    meta = fi.metadata.get("aeroperception", {})
    print(f"file:      {fi.path}{'' if fi.indexed else '  (no index: cut short? `aero mcap recover` it)'}")
    print(f"duration:  {fi.duration_s:.2f} s   messages: {fi.messages}   channels: {len(fi.channels)}")
    if meta:
        print(f"stack:     {meta.get('stack_version', '?')}   scenario: {meta.get('scenario') or '-'}"
              f"   preset: {meta.get('preset', '?')}   started: {meta.get('started_utc', '?')}")
    params = sorted(k.removeprefix("params/") for k in fi.metadata if k.startswith("params/"))
    if params:
        print(f"params of: {', '.join(params)}")
    if fi.truncated:
        print(f"truncated: {fi.truncated}")
    print(f"{'KEY':<40} {'SCHEMA':<24} {'COUNT':>8} {'RATE Hz':>8} {'KB':>10}")
    for c in fi.channels:
        print(f"{c.topic:<40} {c.schema or c.encoding:<24} {c.count:>8} {c.rate_hz:>8.1f} {c.bytes / 1e3:>10.1f}")
    if args.metadata:
        for name, data in sorted(fi.metadata.items()):
            print(f"[{name}]")
            for k, v in sorted(data.items()):
                print(f"  {k} = {v}")
    return 0


def _output(path: str, given: str | None, suffix: str) -> str:
    if given:
        return given
    p = Path(path)
    return str(p.with_name(p.name.removesuffix(".mcap") + suffix))


def mcap_recover(args) -> int:
    from aeroperception.services.recorder.files import RecordingError, recover

    if not Path(args.file).is_file():
        raise CliError(f"{args.file}: no such file")
    out = _output(args.file, args.output, ".recovered.mcap")
    try:
        res = recover(args.file, out)
    except RecordingError as e:
        raise CliError(str(e)) from None
    end = f"; stopped at: {res.truncated}" if res.truncated else "; the file was complete"
    print(f"recovered {res.messages} messages on {res.channels} channels into {out}{end}")
    return 0


def mcap_export(args) -> int:
    from aeroperception.services.recorder.files import RecordingError

    try:
        from aeroperception.services.recorder.foxglove import export
    except ImportError as e:  # pragma: no cover - the tools extra brings it
        raise CliError(f"{e}: install the tools extra (pip install 'aeroperception[tools]')") from None
    out = _output(args.file, args.output, ".foxglove.mcap")
    try:
        counts = export(args.file, out)
    except RecordingError as e:
        raise CliError(str(e)) from None
    print(f"wrote {sum(counts.values())} messages on {len(counts)} channels to {out} (open it in Foxglove)")
    return 0
