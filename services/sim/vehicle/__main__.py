"""Run the simulated vehicle alone (no Zenoh), e.g. for QGroundControl or MAVProxy:

    python -m aeroperception.services.sim.vehicle --speed 1 --seed 0
    mavproxy.py --master udpin:127.0.0.1:14540
"""
from __future__ import annotations

import argparse
import json
import logging
import sys

from aeroperception.services.runtime.params import ParamError, parse_overrides
from aeroperception.services.runtime.signals import ShutdownFlag

from .endpoint import PX4_SITL_BIND, PX4_SITL_TARGET, MavlinkEndpoint, parse_address
from .model import SimVehicle
from .params import make_params
from .runner import SimVehicleRunner


def _home(text: str) -> dict:
    try:
        lat, lon, alt = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LAT,LON,ALT (degrees, degrees, metres AMSL), got {text!r}")
    return {"SIM_HOME_LAT": lat, "SIM_HOME_LON": lon, "SIM_HOME_ALT": alt}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m aeroperception.services.sim.vehicle", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--target", default="%s:%d" % PX4_SITL_TARGET, help="where telemetry goes (HOST:PORT)")
    ap.add_argument("--bind", default="%s:%d" % PX4_SITL_BIND, help="local address to send from / listen on")
    ap.add_argument("--speed", type=float, default=1.0, help="sim seconds per wall second (0: as fast as possible)")
    ap.add_argument("--seed", type=int, default=0, help="seed for wind gusts and sensor noise")
    ap.add_argument("--home", type=_home, help="LAT,LON,ALT of home (local origin, ground level)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="override a parameter")
    ap.add_argument("--sysid", type=int, default=1, help="MAVLink system id")
    ap.add_argument("--status-every", type=float, default=5.0, help="seconds between status lines on stderr (0: never)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")

    try:
        params = make_params({**(args.home or {}), **parse_overrides(args.param)})
        endpoint = MavlinkEndpoint(target=parse_address(args.target), bind=parse_address(args.bind),
                                   system_id=args.sysid)
    except (ParamError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    runner = SimVehicleRunner(SimVehicle(params, seed=args.seed), endpoint, speed=args.speed)

    shutdown = ShutdownFlag().install()  # a handler calling Event.set() can deadlock: see signals.py
    runner.start()
    logging.info("sim vehicle: sending to %s from %s:%d, speed %.1fx, seed %d",
                 args.target, *endpoint.local_address, args.speed, args.seed)
    keys = ("sim_time_s", "realtime_factor", "mode", "armed", "landed_state", "failsafe", "position_enu_m",
            "battery_remaining", "rx_msgs", "rx_bad", "tx_msgs", "setpoints", "vision_odometry", "peer")
    while not shutdown.wait(args.status_every or None):
        d = runner.diagnostics()
        print(json.dumps({k: d.get(k) for k in keys}), file=sys.stderr, flush=True)
    runner.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
