"""The render agent: bids on the master's units, renders the ones it is awarded, uploads their tiles.

One agent process = one `FarmAgent` (the XMPP transport, core.transport.xmpp) + one `RenderWorker` (a persistent
child process that renders, core.render.worker) + its own rule base (core.render.planner). The protocol, as
master/auction.py expects it:

  start     measure speed (agents/speed.py) -> Register; Register again after every reconnect;
            Heartbeat every 2 s listing the units it holds (awarded, not yet answered, not cancelled).
  cfp       room for another unit (it holds fewer than `slots`: 2 by default, one rendering and one
            waiting, so the render process goes on to the next unit while the last one's tile uploads)
            -> Propose with an estimate per offered unit (cost x the spp its own rules pick / speed, + a
            kernel compilation for a new window size, times a per-job correction learnt from its
            finished units); the master adds the wait behind the unit it holds. Else Refuse.
  award     fetch the job's scene bundle once (cached by sha256 under the work dir), plan the unit
            with its own rules, render it with the award's seed, write the tile EXR (meta: the unit,
            seconds, non-finite pixels, spp, depth, band, the rules' crisp outputs, the agent's JID),
            upload it with the award's token, then Inform (tile sha256 and the parameters). Any error
            of that unit -> Failure with the reason; the agent itself carries on.
  cancel    the unit (or every unit of the job) is dropped: a render in flight finishes and is thrown
            away, queued ones never start.

Duplicate awards (same unit, same token) are ignored; a re-award with a new token replaces the old one's
token. Messages are handled one at a time on the XMPP loop and never wait for a render: renders run in a
worker thread that talks to the render process (asyncio.to_thread), one at a time in award order; each
finished tile is hashed, uploaded and informed by a task of its own while the next unit renders.

Run it with `python -m agents.render_agent --server HOST --port P --jid J --password PW --master M`.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import re
import signal
import sys
import tempfile
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.speed import SpeedSample, estimate_seconds, measure_speed
from agents.transfer import fetch_bundle, upload_tile
from core.errors import QuekaroError
from core.model import messages as m
from core.model.hashing import sha256_file
from core.model.job import SceneSpec
from core.model.units import WorkUnit
from core.render.bundle import RULES_NAME, BundleLimits, check_unpacked, read_manifest
from core.render.planner import Planner, RenderParams
from core.render.tiles import Tile, write_tile
from core.render.worker import RenderRequest, RenderWorker
from core.transport.credentials import xmpp_password
from core.transport.xmpp import Envelope, FarmAgent
from fuzzy.engine import DEFUZZIFIERS
from fuzzy.errors import RuleFileError

log = logging.getLogger(__name__)

HEARTBEAT_S = 2.0
POLL_S = 0.25  # how often the beat loop looks for a reconnect (to Register again at once)
ACCEPTED = frozenset({"cfp", "accept-proposal", "reject-proposal", "cancel"})
FINISHED_MEMORY = 4096  # (job, unit, token) of finished awards remembered to ignore their duplicates


@dataclass
class AgentConfig:
    """How one render agent runs. `workdir` holds its bundle cache (by sha256) and its tiles."""

    jid: str
    password: str
    master: str
    server: str | None = None  # host of the XMPP server; default: the JID's domain
    port: int = 5222
    threads: int = 1  # Dr.Jit threads of the render process
    rules: Path | None = None  # default: core.data.default_rules_path()
    defuzzifier: str | None = None  # None: the rule file's dialect decides (centroid, or MASYRO's centre of sums)
    workdir: Path = field(default_factory=lambda: Path(tempfile.gettempdir()) / "quekaro-agent")
    auto_register: bool = False  # in-band registration: the embedded server only
    ca_file: str | None = None
    verify_security: bool = False
    heartbeat_s: float = HEARTBEAT_S
    slots: int = 2  # units held at once (one rendering, the others waiting); 1: no overlap
    max_render_s: float = 6 * 3600.0  # a render longer than this is killed whatever the estimate
    bundle_limits: BundleLimits = field(default_factory=BundleLimits)


@dataclass
class Work:
    """One awarded unit: the latest award for it, and whether the master took it back."""

    award: m.Award
    cancelled: bool = False

    @property
    def key(self) -> tuple[str, int]:
        return self.award.job.job_id, self.award.unit.index


class RenderFailed(QuekaroError):
    """A unit that could not be rendered or delivered; the message is the Failure's reason."""


class Calibration:
    """Per job, the ratio of a unit's real wall time to its uncorrected estimate (moving average).

    The base estimate (agents/speed.py) misses what the reference render cannot know: scene loading,
    kernel compilation, bundle transfer, and a master cost scale that differs from rays (level off).
    """

    def __init__(self, alpha: float = 0.5, max_jobs: int = 64) -> None:
        self.alpha = alpha
        self.ratios: dict[str, float] = {}
        self.max_jobs = max_jobs

    def factor(self, job_id: str) -> float:
        return self.ratios.get(job_id, 1.0)

    def learn(self, job_id: str, base_estimate: float, actual: float) -> None:
        if base_estimate <= 0 or actual <= 0:
            return
        ratio = actual / base_estimate
        old = self.ratios.pop(job_id, None)
        self.ratios[job_id] = ratio if old is None else old + self.alpha * (ratio - old)
        while len(self.ratios) > self.max_jobs:  # oldest job first (dicts keep insertion order)
            self.ratios.pop(next(iter(self.ratios)))


class RenderAgent:
    """A render agent; `await run()` serves until `await stop()` (or a signal, in `main`)."""

    def __init__(self, config: AgentConfig) -> None:
        self.config = config
        self.workdir = Path(config.workdir)
        self.planner = Planner(config.rules, config.defuzzifier)
        self.worker = RenderWorker()
        self.farm = FarmAgent(
            config.jid, config.password, port=config.port, server=config.server, ontology=m.ONTOLOGY,
            peers=[config.master], validate=m.parse, performatives=ACCEPTED, ca_file=config.ca_file,
            verify_security=config.verify_security,
        )
        self.farm.set_handler(self._on_envelope)
        self.speed: SpeedSample | None = None
        self.calibration = Calibration()
        self.works: dict[tuple[str, int], Work] = {}
        self.finished: deque[tuple[str, int, str]] = deque(maxlen=FINISHED_MEMORY)
        self.kernels: set[tuple[Any, ...]] = set()  # what this agent's render process has compiled
        self.rendering = False
        self._deliveries: set[asyncio.Task] = set()
        self._planned: dict[tuple[str, int], RenderParams] = {}  # the rules' choice per unit bid on
        self._planners: dict[tuple[str | None, str | None], Planner] = {(None, config.defuzzifier): self.planner}
        self.units_done = 0
        self.units_failed = 0
        self._queue: asyncio.Queue[Work] = asyncio.Queue()
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task] = []
        self._bundle_locks: dict[str, asyncio.Lock] = {}

    @property
    def jid(self) -> str:
        return self.farm.bare_jid

    # ---- life-cycle ---------------------------------------------------------------------------------

    async def run(self) -> None:
        """Measure speed, connect, register, then serve until stopped."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        (self.workdir / "tiles").mkdir(exist_ok=True)
        (self.workdir / "bundles").mkdir(exist_ok=True)
        await asyncio.to_thread(self.worker.start)
        self.speed = await asyncio.to_thread(measure_speed, self.worker, self.config.threads)
        log.info("%s: speed %.3f Mrays/s (reference render %.3f s, %s)", self.config.jid, self.speed.speed,
                 self.speed.seconds, self.speed.variant)
        await self.farm.start(auto_register=self.config.auto_register)
        self._tasks = [asyncio.create_task(self._beat_forever(), name="agent heartbeat"),
                       asyncio.create_task(self._render_forever(), name="agent renders")]
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()

    async def stop(self) -> None:
        """Ask `run` to return; safe to call from a signal handler's task or before `run` started."""
        self._stop.set()

    async def _shutdown(self) -> None:
        tasks = [*self._tasks, *self._deliveries]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        # A render in flight is abandoned: the child is asked to exit, then killed (RenderWorker.stop).
        await asyncio.to_thread(self.worker.stop)
        with contextlib.suppress(Exception):
            await self.farm.stop()

    # ---- messages out -------------------------------------------------------------------------------

    async def _send(self, msg: m.Message) -> bool:
        performative, body = m.encode(msg)
        return await self.farm.send(self.config.master, performative, body, conversation_id=msg.conversation,
                                    protocol=m.PROTOCOL, ontology=m.ONTOLOGY)

    async def _register(self) -> None:
        assert self.speed is not None
        rules = self.planner.rules_path.name[:256]
        await self._send(m.Register(conversation=f"register-{_stamp()}", speed=self.speed.speed,
                                    threads=self.config.threads, rules=rules))

    def busy_units(self) -> tuple[m.HeldUnit, ...]:
        """The units this agent holds: awarded, not finished, not cancelled."""
        keys = sorted(k for k, w in self.works.items() if not w.cancelled)
        return tuple(m.HeldUnit(job_id=j, index=i) for j, i in keys)

    async def _beat_forever(self) -> None:
        """Register now and after every reconnect; a heartbeat every `heartbeat_s` seconds."""
        registered_at = -1
        next_beat = 0.0
        while True:
            if self.farm.online and registered_at != self.farm.reconnects:
                with _logged("register"):
                    await self._register()
                    registered_at = self.farm.reconnects
                    next_beat = 0.0
            if self.farm.online and time.monotonic() >= next_beat:
                with _logged("heartbeat"):
                    await self._send(m.Heartbeat(conversation=f"hb-{_stamp()}", busy=self.busy_units()[:256]))
                next_beat = time.monotonic() + self.config.heartbeat_s
            await asyncio.sleep(POLL_S)

    # ---- messages in --------------------------------------------------------------------------------

    async def _on_envelope(self, env: Envelope) -> None:
        msg = m.parse(env.performative, env.body)  # the gate validated it already: this cannot fail
        if msg.conversation != env.conversation_id:
            log.warning("%s from %s: conversation %r in the body, %r in the metadata: ignored",
                        env.performative, env.sender, msg.conversation, env.conversation_id)
            return
        match msg:
            case m.CallForProposal():
                await self._on_cfp(msg)
            case m.Award():
                self._on_award(msg)
            case m.Cancel():
                self._on_cancel(msg)
            case m.Reject():
                log.debug("rejected in %s: %s", msg.conversation, msg.reason)

    def is_free(self) -> bool:
        """Room for another unit: it holds fewer than `slots` (rendering, waiting or uploading). With one
        slot, also not rendering at all (not even a cancelled unit)."""
        held = sum(not w.cancelled for w in self.works.values())
        if self.config.slots == 1:
            return not self.rendering and held == 0
        return held < self.config.slots

    async def _on_cfp(self, cfp: m.CallForProposal) -> None:
        job_id = cfp.job.job_id
        if not self.is_free():
            held = ", ".join(f"{j}/{i}" for j, i in self.works) or "a cancelled unit"
            await self._send(m.Refuse(conversation=cfp.conversation, job_id=job_id,
                                      reason=f"busy rendering {held}"[:1024]))
            return
        try:
            plans = self._plan(cfp.job, cfp.units)
        except Exception as exc:  # a rule base that cannot plan this job: say so rather than bid
            await self._send(m.Refuse(conversation=cfp.conversation, job_id=job_id,
                                      reason=f"cannot plan units: {type(exc).__name__}: {exc}"[:1024]))
            return
        for u, p in zip(cfp.units, plans, strict=True):
            self._remember_plan(job_id, u.index, p)
        estimates = tuple(m.Estimate(index=u.index, seconds=min(self.estimate(cfp.job, u, p), 1e9))
                          for u, p in zip(cfp.units, plans, strict=True))
        log.info("proposing for %s: %s", job_id, ", ".join(f"{e.index}: {e.seconds:.3f} s" for e in estimates))
        await self._send(m.Propose(conversation=cfp.conversation, job_id=job_id, estimates=estimates))

    def estimate(self, job: m.JobInfo, unit: WorkUnit, params: RenderParams) -> float:
        """Seconds this agent expects to spend on the unit (see agents/speed.py for the units): the base
        estimate, plus a kernel compilation if the window is new, times the job's learned correction."""
        return self._uncorrected(job, unit, params) * self.calibration.factor(job.job_id)

    def _uncorrected(self, job: m.JobInfo, unit: WorkUnit, params: RenderParams) -> float:
        return self._base_estimate(unit, params) + self._compile_estimate(job, unit, params)

    def _compile_estimate(self, job: m.JobInfo, unit: WorkUnit, params: RenderParams) -> float:
        # Dr.Jit bakes the window size and the depth into the kernel (design.md section 3).
        if self.speed is None or _kernel_key(job, unit, params) in self.kernels:
            return 0.0
        return self.speed.compile_s

    def _base_estimate(self, unit: WorkUnit, params: RenderParams) -> float:
        speed = self.speed.speed if self.speed else 1.0
        return estimate_seconds(unit.cost, params.spp, speed)

    def _plan(self, job: m.JobInfo, units: tuple[WorkUnit, ...]) -> list[RenderParams]:
        features = {k: [float(getattr(u, k)) for u in units] for k in ("C", "S", "Nd")}
        ranges = dict(job.ranges) or None
        planner = self._planner_for(job)
        return planner.plan(features, job.level, user_depth=job.depth, user_spp=job.spp, ranges=ranges)

    def _planner_for(self, job: m.JobInfo) -> Planner:
        """The job's own rules once its bundle is here (else this agent's, for a bid's estimate only), with
        the job's defuzzifier if it names one."""
        rules = self.workdir / "bundles" / job.scene_hash / RULES_NAME
        own = job.rules_sha256 is not None and rules.is_file()
        key = (job.rules_sha256 if own else None, job.defuzzifier or self.config.defuzzifier)
        if key not in self._planners:
            self._planners[key] = Planner(rules if own else self.config.rules, key[1])
        return self._planners[key]

    def _remember_plan(self, job_id: str, index: int, params: RenderParams) -> None:
        self._planned[(job_id, index)] = params
        while len(self._planned) > FINISHED_MEMORY:
            self._planned.pop(next(iter(self._planned)))  # the oldest first

    def _on_award(self, award: m.Award) -> None:
        key = (award.job.job_id, award.unit.index)
        if (*key, award.token) in self.finished:
            log.info("duplicate award of finished unit %s/%d ignored", *key)
            return
        work = self.works.get(key)
        if work is not None and not work.cancelled:
            if work.award.token != award.token:
                log.info("unit %s/%d re-awarded: answering under the new award", *key)
                work.award = award
            return
        work = Work(award)
        self.works[key] = work
        self._queue.put_nowait(work)

    def _on_cancel(self, cancel: m.Cancel) -> None:
        for key, work in list(self.works.items()):
            if key[0] == cancel.job_id and cancel.index in (None, key[1]):
                work.cancelled = True
                del self.works[key]
                log.info("unit %s/%d cancelled by the master: %s", *key, cancel.reason)

    # ---- rendering ----------------------------------------------------------------------------------

    async def _render_forever(self) -> None:
        """Render awarded units one at a time; hand each tile to a delivery task and go on at once."""
        while True:
            work = await self._queue.get()
            if work.cancelled:
                continue
            self.rendering = True
            started = time.monotonic()
            try:
                rendered = await self._render_step(work)
            finally:
                self.rendering = False
            if rendered is None:
                self._forget(work)
                continue
            task = asyncio.create_task(self._deliver(work, *rendered, started), name=f"deliver {work.key}")
            self._deliveries.add(task)
            task.add_done_callback(self._deliveries.discard)

    async def _render_step(self, work: Work) -> tuple[Tile, RenderParams, Path] | None:
        """The unit rendered and its tile written; None if it failed (Failure sent) or was cancelled."""
        try:
            rendered = await self._render(work)
        except Exception as exc:
            self._remove_tile(work.key)
            await self._failed(work, exc)
            return None
        if work.cancelled:
            log.info("unit %s/%d rendered after its cancellation: discarded", *work.key)
            self._remove_tile(work.key)
            return None
        return rendered

    async def _deliver(self, work: Work, tile: Tile, params: RenderParams, tile_path: Path, started: float) -> None:
        """Hash and upload the tile, then Inform; the unit is held (heartbeats list it) until this ends."""
        key = work.key
        try:
            try:
                sha256 = await asyncio.to_thread(sha256_file, tile_path)
                award = work.award  # the latest award: a re-award during the render changes the token
                await self._upload(award, tile_path, sha256)
            except Exception as exc:
                await self._failed(work, exc)
                return
            finally:
                self._remove_tile(key)
            if not work.cancelled:
                await self._done(work, award, tile, params, sha256, time.monotonic() - started)
        finally:
            self._forget(work)

    async def _done(self, work: Work, award: m.Award, tile: Tile, params: RenderParams, sha256: str,
                    wall: float) -> None:
        key = work.key
        self.units_done += 1
        self.finished.append((*key, award.token))
        predicted = self._uncorrected(award.job, award.unit, params)
        log.info("unit %s/%d done: %.3f s in all, render %.3f s, spp %d depth %d band %d (award estimate %.3f s)",
                 *key, wall, tile.meta["seconds"], params.spp, params.depth, params.band, award.estimate_s)
        self.kernels.add(_kernel_key(award.job, award.unit, params))
        self.calibration.learn(key[0], predicted, wall)
        await self._send(m.Inform(
            conversation=award.conversation, job_id=key[0], index=key[1], token=award.token,
            tile_hash=sha256, depth=params.depth, spp=params.spp, band=params.band,
            seconds=float(tile.meta["seconds"]), nonfinite=int(tile.meta.get("nonfinite", 0))))

    async def _failed(self, work: Work, exc: BaseException) -> None:
        if not work.cancelled:
            self.units_failed += 1
            await self._fail(work, exc)

    def _forget(self, work: Work) -> None:
        if self.works.get(work.key) is work:
            del self.works[work.key]

    def _remove_tile(self, key: tuple[str, int]) -> None:
        for leftover in self.workdir.joinpath("tiles").glob(f"{_safe(key[0])}-{key[1]}.exr"):
            leftover.unlink(missing_ok=True)

    async def _fail(self, work: Work, exc: BaseException) -> None:
        award = work.award
        reason = str(exc) if isinstance(exc, QuekaroError) else f"{type(exc).__name__}: {exc}"
        log.warning("unit %s/%d failed: %s", *work.key, reason)
        with _logged("failure"):
            await self._send(m.Failure(conversation=award.conversation, job_id=award.job.job_id,
                                       index=award.unit.index, token=award.token,
                                       reason=reason[:1024] or type(exc).__name__))

    async def _render(self, work: Work) -> tuple[Tile, RenderParams, Path]:
        award = work.award
        job, unit = award.job, award.unit
        spec = await self._scene_for(job, award.token)
        # What it bid on (a job's units and their features never change); planned afresh if forgotten,
        # and always with the job's own rules once its bundle is here.
        remembered = self._planned.pop((job.job_id, unit.index), None)
        params = remembered if remembered and not job.rules_sha256 else self._plan(job, (unit,))[0]
        integrator = job.integrator
        unit_job = RenderRequest(
            scene=spec, variant=job.variant, integrator=integrator,
            max_depth=params.depth, spp=params.spp, seed=award.seed, width=job.width, height=job.height,
            unit=unit.rect, band=params.band, threads=self.config.threads, job_id=job.job_id,
            unit_index=unit.index, sensor=job.sensor)
        # Generous: the master's own deadline (estimate x 3 + 30 s) decides when it gives up.
        timeout = min(self.config.max_render_s, 120.0 + 10.0 * self._base_estimate(unit, params))
        try:
            tile = await asyncio.to_thread(self.worker.render, unit_job, timeout)
        except QuekaroError as exc:
            raise RenderFailed(f"render failed: {exc}") from exc
        tile.meta.update({
            "job_id": job.job_id, "unit_index": unit.index, "spp": params.spp, "depth": params.depth,
            "band": params.band, "outputs": dict(params.outputs), "agent": self.jid, "level": job.level,
            "rules": self._planner_for(job).rules_path.name, "integrator": integrator,
        })
        path = self.workdir / "tiles" / f"{_safe(job.job_id)}-{unit.index}.exr"
        # Not fsynced: the file lives until its upload; a crash loses the unit, which is rendered again.
        await asyncio.to_thread(write_tile, path, tile, durable=False)
        return tile, params, path

    # ---- the data plane -----------------------------------------------------------------------------

    async def _scene_for(self, job: m.JobInfo, token: str) -> SceneSpec:
        """The job's scene, unpacked from its bundle (fetched once per bundle hash, with an award's token)."""
        digest = job.scene_hash
        folder = self.workdir / "bundles" / digest
        lock = self._bundle_locks.setdefault(digest, asyncio.Lock())
        async with lock:
            if not (folder / "QUEKARO-MANIFEST.json").is_file():
                try:
                    await fetch_bundle(job.scene_url, digest, folder, self.config.bundle_limits, token=token)
                except Exception as exc:
                    raise RenderFailed(f"scene bundle {job.scene_url} refused: {_why(exc)}") from exc
        manifest = read_manifest(folder)
        name = getattr(job, "scene_name", None) or manifest["scene"]
        scene = (folder / name).resolve()
        if not scene.is_file() and name != manifest["scene"]:
            scene = (folder / manifest["scene"]).resolve()
        if not scene.is_relative_to(folder.resolve()) or not scene.is_file():
            raise RenderFailed(f"scene {name!r} not found in the bundle of job {job.job_id}")
        defines = {**manifest.get("defines", {}), **(getattr(job, "defines", None) or {})}
        try:
            check_unpacked(scene, defines)
        except QuekaroError as exc:
            raise RenderFailed(f"scene bundle of job {job.job_id} refused: {exc}") from exc
        return SceneSpec(scene, defines)

    async def _upload(self, award: m.Award, path: Path, sha256: str) -> None:
        try:
            await upload_tile(award.upload_url, award.token, path, sha256, agent=self.jid)
        except Exception as exc:
            raise RenderFailed(f"tile upload to {award.upload_url} refused: {_why(exc)}") from exc


# ---- small helpers ---------------------------------------------------------------------------------


def _kernel_key(job: m.JobInfo, unit: WorkUnit, params: RenderParams) -> tuple[Any, ...]:
    window = unit.rect.grow(params.band, job.width, job.height)
    return job.scene_hash, window.w, window.h, params.depth, job.integrator


def _safe(name: str) -> str:
    """A job id as a file name (ids may hold '/', ':' and '@')."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", name)


def _stamp() -> str:
    return f"{time.time_ns():x}"


def _why(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, QuekaroError) else f"{type(exc).__name__}: {exc}"


@contextlib.contextmanager
def _logged(what: str):
    """Errors of one send are logged, never fatal (the next beat tries again)."""
    try:
        yield
    except Exception:
        log.exception("sending %s failed", what)


# ---- command line ----------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="quekaro agent",
                                description="A QUEKARO render agent: bids on units, renders them, uploads tiles.")
    p.add_argument("--server", default=None, help="XMPP server host (default: the JID's domain)")
    p.add_argument("--port", type=int, default=5222, help="XMPP client port (default 5222)")
    p.add_argument("--jid", required=True, help="this agent's JID, e.g. agent-1@localhost (unique per process)")
    p.add_argument("--password", help="XMPP password (better: --password-file or $QUEKARO_XMPP_PASSWORD)")
    p.add_argument("--password-file", help="file holding the XMPP password")
    p.add_argument("--master", required=True, help="the master's JID (only its messages are accepted)")
    p.add_argument("--threads", type=int, default=1, help="Dr.Jit threads of the render process (default 1)")
    p.add_argument("--rules", type=Path, default=None, help="rule file (default rules/pathtracing.xml)")
    p.add_argument("--defuzzifier", default=None, choices=DEFUZZIFIERS,
                   help="default for jobs that name none (default: centroid; centre of sums for MASYRO's dialect)")
    p.add_argument("--workdir", type=Path, default=None, help="bundle cache and tiles (default: a temp dir)")
    p.add_argument("--register", action="store_true", help="create the XMPP account in-band (embedded server)")
    p.add_argument("--ca-file", default=None, help="CA certificate to verify the XMPP server's TLS with")
    p.add_argument("--heartbeat", type=float, default=HEARTBEAT_S, help="seconds between heartbeats")
    p.add_argument("--slots", type=int, default=2,
                   help="units held at once: 2 (default) renders the next while the last uploads; 1 none")
    p.add_argument("--log-level", default=os.environ.get("QUEKARO_LOG", "INFO"))
    return p


def config_from_args(args: argparse.Namespace) -> AgentConfig:
    password = xmpp_password(args.password, args.password_file)
    if args.threads < 1:
        raise QuekaroError(f"--threads {args.threads}: must be at least 1")
    if args.slots < 1:
        raise QuekaroError(f"--slots {args.slots}: must be at least 1")
    workdir = args.workdir or Path(tempfile.gettempdir()) / "quekaro-agent" / _safe(args.jid)
    return AgentConfig(jid=args.jid, password=password, master=args.master, server=args.server,
                       port=args.port, threads=args.threads, rules=args.rules, defuzzifier=args.defuzzifier,
                       workdir=workdir, auto_register=args.register, ca_file=args.ca_file,
                       verify_security=bool(args.ca_file), heartbeat_s=args.heartbeat, slots=args.slots)


async def serve(config: AgentConfig) -> None:
    """Run an agent until SIGTERM or SIGINT, then stop it cleanly."""
    agent = RenderAgent(config)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, agent._stop.set)
    await agent.run()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO), stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        asyncio.run(serve(config_from_args(args)))
    except (QuekaroError, RuleFileError, ValueError) as exc:  # a bad option, rule file or login
        print(f"render agent: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
