"""`aero certs`: a development CA, certificates and credentials for secured Zenoh links (tools/certs.py)."""
from __future__ import annotations

import argparse
import socket
from pathlib import Path

from aeroperception.tools.common import CliError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("certs", help="create a development CA, TLS certificates, passwords and secure Zenoh configs")
    p.add_argument("--out", default="certs", metavar="DIR", help="output folder (default ./certs)")
    p.add_argument("--host", action="append", default=None, metavar="NAME",
                   help="router host name or IP its clients connect to (repeatable; "
                        "default: localhost, 127.0.0.1 and this machine's host name)")
    p.add_argument("--days", type=int, default=365, help="validity of every certificate")
    p.add_argument("--force", action="store_true", help="overwrite an existing CA in DIR")
    p.set_defaults(func=run)


def run(args) -> int:
    from aeroperception.tools import certs  # cryptography is imported only by this command

    hosts = args.host or ["localhost", "127.0.0.1", socket.gethostname()]
    if args.days < 1:
        raise CliError("--days must be at least 1")
    try:
        issued = certs.create(Path(args.out), list(dict.fromkeys(hosts)), days=args.days, force=args.force)
    except FileExistsError as e:
        raise CliError(f"{e}: keep that CA, or pass --force to replace it (clients then need the new files)") from None
    except OSError as e:
        raise CliError(f"cannot write to {args.out}: {e.strerror}") from None
    out = issued.out
    print(f"aero certs: CA, router ({', '.join(hosts)}) and {', '.join(certs.ROLES)} certificates, "
          f"users.txt and Zenoh configs in {out}")
    print(f"  router:   aero router --zenoh-config {out / 'router.json5'}")
    for role in certs.ROLES:
        print(f"  {role + ':':<9} AERO_ZENOH_CONFIG={out / (role + '.json5')} aero ...  (connect: tls/HOST:7447)")
    print("  keep ca.key offline; *.key, users.txt and the configs are secrets (mode 600)")
    return 0
