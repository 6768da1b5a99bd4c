"""A lying agent: a real XMPP account of the farm that bids 0 s on everything and lies about each unit it
is awarded, until `--lies` awards. Prints one JSON line per lie.

- `--mode foreign` (the chaos test's): answers each award with an INFORM but never its tile, and PUTs an
  invented tile for another unit than the one it holds, with the token it holds.
- `--mode tiles`: uploads a tile for the unit it holds, placed right, whose header lies, one lie per award
  in TILE_LIES' order (another agent named as its renderer, absurd figures, an extra channel); a refused
  one is followed by a FAILURE, as an agent whose upload fails sends.

    python tests/liar_agent.py --jid agent-liar@localhost --port 5222 --master master@localhost --lies 4
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path

import aiohttp
import numpy as np

from core.image.tiles import Tile, write_tile
from core.model import messages as m
from core.model.geometry import Rect
from core.transport.xmpp import Envelope, FarmAgent


def emit(event: str, **fields: object) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


async def put_foreign_tile(award: m.Award) -> int:
    """Upload an invented tile for the unit after the awarded one, with the award's token."""
    other = award.unit.index + 1
    rect = Rect(0, 0, 4, 4)
    with tempfile.TemporaryDirectory() as tmp:
        tile = Tile(np.full((4, 4, 3), 99.0, np.float32), rect, rect, {"job_id": award.job.job_id,
                                                                       "unit_index": other})
        data = write_tile(Path(tmp) / "t.exr", tile, durable=False).read_bytes()
    url = award.upload_url.rsplit("/units/", 1)[0] + f"/units/{other}/tile"
    headers = {"X-Quekaro-Token": award.token, "X-Content-SHA256": hashlib.sha256(data).hexdigest()}
    async with aiohttp.ClientSession() as session, session.put(url, data=data, headers=headers) as resp:
        return resp.status


TILE_LIES = (
    ("forged-agent", {"agent": "agent-0-honest@localhost"}, ()),
    ("absurd-spp", {"spp": 10**9, "seconds": -1e300}, ()),
    ("nan-seconds", {"seconds": "NaN"}, ()),  # float() reads it; a header cannot hold a JSON NaN
    ("extra-channel", {}, ("EVIL",)),
)


async def put_lying_tile(award: m.Award, lie: int) -> tuple[str, int]:
    """Upload a tile for the awarded unit (band 0, flat 0.5) whose header tells TILE_LIES[lie]."""
    name, meta, extra = TILE_LIES[lie % len(TILE_LIES)]
    rect = award.unit.rect
    header = {"job_id": award.job.job_id, "unit_index": award.unit.index, "spp": award.unit.spp or award.job.spp,
              "depth": award.job.depth, "band": 0, "seconds": 0.1, "nonfinite": 0, **meta}
    channels = ("R", "G", "B", *extra)
    with tempfile.TemporaryDirectory() as tmp:
        pixels = np.full((rect.h, rect.w, len(channels)), 0.5, np.float32)
        path = write_tile(Path(tmp) / "t.exr", Tile(pixels, rect, rect, header, channels), durable=False)
        data = path.read_bytes()
    headers = {"X-Quekaro-Token": award.token, "X-Content-SHA256": hashlib.sha256(data).hexdigest()}
    async with aiohttp.ClientSession() as session, session.put(award.upload_url, data=data,
                                                               headers=headers) as resp:
        return name, resp.status


async def run(args: argparse.Namespace) -> int:
    agent = FarmAgent(args.jid, os.environ["QUEKARO_XMPP_PASSWORD"], port=args.port, server="127.0.0.1",
                      ontology=m.ONTOLOGY, peers=[args.master], validate=m.parse,
                      performatives=frozenset({"cfp", "accept-proposal", "accept-proposals", "reject-proposal",
                                               "cancel"}))
    done = asyncio.Event()
    lies = 0

    async def send(msg: m.Message) -> None:
        performative, body = m.encode(msg)
        await agent.send(args.master, performative, body, conversation_id=msg.conversation,
                         protocol=m.PROTOCOL, ontology=m.ONTOLOGY)

    async def on_message(env: Envelope) -> None:
        msg = m.parse(env.performative, env.body)
        for one in msg.each() if isinstance(msg, m.Awards) else (msg,):
            await on_one(one)

    async def on_one(msg: m.Message) -> None:
        nonlocal lies
        if isinstance(msg, m.CallForProposal) and lies < args.lies:
            estimates = tuple(m.Estimate(index=u.index, seconds=0.0) for u in msg.units)
            await send(m.Propose(conversation=msg.conversation, job_id=msg.job.job_id, estimates=estimates))
        elif isinstance(msg, m.Award) and lies < args.lies and args.mode == "tiles":
            lie, status = await put_lying_tile(msg, lies)
            lies += 1
            if status >= 400:
                await send(m.Failure(conversation=msg.conversation, job_id=msg.job.job_id, index=msg.unit.index,
                                     token=msg.token, reason=f"upload refused ({status})"))
            emit("lied", job=msg.job.job_id, unit=msg.unit.index, lie=lie, status=status)
            if lies >= args.lies:
                done.set()
        elif isinstance(msg, m.Award) and lies < args.lies:
            lies += 1
            status = await put_foreign_tile(msg)
            await send(m.Inform(conversation=msg.conversation, job_id=msg.job.job_id, index=msg.unit.index,
                                token=msg.token, tile_hash="ab" * 32, depth=1, spp=1, band=0, seconds=0.0,
                                nonfinite=0))
            emit("lied", job=msg.job.job_id, unit=msg.unit.index, foreign_put=status)
            if lies >= args.lies:
                done.set()

    agent.set_handler(on_message)
    await agent.start()  # its account is made for it (LocalFarm.add_account)
    await send(m.Register(conversation="liar", speed=1000.0, threads=1, rules="lies.xml"))
    emit("online")

    async def heartbeat() -> None:
        while True:
            await send(m.Heartbeat(conversation="hb", busy=()))
            await asyncio.sleep(2.0)

    beat = asyncio.create_task(heartbeat())
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(done.wait(), timeout=args.timeout)
    beat.cancel()
    await agent.stop()
    emit("stopped", lies=lies)
    return 0


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--jid", required=True)
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--master", required=True)
    p.add_argument("--lies", type=int, default=4)
    p.add_argument("--mode", choices=("foreign", "tiles"), default="foreign")
    p.add_argument("--timeout", type=float, default=120.0)
    return asyncio.run(run(p.parse_args()))


if __name__ == "__main__":
    sys.exit(main())
