"""A FarmAgent in its own process, driven by tests/test_xmpp.py: echo, ping, stream, send one message, or sink.

Agents in one process bypass XMPP (docs/design.md section 4), so every XMPP test runs two of these. Each
prints JSON lines on stdout: {"event": "online"|"refused"|"reconnected"|"pong"|"result"|"error", ...};
PEER_LOG=DEBUG in the environment shows slixmpp's traffic on stderr.

    python tests/xmpp_peer.py --jid echo@localhost --password pw --port 5222 --peers ping@localhost echo
    python tests/xmpp_peer.py --jid ping@localhost ... ping --to echo@localhost --count 200 --burst 1000
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import sys
import time

from spade.agent import Agent, AuthenticationFailure

from core.transport.rates import SenderRates
from core.transport.xmpp import Envelope, FarmAgent, XmppError

PROTOCOL = "quekaro-test"


def emit(event: str, **fields: object) -> None:
    print(json.dumps({"event": event, "t": time.time(), **fields}), flush=True)


def make_agent(args: argparse.Namespace) -> FarmAgent:
    rates = SenderRates(*(float(v) for v in args.rate.split(","))) if args.rate else None
    agent = FarmAgent(args.jid, args.password, port=args.port, server=args.server,
                      peers=[p for p in args.peers.split(",") if p], max_body=args.max_body, rates=rates)
    agent.on_refusal = lambda r: emit("refused", sender=r.sender, kind=r.kind, reason=r.reason, size=r.size)
    return agent


async def watch_reconnects(agent: FarmAgent) -> None:
    seen = 0
    while True:
        await asyncio.sleep(0.05)
        if agent.reconnects > seen:
            seen = agent.reconnects
            emit("reconnected", outage_s=agent.last_outage_s, count=seen)


async def run_echo(agent: FarmAgent, args: argparse.Namespace, stop: asyncio.Event) -> None:
    async def echo(env: Envelope) -> None:
        await agent.send(env.sender, "inform", env.body, conversation_id=env.conversation_id,
                         protocol=env.protocol)

    agent.set_handler(echo)
    await stop.wait()


async def run_sink(agent: FarmAgent, args: argparse.Namespace, stop: asyncio.Event) -> None:
    """Say when each message arrives, and answer none."""
    async def got(env: Envelope) -> None:
        emit("got", sender=env.sender, conversation=env.conversation_id)

    agent.set_handler(got)
    await stop.wait()


class Pinger:
    """Sends pings whose conversation id is their sequence number and waits for the echoes."""

    def __init__(self, agent: FarmAgent, to: str) -> None:
        self.agent, self.to = agent, to
        self.waiting: dict[str, asyncio.Future[float]] = {}
        self.received: set[str] = set()
        agent.set_handler(self.on_reply)

    async def on_reply(self, env: Envelope) -> None:
        self.received.add(env.conversation_id)
        fut = self.waiting.pop(env.conversation_id, None)
        if fut and not fut.done():
            fut.set_result(time.perf_counter())

    async def send(self, seq: str, body: str) -> asyncio.Future[float]:
        fut: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        self.waiting[seq] = fut
        if not await self.agent.send(self.to, "request", body, conversation_id=seq, protocol=PROTOCOL):
            fut.cancel()
        return fut


async def run_ping(agent: FarmAgent, args: argparse.Namespace, stop: asyncio.Event) -> None:
    pinger = Pinger(agent, args.to)
    rtts = []
    for i in range(args.count):
        t0 = time.perf_counter()
        fut = await pinger.send(f"rtt-{i}", f"ping {i}")
        rtts.append((await asyncio.wait_for(fut, 10.0)) - t0)
    t0 = time.perf_counter()
    futs = [await pinger.send(f"burst-{i}", f"burst {i} " + "x" * 64) for i in range(args.burst)]
    done, _ = await asyncio.wait(futs, timeout=60.0)
    elapsed = time.perf_counter() - t0
    rtts.sort()
    emit("result", count=len(rtts), rtt_median_ms=1000 * rtts[len(rtts) // 2] if rtts else None,
         rtt_p95_ms=1000 * rtts[int(len(rtts) * 0.95)] if rtts else None,
         burst=args.burst, burst_received=len(done), msgs_per_s=len(done) / elapsed if elapsed else None)


async def run_stream(agent: FarmAgent, args: argparse.Namespace, stop: asyncio.Event) -> None:
    """Ping every `interval` s until stopped; report each answer (tests restart the server meanwhile)."""
    pinger = Pinger(agent, args.to)
    seq = 0
    while not stop.is_set():
        seq += 1
        sent_at = time.time()
        fut = await pinger.send(f"s-{seq}", f"stream {seq}")
        fut.add_done_callback(lambda f, s=seq, t=sent_at: None if f.cancelled()
                              else emit("pong", seq=s, sent=t, rtt_ms=1000 * (time.time() - t)))
        with_timeout = asyncio.create_task(asyncio.wait_for(stop.wait(), args.interval))
        await asyncio.gather(with_timeout, return_exceptions=True)
    emit("result", sent=seq, received=len(pinger.received))


async def run_send(agent: FarmAgent, args: argparse.Namespace, stop: asyncio.Event) -> None:
    """Send one message (possibly malformed on purpose) past the sender-side checks, then exit."""
    from spade.message import Message

    body = args.body if args.body_size is None else "x" * args.body_size
    meta = {"performative": "request", "ontology": args.ontology, "protocol": PROTOCOL,
            "conversation-id": args.conversation}
    meta = {k: v for k, v in meta.items() if v}
    # Built by hand on purpose: FarmAgent.send refuses what this test wants the receiver to refuse.
    for _ in range(args.copies):
        Message(to=args.to, sender=str(agent.jid), body=body, metadata=meta).prepare(agent.client).send()
    emit("sent", size=len(body), copies=args.copies)
    await asyncio.sleep(args.linger)


MODES = {"echo": run_echo, "ping": run_ping, "stream": run_stream, "send": run_send, "sink": run_sink}


async def amain(args: argparse.Namespace) -> int:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    agent = make_agent(args)
    try:
        if args.register:  # an intruder's try: SPADE's in-band registration (the farm never registers in-band)
            await Agent.start(agent, auto_register=True)
        else:
            await agent.start(timeout=args.connect_timeout)
    except AuthenticationFailure as exc:
        emit("error", reason=f"in-band registration and login refused: {exc}")
        return 2
    except XmppError as exc:
        emit("error", reason=str(exc))
        return 2
    await asyncio.sleep(args.warmup)
    emit("online", jid=agent.bare_jid, tls=agent.tls)
    watcher = asyncio.create_task(watch_reconnects(agent))
    try:
        await MODES[args.mode](agent, args, stop)
    except Exception as exc:
        emit("error", reason=f"{type(exc).__name__}: {exc}")
        return 1
    finally:
        watcher.cancel()
        await agent.stop()
    return 0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--jid", required=True)
    p.add_argument("--password", required=True)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--server", default=None, help="host to connect to (default: the JID's domain)")
    p.add_argument("--peers", default="", help="comma-separated JIDs whose messages are accepted")
    p.add_argument("--register", action="store_true", help="try in-band registration (closed: it fails)")
    p.add_argument("--max-body", type=int, default=4096)
    p.add_argument("--connect-timeout", type=float, default=30.0)
    p.add_argument("--warmup", type=float, default=0.0, help="seconds to wait once online")
    p.add_argument("--to", default="")
    p.add_argument("--count", type=int, default=100)
    p.add_argument("--burst", type=int, default=500)
    p.add_argument("--interval", type=float, default=0.1)
    p.add_argument("--body", default="hello")
    p.add_argument("--body-size", type=int, default=None)
    p.add_argument("--ontology", default="quekaro")
    p.add_argument("--conversation", default="c-1")
    p.add_argument("--linger", type=float, default=1.0)
    p.add_argument("--copies", type=int, default=1, help="send mode: how many times to send the message")
    p.add_argument("--rate", default="", help="RATE,BURST: each sender's allowance (core.transport.rates)")
    p.add_argument("mode", choices=sorted(MODES))
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    level = getattr(logging, os.environ.get("PEER_LOG", "WARNING"))
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    return asyncio.run(amain(parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
