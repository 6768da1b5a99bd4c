"""Driving the master's auction in tests: each old-style call as the stimulus the master now sends it."""

from __future__ import annotations

import random
from collections.abc import Iterable, Mapping, Sequence

from core.model import messages as m
from core.model.units import WorkUnit
from master import auction as au


def message(a: au.Auction, sender: str, msg: m.Message, now: float) -> list[au.Instruction]:
    """A message from an agent, as the master's XMPP handler passes it."""
    return a.handle(au.MessageReceived(sender, msg), now)


def register(a: au.Auction, agent: str, now: float, speed: float = 1.0, slots: int | None = None,
             rules: tuple[str | None, str | None] = (None, None)) -> list[au.Instruction]:
    """An agent's Register (the Welcome it answers with is dropped)."""
    msg = m.Register(conversation=f"register-{agent}", speed=speed, threads=1, rules="r", slots=slots,
                     rules_sha256=rules[0], defuzzifier=rules[1])
    out = message(a, agent, msg, now)
    return [i for i in out if not (isinstance(i, au.SendToAgent) and isinstance(i.message, m.Welcome))]


def tick(a: au.Auction, now: float) -> list[au.Instruction]:
    return a.handle(au.Tick(), now)


def submit(a: au.Auction, info: m.JobInfo, units: Sequence[WorkUnit], done: Iterable[int] = (),
           failures: Iterable[tuple[int, str, str]] = (), delivered_by: Mapping[int, str] | None = None,
           channels: tuple[str, ...] | None = None) -> list[au.Instruction]:
    return a.handle(au.JobSubmitted(info, units, channels, frozenset(done), tuple(failures),
                                    dict(delivered_by or {})), 0.0)


def cancel(a: au.Auction, job_id: str, reason: str = "cancelled by the user") -> list[au.Instruction]:
    return a.handle(au.JobCancelRequested(job_id, reason), 0.0)


def stored(award: m.Award, seconds: float, depth: int = 4, spp: int = 8, band: int = 2, nonfinite: int = 0,
           sha256: str = "cd" * 32, channels: tuple[str, ...] = (), first_spp: int | None = None,
           token: str | None = None) -> au.TileStored:
    """The tile an award's holder uploads, as the master stores and reads it back."""
    figures = m.TileFigures(depth=depth, spp=spp, band=band, seconds=seconds, nonfinite=nonfinite,
                            first_spp=first_spp)
    return au.TileStored(award.job.job_id, award.unit.index, award.token if token is None else token,
                         f"/tiles/{award.job.job_id}/{award.unit.index}.exr", sha256, figures, channels)


def tile(a: au.Auction, award: m.Award, seconds: float, now: float, **kw) -> list[au.Instruction]:
    """The award's tile stored at `now`."""
    return a.handle(stored(award, seconds, **kw), now)


def uploadable(a: au.Auction, job_id: str, index: int, token: str) -> bool:
    return a.award_for(job_id, index, token) is not None


def informed(a: au.Auction, agent: str, inform: m.Inform, now: float) -> list[au.Instruction]:
    """What an agent's report of a finished unit stands for: its tile stored with the figures the report
    names (the holder is the award's, whoever `agent` is)."""
    figures = m.TileFigures(depth=inform.depth, spp=inform.spp, band=inform.band, seconds=inform.seconds,
                            nonfinite=inform.nonfinite)
    tile = au.TileStored(inform.job_id, inform.index, inform.token, f"/tiles/{inform.job_id}/{inform.index}.exr",
                         inform.tile_hash, figures, ())
    return a.handle(tile, now)


def refusal(info: m.JobInfo, unit: WorkUnit, figures: m.TileFigures) -> str:
    """Why the auction refuses a tile with these figures for the job's unit, once awarded ("" if it takes it)."""
    a = au.Auction(au.Config(slots=2), rng=random.Random(1))
    submit(a, info, [unit])
    register(a, "agent-1@localhost", 0.0)
    [call] = [i.message for i in tick(a, 0.0) if isinstance(i, au.SendToAgent)]
    estimates = tuple(m.Estimate(index=u.index, seconds=1.0) for u in call.units)
    propose = m.Propose(conversation=call.conversation, job_id=info.job_id, estimates=estimates)
    message(a, "agent-1@localhost", propose, 0.0)
    [award] = [i.message for i in tick(a, 0.0) if isinstance(i, au.SendToAgent) and isinstance(i.message, m.Award)]
    tile = au.TileStored(info.job_id, unit.index, award.token, "/tiles/t.exr", "cd" * 32, figures, ())
    return next((i.reason for i in a.handle(tile, 1.0) if isinstance(i, au.RefuseTile)), "")
