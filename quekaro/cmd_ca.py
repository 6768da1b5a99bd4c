"""`quekaro ca init | issue`: the farm's own certificate authority, for TLS on every link across hosts
(Prosody's certificate, the master's HTTPS); every process is then given ca.pem to verify its peers."""

from __future__ import annotations

import argparse
from pathlib import Path

from core.transport.tls import issue, make_ca


def register(sub: argparse._SubParsersAction) -> None:
    ca = sub.add_parser("ca", help="the farm's certificate authority (TLS across hosts)")
    ca_sub = ca.add_subparsers(dest="ca", metavar="ACTION", required=True)
    init = ca_sub.add_parser("init", help="make DIR/ca.pem and DIR/ca.key (once per farm)")
    init.add_argument("--dir", type=Path, required=True, help="where the CA lives (keep ca.key private)")
    init.set_defaults(func=run_init)
    cert = ca_sub.add_parser("issue", help="a server certificate signed by the CA: DIR/NAME.pem and NAME.key")
    cert.add_argument("name", help="file name, e.g. master or xmpp")
    cert.add_argument("hosts", nargs="+", help="host names and addresses the server is reached by; "
                      "for Prosody its XMPP domain")
    cert.add_argument("--dir", type=Path, required=True, help="the CA's folder (quekaro ca init)")
    cert.add_argument("--out", type=Path, help="where to write the pair (default: the CA's folder)")
    cert.set_defaults(func=run_issue)


def run_init(args: argparse.Namespace) -> int:
    print(make_ca(args.dir))
    return 0


def run_issue(args: argparse.Namespace) -> int:
    cert, key = issue(args.dir, args.name, args.hosts, args.out or args.dir)
    print(f"{cert}\n{key}")
    return 0
