"""`aero play euroc DIR`, `aero play pcap FILE`: a real recording's sensors into the live stack at
their own timing, so the unchanged services run on real data.

euroc: stereo images, camera infos (also answered as queries, as a camera driver does), the IMU and
the ground truth on Zenoh, with sim/clock on the recording's time line for services run with
--sim-time. pcap: the capture's UDP datagrams to a lidar_driver's port, as the sensor sent them.
"""
from __future__ import annotations

import argparse
import socket

import zenoh

from aeroperception.tools.common import CliError, add_session_arguments, full_key, open_client


def register(sub: argparse._SubParsersAction) -> None:
    play = sub.add_parser("play", help="play a real recording (EuRoC folder, LiDAR pcap) into the live stack")
    psub = play.add_subparsers(dest="play_cmd", required=True, metavar="SOURCE")

    p = psub.add_parser("euroc", help="an EuRoC/ASL folder: stereo images + infos, IMU, ground truth, sim/clock")
    add_session_arguments(p)
    p.add_argument("dir", metavar="DIR", help="the folder holding mav0/")
    _timing_arguments(p)
    p.add_argument("--no-clock", action="store_true", help="do not publish sim/clock")
    p.add_argument("--no-truth", action="store_true", help="do not publish the ground truth on sim/truth/state")
    p.set_defaults(func=play_euroc)

    p = psub.add_parser("pcap", help="a LiDAR capture's UDP datagrams to a lidar_driver, at their capture timing")
    p.add_argument("file", metavar="FILE", help="classic pcap (tcpdump / Wireshark)")
    p.add_argument("--to", default="127.0.0.1", metavar="HOST",
                   help="where the lidar_driver listens (default 127.0.0.1)")
    p.add_argument("--port", action="append", default=[], metavar="PORT|FROM=TO",
                   help="where to send: PORT for every datagram, or FROM=TO for those the capture sent to FROM "
                        "(repeatable; the others keep their captured port). Default: each its captured port")
    _timing_arguments(p)
    p.set_defaults(func=play_pcap)


def _timing_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--start", type=float, default=0.0, help="seconds into the recording to start at")
    p.add_argument("--duration", type=float, default=None, help="seconds to play (default: to the end)")
    p.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C)")


def _window(args):
    from aeroperception.tools.playback.euroc import Window

    if not args.rate > 0:
        raise CliError(f"--rate {args.rate}: must be > 0")
    if args.start < 0 or (args.duration is not None and args.duration <= 0):
        raise CliError("--start must be >= 0 and --duration > 0")
    return Window(args.start, args.duration)


def _play(messages, publish, rate: float, loop: bool, clock_key: str | None):
    """Run the Replayer over messages() (again with --loop) until the end or Ctrl-C; the last stats."""
    from aeroperception.services.recorder.replay import Replayer
    from aeroperception.services.runtime.signals import ShutdownFlag
    from aeroperception.tools.playback.euroc import PlaybackError

    stop = ShutdownFlag().install()
    total = 0
    while True:
        r = Replayer(publish, rate=rate, clock=clock_key is not None, clock_key=clock_key or "",
                     stop=lambda: bool(stop))
        try:
            stats = r.run(messages())
        except PlaybackError as e:
            raise CliError(str(e)) from None
        total += stats.messages
        if not loop or stop:
            return total, stats


def play_euroc(args) -> int:
    from aeroperception.schemas import encode
    from aeroperception.services.runtime.node import encoding_for
    from aeroperception.services.runtime.wiring import zenoh_qos
    from aeroperception.services.sim.contract import OUTPUTS
    from aeroperception.tools.playback.euroc import INFO_KEYS, EurocPlayback, PlaybackError

    # the keys a camera, an IMU and a truth source publish, with the QoS the simulator declares for them
    declared = OUTPUTS.declared

    try:
        pb = EurocPlayback(args.dir, _window(args), truth=not args.no_truth,
                           prefix=f"{args.vehicle}/" if args.vehicle else "")
    except (PlaybackError, FileNotFoundError, ValueError) as e:
        raise CliError(str(e)) from None
    session = open_client(args)
    pubs: dict[str, zenoh.Publisher] = {}
    now = {"t": pb.t0_ns}

    def publish(key: str, payload: bytes, encoding: str) -> None:
        pub = pubs.get(key)
        if pub is None:
            topic = declared.get(key.removeprefix(pb.prefix))
            pub = pubs[key] = session.declare_publisher(key, encoding=zenoh.Encoding(encoding),
                                                        **(zenoh_qos(topic.qos) if topic else {}))
        pub.put(payload)

    def answer(cam: str):
        def on_query(q: zenoh.Query) -> None:
            info = pb.info(cam, now["t"])
            q.reply(q.key_expr, encode(info), encoding=encoding_for(type(info)))
        return on_query

    def stamped(msgs):
        for m in msgs:
            now["t"] = m.log_time_ns
            yield m

    queryables = [session.declare_queryable(full_key(args, INFO_KEYS[c]), answer(c)) for c in pb.infos]
    print(f"playing {args.dir}: {len(pb.frames)} frames ({'stereo' if len(pb.infos) == 2 else 'mono'}), "
          f"{pb.duration_s:.1f} s at x{args.rate:g}" + ("" if pb.truth else ", no ground truth"), flush=True)
    try:
        total, stats = _play(lambda: stamped(pb.messages()), publish, args.rate, args.loop,
                             None if args.no_clock else full_key(args, "sim/clock"))
    finally:
        for e in [*pubs.values(), *queryables]:
            e.undeclare()
        session.close()
    print(f"played {total} messages ({stats.clock_ticks} clock ticks; latest {stats.late_max_s * 1e3:.1f} ms behind)")
    return 0


def _port_map(items: list[str]) -> dict[int | None, int]:
    """--port values: {captured port: port to send to}; the key None maps every port."""
    out: dict[int | None, int] = {}
    for item in items:
        src, sep, dst = item.rpartition("=")
        try:
            key, port = (int(src) if sep else None), int(dst)
        except ValueError:
            raise CliError(f"--port {item!r}: expected PORT or FROM=TO (e.g. 2368=12368)") from None
        if not 0 < port < 65536 or (key is not None and not 0 < key < 65536):
            raise CliError(f"--port {item!r}: ports are 1-65535")
        if key is None and len(items) > 1:
            raise CliError(f"--port {item!r}: one port for every datagram excludes other --port values")
        out[key] = port
    return out


def play_pcap(args) -> int:
    from aeroperception.services.lib.lidar.pcap import PcapStats
    from aeroperception.tools.playback.pcap import UDP_PREFIX, datagrams

    window = _window(args)
    ports = _port_map(args.port)
    stats = PcapStats()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(key: str, payload: bytes, _encoding: str) -> None:
        sock.sendto(payload, (args.to, int(key.removeprefix(UDP_PREFIX))))

    try:
        total, st = _play(lambda: datagrams(args.file, window, ports, stats), send, args.rate, args.loop, None)
    except OSError as e:
        raise CliError(f"sending to {args.to}: {e}") from None
    finally:
        sock.close()
    skipped = ", ".join(f"{n} {why}" for why, n in stats.skipped.items())
    print(f"sent {total} datagrams from {args.file} to {args.to}" + (f" (skipped: {skipped})" if skipped else "")
          + f"; latest {st.late_max_s * 1e3:.1f} ms behind")
    return 0
