"""`aero chaos`: list the rows, run some or all of them on a fresh stack (the built-in sim, or PX4 SITL
with `--profile px4`), print the table."""
from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

from aeroperception.tools.common import CliError
from aeroperception.tools.cli import px4_sitl
from aeroperception.tools.harness import Px4Stack, SimStack, StackStartError, profile_services
from aeroperception.tools.harness.px4_stack import PX4_FLIGHT_SERVICES

from .rows import build_rows
from .judging import RowResult
from .running import format_table, run_row

REPO = Path(__file__).resolve().parents[3]
DEFAULT_MISSION = REPO / "examples" / "missions" / "survey_01.json"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("chaos", help="inject faults into a sim or PX4 SITL stack mid-mission, print a figures table")
    p.add_argument("--profile", choices=("sim", "px4"), default="sim",
                   help="the flight controller: the built-in sim (judged by sim/truth/state) or PX4 SITL "
                        "(judged by SIH's HIL_STATE_QUATERNION)")
    p.add_argument("--px4", default=None, metavar="DIR",
                   help="px4 profile: the PX4 build (bin/px4 + etc/; default $AERO_PX4_DIR)")
    p.add_argument("--rows", default="", help="comma-separated rows (default: all); `--list` shows them")
    p.add_argument("--list", action="store_true", help="list the rows and their expected outcomes")
    p.add_argument("--json", default=None, metavar="FILE", help="write the results as JSON too")
    p.add_argument("--mission", default=str(DEFAULT_MISSION), help="mission file flown in each row")
    p.add_argument("--log-dir", default=None, help="stack logs (default a new temporary directory)")
    p.set_defaults(func=run)


def run(args) -> int:
    px4_build = None
    if args.profile == "px4":
        px4_build = px4_sitl.build_dir(args.px4)
        services = PX4_FLIGHT_SERVICES
    elif args.px4 is not None:
        raise CliError("--px4: the sim profile starts no PX4 (use --profile px4)")
    else:
        services = profile_services("sim")
    rows = build_rows(services, args.profile)
    if args.list:
        for r in rows.values():
            print(f"{r.name:<16} {r.injected}\n{'':<16} expected: {r.expected}")
        return 0
    names = [s.strip() for s in args.rows.split(",") if s.strip()] or list(rows)
    unknown = [n for n in names if n not in rows]
    if unknown:
        raise CliError(f"unknown row {', '.join(unknown)}; rows: {', '.join(rows)}")
    try:
        mission_json = Path(args.mission).read_text()
    except OSError as e:
        raise CliError(f"cannot read mission {args.mission}: {e.strerror}") from None
    print(f"aero chaos: {len(names)} rows on the {args.profile} profile ({', '.join(services)})", flush=True)
    try:
        if px4_build is not None:
            st = Px4Stack(px4_build, args.log_dir, services)
        else:
            st = SimStack(args.log_dir, sensors=rows[names[0]].sensors)
    except StackStartError as e:
        raise CliError(f"the {args.profile} stack did not come up: {str(e).splitlines()[0]}") from None
    print(f"stack up (router {st.endpoint}, logs {st.log_dir})", flush=True)
    results: list[RowResult] = []
    try:
        for name in names:
            res = run_row(st, rows[name], mission_json)
            results.append(res)
            print(f"  {res.row:<16} {res.verdict}  {res.observed}  [safe: {res.safe_why}] ({res.duration_s:.0f} s)",
                  flush=True)
    finally:
        st.stop()
    print()
    print(format_table(results))
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(r) | {"verdict": r.verdict} for r in results], indent=1) + "\n")
    failed = [r.row for r in results if not r.passed]
    print(f"\n{sum(r.passed for r in results)}/{len(results)} rows pass; failing: {', '.join(failed) or 'none'}")
    return 1 if failed else 0

