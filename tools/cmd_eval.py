"""`aero eval lidar|...`: accuracy of the perception services against truth (simulator truth or
real recordings), printed as a table and optionally written as JSON."""
from __future__ import annotations

import argparse
import importlib


def register(sub: argparse._SubParsersAction) -> None:
    ev = sub.add_parser("eval", help="accuracy against truth (tables, JSON)")
    esub = ev.add_subparsers(dest="eval_cmd", required=True)
    p = esub.add_parser("lidar", help="ground removal P/R/F1 and obstacle FP/FN vs sim truth; KITTI vs Patchwork++")
    p.add_argument("--scenario", action="append", default=None,
                   help="scenario to render scans in (repeatable; default open_field, village, slope_forest)")
    p.add_argument("--kitti", nargs="*", default=None, metavar="BIN",
                   help="SemanticKITTI .bin scans (default: ../shared/data/kitti when present)")
    p.add_argument("-n", type=int, default=20, help="scans per scenario")
    p.add_argument("--json", default=None, metavar="FILE", help="write the figures as JSON")
    p.set_defaults(func=_lidar)


def _lidar(a) -> int:
    from aeroperception.tools.shared_data import kitti_scans

    mod = importlib.import_module("aeroperception.tools.eval_lidar")
    scenarios = a.scenario or ["open_field", "village", "slope_forest"]
    kitti = a.kitti if a.kitti is not None else [str(p) for p in kitti_scans()]
    return mod.run(scenarios, kitti, a.n, a.json)
