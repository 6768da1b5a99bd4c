"""A bare slixmpp client for probing the XMPP server itself, not the farm's FarmAgent on top of it.

    python tests/raw_xmpp.py sink  --jid a@localhost --password P --port N            prints each message's from
    python tests/raw_xmpp.py forge --jid b@localhost --password P --port N --to a@localhost --forged master@localhost

Each prints JSON lines: {"event": "online"|"got"|"sent"|"error", ...}. Certificates are not verified
(loopback probing only).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import ssl
import sys

import slixmpp


def emit(event: str, **fields: object) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


class Probe(slixmpp.ClientXMPP):
    def __init__(self, args: argparse.Namespace) -> None:
        super().__init__(args.jid, args.password)
        self.args = args
        self.ready = asyncio.Event()
        self.add_event_handler("session_start", self.started)
        self.add_event_handler("message", lambda msg: emit("got", sender=str(msg["from"]), body=msg["body"]))
        self.add_event_handler("failed_auth", lambda _e: emit("error", reason="authentication failed"))

    async def started(self, _event: object) -> None:
        self.send_presence()
        emit("online", jid=str(self.boundjid))
        self.ready.set()


async def main(args: argparse.Namespace) -> int:
    probe = Probe(args)
    context = ssl.create_default_context()
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    probe.ssl_context = context
    probe.connect(host="127.0.0.1", port=args.port)
    try:
        await asyncio.wait_for(probe.ready.wait(), 20)
    except TimeoutError:
        emit("error", reason="not online within 20 s")
        return 2
    if args.mode == "forge":
        probe.send_message(mto=args.to, mbody="forged", mfrom=args.forged)
        emit("sent", to=args.to, forged=args.forged)
    await asyncio.sleep(args.linger)
    probe.disconnect()
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("mode", choices=("sink", "forge"))
    p.add_argument("--jid", required=True)
    p.add_argument("--password", required=True)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--to", default="")
    p.add_argument("--forged", default="")
    p.add_argument("--linger", type=float, default=3.0)
    sys.exit(asyncio.run(main(p.parse_args())))
