"""`aero run SERVICE [flags]`: one service in the foreground (same as python -m ...services.SERVICE)."""
from __future__ import annotations

import argparse
import importlib
import pkgutil

import aeroperception.services as services_pkg

from aeroperception.tools.common import CliError

NOT_SERVICES = set(services_pkg.LIBRARIES)


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(services_pkg.__path__)
                  if m.ispkg and m.name not in NOT_SERVICES)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run one service in the foreground: aero run SERVICE [--param k=v]")
    p.add_argument("service", help=f"one of: {', '.join(available())}")


def run_service(argv: list[str]) -> int:
    if not argv or argv[0].startswith("-"):
        raise CliError(f"usage: aero run SERVICE [flags]; services: {', '.join(available())}")
    name = argv[0]
    if name not in available():
        raise CliError(f"unknown service {name!r}; services: {', '.join(available())}")
    module = importlib.import_module(f"aeroperception.services.{name}.main")
    return module.main(argv[1:])
