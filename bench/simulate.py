"""The auction under a simulated clock: the master's real `Auction` driven by discrete events.

Agents here are a few lines each (bid cost / speed, render that long, inform), messages take a fixed
latency and time jumps from event to event, so the scaling benchmark (`bench.scaling`) measures the award
logic that the farm runs, at any number of agents, without a farm. A benchmark's tool, not the product's.
"""

from __future__ import annotations

import heapq
import math
import random
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

from core.image.passes import WEIGHT
from core.model import messages as m
from core.model.geometry import Rect
from core.model.status import JobStatus
from core.model.units import WorkUnit
from master.auction import (
    Auction,
    Config,
    Instruction,
    JobSubmitted,
    MessageReceived,
    PassMerged,
    SendToAgent,
    Tick,
    TileStored,
    pass_origin,
)
from planning.progressive import BUDGET, Goal


@dataclass(frozen=True)
class SimResult:
    makespan: float
    units: int
    agents: int
    busy_s: dict[str, float]  # seconds each agent spent rendering
    messages: int
    master_cpu_s: float = 0.0  # CPU seconds the auction (the master's decisions) took in this process


# The simulated agents render a unit a call, as the farm's did before its agents rendered units in batches:
# 2 slots (one unit a round and a call), the setting the scaling and hosts figures were measured with.
UNBATCHED_AUCTION = Config(slots=2)
PASS_SPP = 16  # a progressive job's samples per unit: its budget, in planning.progressive's budget passes
PASS_CHANNELS = ("R", "G", "B", WEIGHT)


def simulate(
    costs: Sequence[float],
    speeds: Sequence[float],
    latency: float = 0.002,
    config: Config | None = None,
    seed: int = 0,
    heartbeat_s: float = 5.0,
    jitter: float = 0.0,
    delivery: float = 0.0,
    estimates: Sequence[float] | None = None,
    passes: bool = False,
) -> SimResult:
    """Makespan of one job of units with these costs on agents of these speeds, by discrete-event simulation.

    Each message takes `latency` seconds one way; agents estimate cost / speed and render in that time
    (times a uniform factor in [1 - jitter, 1 + jitter]); they beat every `heartbeat_s`. A tile's
    `delivery` (writing, hashing and uploading it) starts when its render ends and delays the inform; the
    agent's next render may start meanwhile if that unit was already awarded (a second slot). The agents register
    at `latency` and the job is submitted at twice that, as a user submits to a running farm (were the job
    first, the first agent to register would be alone to take the biggest unit, whatever its speed). The
    master side is the real `Auction`, so the benchmark measures the award logic that the farm runs; its
    agents render a unit a call, so by default it runs that logic with 2 slots (`UNBATCHED_AUCTION`), as
    a farm does whose agents do not batch (emulated ones, or `--slots 2`). The makespan counts from the
    submission.

    `estimates`: what the agents bid for each unit, in seconds at speed 1 (default: `costs`, exact bids),
    also the unit's cost as the master knows it. Real agents bid from the master's cost (the pixel count at
    level off) times a per-job correction, so their bids miss units that cost more or less per pixel than
    the mean; bench.hosts passes such bids (measured there: with exact bids the simulator came out 8 %
    short of 8 emulated agents, bids of 0.8-1.4x the render time losing the tail).

    `passes`: the job renders progressively (`--progressive`, planning.progressive): each unit's samples in
    passes, each pass a unit of its own at its share of the unit's cost, merged (here: at once) when its
    tile lands, and idle agents take extra passes of the last units. The makespan is the job's, extra
    passes included; `busy_s` counts them too.
    """
    if not costs or not speeds:
        raise ValueError("simulate needs at least one unit and one agent")
    bids = list(costs if estimates is None else estimates)
    if len(bids) != len(costs):
        raise ValueError(f"simulate: {len(bids)} estimates for {len(costs)} units")
    rng = random.Random(seed)
    # Its units have no pixels: each renders its five passes (pass_samples 1), as bench hosts' units do.
    auction = Auction(replace(config or UNBATCHED_AUCTION, pass_samples=1), rng=random.Random(seed + 1))
    info = m.JobInfo(
        job_id="sim",
        scene_url="http://sim/scene",
        scene_hash="0" * 64,
        width=1,
        height=1,
        spp=1,
        depth=1,
        level="off",
        ranges={},
        passes=passes,
    )
    specs = [
        WorkUnit(index=i, rect=Rect(0, 0, 1, 1), C=0.0, S=1, Nd=0.0, cost=float(c) / (PASS_SPP if passes else 1))
        for i, c in enumerate(bids)
    ]
    sim = _Sim(auction, latency, rng, jitter, {f"agent{i}": float(s) for i, s in enumerate(speeds)}, delivery,
               [float(c) for c in costs])
    submitted = 2 * latency
    goal = Goal(BUDGET, PASS_SPP) if passes else None
    sim.push(submitted, "submit", "", JobSubmitted(info, specs, goal=goal))
    for name in sim.speeds:
        sim.push(
            latency,
            "master",
            name,
            m.Register(conversation="r", speed=sim.speeds[name], threads=1, rules="r"),
        )
        sim.push(heartbeat_s, "beat", name, heartbeat_s)
    makespan = sim.run() - submitted
    return SimResult(makespan, len(costs), len(speeds), sim.busy, sim.messages, sim.master_cpu_s)


class _Sim:
    """Event queue of the simulation: messages to the master or an agent, agent heartbeats, timers."""

    def __init__(self, auction: Auction, latency: float, rng: random.Random, jitter: float,
                 speeds: dict[str, float], delivery: float = 0.0, costs: Sequence[float] = ()) -> None:
        self.auction, self.latency, self.rng, self.jitter, self.speeds = auction, latency, rng, jitter, speeds
        self.delivery = delivery
        self.costs = costs  # each unit's render seconds at speed 1 (its bids: the unit's cost)
        self.queue: list[tuple[float, int, str, str, Any]] = []
        self.seq = 0
        self.busy = dict.fromkeys(speeds, 0.0)
        self.render_end = dict.fromkeys(speeds, 0.0)
        self.holding: dict[str, set[tuple[str, int]]] = {name: set() for name in speeds}
        self.messages = 0
        self.timer = math.inf
        self.tick_due = False  # a tick queued after the master's events of this instant (`run`)
        self.merged: dict[int, int] = {}  # a progressive job's samples merged per unit
        self.master_cpu_s = 0.0

    def handle(self, stimulus: Any, now: float) -> list[Instruction]:
        """The auction's answer to `stimulus`, its CPU time counted as the master's."""
        return self._master(self.auction.handle, stimulus, now)

    def _master(self, call: Any, *args: Any) -> Any:
        """`call(*args)`, a decision of the master's, its CPU time counted in `master_cpu_s`."""
        started = time.process_time()
        try:
            return call(*args)
        finally:
            self.master_cpu_s += time.process_time() - started

    def push(self, t: float, kind: str, who: str, payload: Any) -> None:
        self.seq += 1
        heapq.heappush(self.queue, (t, self.seq, kind, who, payload))

    def run(self) -> float:
        job: str | None = None
        while self.queue:
            now, _, kind, who, payload = heapq.heappop(self.queue)
            if kind == "submit":
                self.handle(payload, now)
                job = payload.info.job_id
                self.deliver(self.handle(Tick(), now), now)
            elif kind == "master":
                self.messages += 1
                # A stored tile stands for its upload, which the real master reads and hands to the auction.
                stimulus = payload if isinstance(payload, TileStored) else MessageReceived(who, payload)
                out = self.handle(stimulus, now)
                if isinstance(stimulus, TileStored) and self.auction.merges_passes(stimulus.job_id):
                    out += self.handle(self._merged(stimulus), now)  # the master's merge, at once
                self.send(out, now)  # the tick's `deliver` sets the timer
                if not self.tick_due:  # as the master: one tick after the events already waiting
                    self.tick_due = True
                    self.push(now, "tick", "", None)
            elif kind == "tick":
                self.tick_due = False
                self.deliver(self.handle(Tick(), now), now)
            elif kind == "agent":
                self.messages += 1
                self.agent_receives(who, payload, now)
            elif kind == "beat":
                busy = tuple(m.HeldUnit(job_id=j, index=i) for j, i in sorted(self.holding[who]))
                self.push(now + self.latency, "master", who, m.Heartbeat(conversation="hb", busy=busy))
                if job is None or self._status(job) == JobStatus.RUNNING:
                    self.push(now + payload, "beat", who, payload)
            elif kind == "release":
                self.holding[who].discard(payload)
            elif kind == "timer" and now >= self.timer:
                self.timer = math.inf
                self.deliver(self.handle(Tick(), now), now)
            if job is not None and self._status(job) != JobStatus.RUNNING:
                if self._status(job) != JobStatus.DONE:
                    raise RuntimeError(f"simulated job ended {self._status(job)}: {self.auction.job_view(job).error}")
                return now
        raise RuntimeError("simulation ran out of events before the job finished")

    def _merged(self, tile: TileStored) -> PassMerged:
        """What the master tells the auction once it merged a pass (the samples so far of its unit)."""
        unit, _ = pass_origin(tile.index, self.auction.job_passes(tile.job_id))
        self.merged[unit] = self.merged.get(unit, 0) + tile.figures.spp
        return PassMerged(tile.job_id, tile.index, self.merged[unit], tile.figures.seconds, None)

    def _status(self, job_id: str) -> str:
        return self.auction.job_status(job_id)

    def send(self, instructions: list[Instruction], now: float) -> None:
        """The master's messages, each to arrive a latency later."""
        for item in instructions:
            if isinstance(item, SendToAgent):
                self.push(now + self.latency, "agent", item.to, item.message)

    def deliver(self, instructions: list[Instruction], now: float) -> None:
        """The master's messages sent, and its timer set for the auction's next deadline."""
        self.send(instructions, now)
        due = self._master(self.auction.next_deadline)
        if due is not None and due < self.timer:
            self.timer = max(due, now)
            self.push(self.timer + 1e-9, "timer", "", None)

    def agent_receives(self, name: str, msg: m.Message, now: float) -> None:
        speed = self.speeds[name]
        if isinstance(msg, m.CallForProposal):
            est = tuple(m.Estimate(index=u.index, seconds=u.work / speed) for u in msg.units)
            reply = m.Propose(conversation=msg.conversation, job_id=msg.job.job_id, estimates=est)
            self.push(now + self.latency, "master", name, reply)
        elif isinstance(msg, m.Award):
            cost = self._cost(msg.job, msg.unit)
            seconds = cost / speed * (1 + self.rng.uniform(-self.jitter, self.jitter))
            self.busy[name] += seconds
            self.holding[name].add((msg.job.job_id, msg.unit.index))
            spp = msg.unit.spp or 1
            figures = m.TileFigures(depth=1, spp=spp, band=0, seconds=seconds, nonfinite=0)
            tile = TileStored(msg.job.job_id, msg.unit.index, msg.token, "", "0" * 64, figures,
                              PASS_CHANNELS if msg.job.passes else ())
            # A unit awarded into a free slot starts when the one rendering ends; the tile's delivery
            # (upload) overlaps the next render, and the master has it when that is done.
            end = max(now, self.render_end[name]) + seconds
            self.render_end[name] = end
            self.push(end + self.delivery, "release", name, (msg.job.job_id, msg.unit.index))
            self.push(end + self.delivery + self.latency, "master", name, tile)

    def _cost(self, job: m.JobInfo, unit: WorkUnit) -> float:
        """A unit's render seconds at speed 1; a pass's, its share of its unit's."""
        if not job.passes:
            return self.costs[unit.index] if self.costs else unit.cost
        template, _ = pass_origin(unit.index, self.auction.job_passes(job.job_id))
        return (self.costs[template] if self.costs else unit.cost * PASS_SPP) * (unit.spp or 1) / PASS_SPP
