"""The master as a process: read its options, run `MasterService` until SIGTERM or SIGINT."""

from __future__ import annotations

import argparse
import asyncio
import signal
from pathlib import Path

from core.errors import QuekaroError
from core.home import default_home
from core.logs import configure
from core.transport.credentials import xmpp_password
from master import auction as au
from master.service import MasterConfig, MasterService


def config_from(args: argparse.Namespace) -> MasterConfig:
    return MasterConfig(
        home=Path(args.home or default_home()), jid=args.jid, password=xmpp_password(args.password, args.password_file),
        xmpp_host=args.server, xmpp_port=args.port, ca_file=args.ca_file,
        http_host=args.http_host, http_port=args.http_port, public_url=args.public_url, threads=args.threads,
        tls_cert=args.tls_cert, tls_key=args.tls_key, insecure_http=args.insecure_http,
        auction=au.Config(slots=_slots(args), pass_samples=_pass_samples(args)), agent_allowlist=args.agents_allow,
    )


def _slots(args: argparse.Namespace) -> int:
    slots = au.Config.slots if args.slots is None else args.slots
    if slots < 1:
        raise QuekaroError(f"--slots {slots}: must be at least 1")
    return slots


def _pass_samples(args: argparse.Namespace) -> int:
    least = au.Config.pass_samples if args.pass_samples is None else args.pass_samples
    if least < 1:
        raise QuekaroError(f"--pass-samples {least}: must be at least 1")
    return least


async def serve(config: MasterConfig) -> None:
    """Run the master until a stop signal arrives."""
    config.data_plane()  # refuses what it cannot serve before anything is written to its home
    service = MasterService(config)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await service.start()
    try:
        await stop.wait()
    finally:
        await service.stop()


def main(args: argparse.Namespace) -> int:
    configure(args.log_level, args.log_format, role="master")
    asyncio.run(serve(config_from(args)))
    return 0
