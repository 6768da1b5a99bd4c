"""The render agent: bids on the master's units, renders the ones it is awarded, uploads their tiles.

`RenderAgent` carries out the I/O of `agents.state.AgentState`, which makes every decision: one `FarmAgent`
(XMPP), one `RenderProcess` (the renders) and its own `Planner` (the rules). Its protocol: `RenderAgent`'s
docstring, and docs/ARCHITECTURE.md ("Message flow of one unit"). Run it with
`python -m agents.render_agent --server HOST --port P --jid J --password PW --master M` (`--log-format json`).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import logging
import os
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from agents.emulate import MARK, Emulation
from agents.speed import SpeedSample, estimate_seconds, measure_speed
from agents.state import (
    HEARTBEAT_S,
    MAX_RENDER_S,
    SLOTS,
    AbortRender,
    AgentState,
    BundleFailed,
    BundleReady,
    Calibration,
    DiscardTile,
    FetchBundle,
    Instruction,
    Log,
    Measured,
    MessageReceived,
    Params,
    RenderFailed,
    RenderFinished,
    SendToMaster,
    StartRender,
    Stimulus,
    Tick,
    Transition,
    Upload,
    UploadDone,
    UploadFailed,
    describe,
)
from agents.transfer import fetch_bundle, upload_tile
from core.errors import QuekaroError
from core.home import default_home, make_private
from core.image.tiles import Tile, write_tile
from core.logs import FORMATS, configure, fields
from core.model import messages as m
from core.model.hashing import sha256_file
from core.model.job import SceneSpec
from core.model.units import WorkUnit
from core.render.batch import batch_name, batches, render_batch, together_problem_here
from core.render.process import RenderProcess, RenderRequest
from core.rules.unit_params import Planner, RenderParams, adaptive_params
from core.scene.bundle import RULES_NAME, BundleLimits, check_unpacked, read_manifest
from core.transport.credentials import xmpp_password
from core.transport.tls import client_context, is_loopback
from core.transport.xmpp import Envelope, FarmAgent
from fuzzy.engine import DEFUZZIFIERS
from fuzzy.errors import RuleFileError

log = logging.getLogger(__name__)

POLL_S = 0.25  # how often the beat loop ticks (to Register again at once after a reconnect)
ACCEPTED = frozenset({"cfp", "accept-proposal", "accept-proposals", "reject-proposal", "cancel", "welcome",
                      "introduce"})



def host_name() -> str | None:
    """This machine's name as Register carries it (letters, digits, '.', '_', '-'), or None if it has none."""
    name = re.sub(r"[^A-Za-z0-9._-]", "-", socket.gethostname())[:253]
    return name or None

@dataclass
class AgentConfig:
    """How one render agent runs. `workdir` holds its bundle cache (by sha256) and its tiles."""

    jid: str
    password: str
    master: str
    master_url: str = ""  # where bundles and tiles travel (`--master-url`); none: nowhere
    server: str | None = None  # host of the XMPP server; default: the JID's domain
    port: int = 5222
    threads: int = 1  # Dr.Jit threads of the render process
    rules: Path | None = None  # default: core.data.default_rules_path()
    defuzzifier: str | None = None  # None: the rule file's dialect decides (centroid, or MASYRO's centre of sums)
    workdir: Path = field(default_factory=lambda: default_home().parent / "agents" / "agent")
    ca_file: str | None = None  # the farm's CA: verifies the XMPP server and the master's HTTPS
    verify_security: bool = False
    insecure_http: bool = False  # accept a plain-HTTP data plane across a network (said in every refusal)
    heartbeat_s: float = HEARTBEAT_S
    slots: int = SLOTS  # units held at once (a batch rendering, the others waiting); 1: no overlap
    max_render_s: float = MAX_RENDER_S  # a render longer than this is killed whatever the estimate
    bundle_limits: BundleLimits = field(default_factory=BundleLimits)
    emulate: Path | None = None  # a cost map (agents/emulate.py): renders are slept, Mitsuba never loads
    emulate_speed: float = 1.0  # the emulated agent's speed, as a factor of the map's


class UnitStepError(QuekaroError):
    """A step of a unit (its bundle, render or upload) that failed; the message is the Failure's reason."""


class _StepTime:
    """What is left of a render step's timeout."""

    def __init__(self, timeout: float) -> None:
        self.timeout, self.deadline = timeout, time.monotonic() + timeout

    def spent(self) -> bool:
        return time.monotonic() >= self.deadline

    def left(self) -> float:
        """The seconds left, raising UnitStepError once none are."""
        if self.spent():
            raise UnitStepError(f"not rendered: its render step's {self.timeout:.0f} s were spent before its call")
        return self.deadline - time.monotonic()


class RenderAgent:
    """A render agent; `await run()` serves until `await stop()` (or a signal, in `main`). Its decisions are
    `self.state`'s (agents.state.AgentState); this class carries out their I/O.

    Its side of the protocol, as master.auction expects it:
      start   measure speed -> Register; again after each reconnect, when the master's Introduce asks, and
              with each heartbeat until a Welcome answers; then a Heartbeat every 2 s listing its units.
      cfp     with room (fewer than `slots` held) a Propose with an estimate per unit (`estimate`); else Refuse.
      award   (or an Awards message, each award handled as if sent alone) fetch the bundle, plan, render with
              the award's seed, upload the tile with its token; a unit's error -> Failure, and the agent goes on.
      cancel  drop the unit (or every unit of the job): a render none of whose units is wanted is killed,
              queued ones (and one still fetching its bundle) never start.
    Duplicate awards (same token) are ignored; a re-award's new token replaces the old one. Messages are
    handled one at a time and never wait: a fetch, a render step or an upload runs as a task that feeds its
    end back as a stimulus, and a step's tiles upload while the next step renders."""

    def __init__(self, config: AgentConfig) -> None:
        self.config = config
        self.workdir = Path(config.workdir)
        self.planner = Planner(config.rules, config.defuzzifier)
        # --emulate: the render process and the speed measurement are the emulation's (agents/emulate.py).
        self.emulation = Emulation.load(config.emulate, config.emulate_speed, self.workdir) if config.emulate else None
        self.worker = self.emulation.worker if self.emulation else RenderProcess()
        self._aborts: dict[int, threading.Event] = {}  # per render ticket: set to end it (AbortRender)
        self._together: dict[str, str | None] = {}  # per job: why its units render one by one (None: they need not)
        self.farm = FarmAgent(
            config.jid, config.password, port=config.port, server=config.server, ontology=m.ONTOLOGY,
            peers=[config.master], validate=m.parse, performatives=ACCEPTED, ca_file=config.ca_file,
            verify_security=config.verify_security,
        )
        self.farm.set_handler(self._on_envelope)
        if self.emulation:
            self.emulation.watch(self.farm, self._on_envelope)
        self.speed: SpeedSample | None = None
        self.state = AgentState(self._plan, estimate_seconds, slots=config.slots, threads=config.threads,
                                rules=self.planner.rules_path.name, heartbeat_s=config.heartbeat_s,
                                max_render_s=config.max_render_s, session=_stamp(), check_url=self._url_refusal,
                                batch=1 if self.emulation else None,  # an emulated render sleeps a unit at a time
                                rules_sha256=self.planner.rulebase.digest(), defuzzifier=config.defuzzifier,
                                host=host_name())
        self._tls = client_context(Path(config.ca_file) if config.ca_file else None)
        self._planners: dict[tuple[str | None, str | None], Planner] = {(None, config.defuzzifier): self.planner}
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task] = []
        self._io: set[asyncio.Task] = set()  # bundle fetches, renders and uploads under way
        self._bundle_locks: dict[str, asyncio.Lock] = {}
        self._stimuli = itertools.count(1)  # numbers the stimulus ids of messages and ticks

    @property
    def jid(self) -> str:
        return self.farm.bare_jid

    @property
    def calibration(self) -> Calibration:
        return self.state.calibration

    @property
    def units_done(self) -> int:
        return self.state.units_done

    @property
    def units_failed(self) -> int:
        return self.state.units_failed

    def busy_units(self) -> tuple[m.HeldUnit, ...]:
        """The units this agent holds: awarded, not finished, not cancelled."""
        return self.state.busy_units()

    def is_free(self) -> bool:
        """Room for another unit (AgentState.is_free)."""
        return self.state.is_free()

    def estimate(self, job: m.JobInfo, unit: WorkUnit, params: RenderParams) -> float:
        """Seconds this agent expects to spend on the unit (AgentState.estimate): cost x the spp its own rules
        pick / speed, plus a kernel compilation for a new window size, times the job's learnt correction.
        The master adds the wait behind the units the agent holds."""
        return self.state.estimate(job, unit, params)

    # ---- life-cycle ---------------------------------------------------------------------------------

    async def run(self) -> None:
        """Measure speed, connect, register, then serve until stopped."""
        if make_private(self.workdir, "--workdir"):
            log.warning("--workdir %s: others could read it; now only this user can", self.workdir)
        (self.workdir / "tiles").mkdir(exist_ok=True)
        (self.workdir / "bundles").mkdir(exist_ok=True)
        await asyncio.to_thread(self.worker.start)
        measure = self.emulation.measure_speed if self.emulation else measure_speed
        self.speed = await asyncio.to_thread(measure, self.worker, self.config.threads)
        log.info("%s: speed %.3f Mrays/s (reference render %.3f s, %s)", self.config.jid, self.speed.speed,
                 self.speed.seconds, self.speed.variant)
        await self._feed(Measured(self.speed.speed, self.speed.compile_s, stimulus_id="measured"))
        await self.farm.start()
        self._tasks = [asyncio.create_task(self._beat_forever(), name="agent heartbeat")]
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()

    async def stop(self) -> None:
        """Ask `run` to return; safe to call from a signal handler's task or before `run` started."""
        self._stop.set()

    async def _shutdown(self) -> None:
        tasks = [*self._tasks, *self._io]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        # A render in flight is abandoned: the child is asked to exit, then killed (RenderProcess.stop).
        await asyncio.to_thread(self.worker.stop)
        with contextlib.suppress(Exception):
            await self.farm.stop()

    async def _beat_forever(self) -> None:
        """Tick the state: it registers after every (re)connection and beats every `heartbeat_s` seconds."""
        while True:
            with _logged("tick"):
                await self._feed(Tick(online=self.farm.online, connection=self.farm.reconnects,
                                      stimulus_id=f"tick-{next(self._stimuli)}"))
            await asyncio.sleep(POLL_S)

    # ---- stimuli in, instructions out ---------------------------------------------------------------

    async def _on_envelope(self, env: Envelope) -> None:
        msg = m.parse(env.performative, env.body)  # the gate validated it already: this cannot fail
        if msg.conversation != env.conversation_id:
            log.warning("%s from %s: conversation %r in the body, %r in the metadata: ignored",
                        env.performative, env.sender, msg.conversation, env.conversation_id)
            return
        sid = f"{env.performative}:{env.conversation_id}#{next(self._stimuli)}"  # e.g. cfp:cfp-ab12-3#41
        if isinstance(msg, m.Awards):
            for award in msg.each():  # as if sent one by one
                await self._feed(MessageReceived(award, stimulus_id=f"{sid}:{award.unit.index}"))
        elif isinstance(msg, m.CallForProposal | m.Award | m.Reject | m.Cancel | m.Welcome | m.Introduce):
            await self._feed(MessageReceived(msg, stimulus_id=sid))

    async def _feed(self, stimulus: Stimulus) -> None:
        """One stimulus into the state machine, and its instructions carried out (long ones as tasks)."""
        await self._execute(self.state.handle(stimulus, time.monotonic()))

    async def _execute(self, instructions: list[Instruction]) -> None:
        for instruction in instructions:
            match instruction:
                case SendToMaster(message=msg):
                    if isinstance(msg, m.Failure):
                        self._log_story(msg.job_id, msg.index)
                    with _logged(f"sending {msg.performative}"):
                        await self._send(msg)
                case Log(level=level, text=text):
                    log.log(level, "%s", text)
                case DiscardTile(job_id=job_id, index=index):
                    self._remove_tile(job_id, index)
                case AbortRender(ticket=ticket):
                    if ticket in self._aborts:
                        log.info("ending the render of ticket %d: its units were cancelled", ticket)
                        self._aborts[ticket].set()
                        self.worker.interrupt()
                case StartRender(ticket=ticket):
                    self._aborts[ticket] = threading.Event()  # now: a cancel may come before its task runs
                    self._perform_later(instruction)
                case FetchBundle() | Upload():
                    self._perform_later(instruction)

    def _log_story(self, job_id: str, index: int) -> None:
        """A failed unit's status changes, on one line: what happened to it, and when."""
        story = self.state.story(job_id, index)
        log.warning("unit %d of job %s: story: %s", index, job_id, story_line(story),
                    extra=fields(job_id=job_id, index=index, story=[vars(t) for t in story]))

    def _perform_later(self, command: FetchBundle | StartRender | Upload) -> None:
        task = asyncio.create_task(self._perform(command), name=f"{type(command).__name__} {command.ticket}")
        self._io.add(task)
        task.add_done_callback(self._io.discard)

    async def _perform(self, command: FetchBundle | StartRender | Upload) -> None:
        """One I/O step of a unit (of a batch's units), as a task of its own; its end goes back to the state
        as a stimulus per unit."""
        match command:
            case FetchBundle():
                stimuli: list[Stimulus] = [await self._fetch(command)]
            case StartRender():
                try:
                    stimuli = list(await self._render(command))
                except Exception as exc:  # every unit of the step is answered, or the agent would wait forever
                    stimuli = [RenderFailed(ticket, describe(exc), stimulus_id=f"render-{ticket}")
                               for ticket in command.tickets]
                finally:  # however the render ended: its abort has no render left to end
                    self._aborts.pop(command.ticket, None)
            case Upload():
                stimuli = [await self._upload(command)]
        for stimulus in stimuli:
            with _logged(f"handling {stimulus!r}"):
                await self._feed(stimulus)

    async def _send(self, msg: m.Message) -> bool:
        performative, body = m.encode(msg)
        return await self.farm.send(self.config.master, performative, body, conversation_id=msg.conversation,
                                    protocol=m.PROTOCOL, ontology=m.ONTOLOGY)

    # ---- planning (a computation the state machine calls) -------------------------------------------

    def _url_refusal(self, url: str) -> str | None:
        """Why the agent will not fetch or upload at `url` (a message names it): not at the master's own
        URL, or plain HTTP across a network."""
        if not at_master(url, self.config.master_url):
            return (f"{url} is not at the master's URL {self.config.master_url or '(none given)'} (--master-url): "
                    "bundles and tiles travel there alone")
        refused = url_refusal(url, self.config.insecure_http)
        if refused is None and not url.startswith("https:") and not is_loopback(urlsplit(url).hostname):
            log.warning("job data at %s travels in plain HTTP (--insecure-http)", url)
        return refused

    def _plan(self, job: m.JobInfo, units: tuple[WorkUnit, ...]) -> list[RenderParams]:
        if job.first_spp is not None or job.passes:  # adaptive or progressive: the master set each unit's samples
            return adaptive_params(units, job.depth, job.min_band)
        features = {k: [float(getattr(u, k)) for u in units] for k in ("C", "S", "Nd")}
        ranges = dict(job.ranges) or None
        planner = self._planner_for(job)
        return planner.plan(features, job.level, user_depth=job.depth, user_spp=job.spp, ranges=ranges,
                            min_band=job.min_band, depth_floor=[u.depth_floor for u in units])

    def _planner_for(self, job: m.JobInfo) -> Planner:
        """The job's own rules once its bundle is here (else this agent's, for a bid's estimate only), with
        the job's defuzzifier if it names one."""
        rules = self.workdir / "bundles" / job.scene_hash / RULES_NAME
        own = job.rules_sha256 is not None and rules.is_file()
        key = (job.rules_sha256 if own else None, job.defuzzifier or self.config.defuzzifier)
        if key not in self._planners:
            self._planners[key] = Planner(rules if own else self.config.rules, key[1])
        return self._planners[key]

    # ---- the I/O steps of a unit: bundle, render, upload --------------------------------------------

    async def _fetch(self, command: FetchBundle) -> BundleReady | BundleFailed:
        sid = f"bundle-{command.ticket}"
        try:
            return BundleReady(command.ticket, await self._scene_for(command.job, command.token), stimulus_id=sid)
        except Exception as exc:
            return BundleFailed(command.ticket, describe(exc), stimulus_id=sid)

    async def _render(self, command: StartRender) -> list[RenderFinished | RenderFailed]:
        """Render the command's units in the render process, in one call where they can (core.render.batch),
        and write their tile EXRs (meta: the unit, the parameters): a stimulus per unit, in the command's order."""
        items = [(command.ticket, command.award, command.params),
                 *((b.ticket, b.award, b.params) for b in command.more)]
        requests = [self._request(command.scene, award, params) for _, award, params in items]
        abort = self._aborts.get(command.ticket)
        job = command.award.job
        may_batch = self.state.batches(job)  # emulated agents have batches of one
        results = await asyncio.to_thread(self._render_tiles, requests, command.timeout_s, abort, may_batch)
        return [await self._written(ticket, award, params, result)
                for (ticket, award, params), result in zip(items, results, strict=True)]

    def _request(self, scene: SceneSpec, award: m.Award, params: Params) -> RenderRequest:
        job, unit = award.job, award.unit
        return RenderRequest(
            scene=scene, variant=job.variant, integrator=job.integrator,
            max_depth=params.depth, spp=params.spp, seed=award.seed, width=job.width, height=job.height,
            unit=unit.rect, band=params.band, threads=self.state.threads_for(job), job_id=job.job_id,
            unit_index=unit.index, sensor=job.sensor, first=job.first_spp,
            pass_index=unit.index if job.passes else None, spill=job.spill)

    def _render_tiles(self, requests: list[RenderRequest], timeout: float, abort: threading.Event | None,
                      may_batch: bool) -> list[Tile | Exception]:
        """Each request's tile, or the error that ended it: in batches of one call each where `may_batch`
        (AgentState.batches) and the scene allows, else one by one, each call within `timeout`. A batch of
        one unit renders as a batch too: on the film of the others, it reuses their kernel where its own
        window would compile one. Batches share the step's `timeout`, and a batch that fails is rendered
        again unit by unit only within what is left of it, so that its units are never held past it (their
        deadline at the master has passed by then). Runs in a worker thread."""
        step = _StepTime(timeout)
        together = may_batch and self._together_problem(requests[0], timeout) is None
        groups = batches(requests) if together else [[r] for r in requests]
        tiles: dict[int, Tile | Exception] = {}
        def alone(request: RenderRequest, budget: Callable[[], float]) -> Tile | Exception:
            return self._attempt(lambda: [self.worker.render(request, budget(), abort)], 1)[0]

        for group in groups:
            if not together:
                made = [alone(group[0], lambda: timeout)]
            else:
                made = self._attempt(lambda g=group: render_batch(self.worker, g, step.left(), abort), len(group))
                failed = made[0] if isinstance(made[0], Exception) else None
                if failed and not step.spent() and not (abort and abort.is_set()):
                    # Each unit on its own (Mitsuba's render call), so that one bad unit (or a crash) fails
                    # alone, its agent is not blocklisted for the job by a whole batch's failures at once,
                    # and a unit the batch's path cannot render is rendered the other way; a batch that ran
                    # out of the step's time leaves none to them, and fails its units with its own reason.
                    log.warning("%s failed together (%s): each rendered alone", batch_name(group), failed)
                    made = [alone(r, step.left) for r in group]
            tiles.update(zip((r.unit_index for r in group), made, strict=True))
        return [tiles[r.unit_index] for r in requests]

    @staticmethod
    def _attempt(render: Callable[[], list[Tile]], units: int) -> list[Tile | Exception]:
        """`render()`'s tiles, or its error (a render error named as the unit's Failure says it) for each unit."""
        try:
            try:
                return list(render())
            except UnitStepError:
                raise
            except QuekaroError as exc:
                raise UnitStepError(f"render failed: {exc}") from exc
        except Exception as exc:
            return [exc] * units

    def _together_problem(self, request: RenderRequest, timeout: float) -> str | None:
        """Why the job's units render one by one (core.render.batch), asked of the render process once a job."""
        if request.job_id not in self._together:
            try:
                problem = self.worker.call(together_problem_here, request, doing="checking the scene", timeout=timeout)
            except Exception as exc:  # not kept: a crash or a timeout says nothing of the scene
                log.warning("job %s: the scene's check failed (%s): its units render one by one", request.job_id,
                            describe(exc))
                return describe(exc)
            if problem:
                log.info("job %s: units render one by one: %s", request.job_id, problem)
            self._together[request.job_id] = problem
            while len(self._together) > 64:
                self._together.pop(next(iter(self._together)))
        return self._together[request.job_id]

    async def _written(self, ticket: int, award: m.Award, params: Params,
                       result: Tile | Exception) -> RenderFinished | RenderFailed:
        """The unit's tile written where its upload reads it, as a stimulus. Its header: the unit, seconds,
        non-finite pixels, spp, depth, band, the rules' crisp outputs and the agent's JID."""
        sid = f"render-{ticket}"
        try:
            if isinstance(result, Exception):
                raise result
            meta = self._tile_meta(award.job, params)
            result.meta.update(self.emulation.mark(meta) if self.emulation else meta)
            path = self._tile_path(award.job.job_id, award.unit.index)
            # Not fsynced: the file lives until its upload; a crash loses the unit, which is rendered again.
            await asyncio.to_thread(write_tile, path, result, durable=False)
        except Exception as exc:
            return RenderFailed(ticket, describe(exc), stimulus_id=sid)
        return RenderFinished(ticket, path, float(result.meta["seconds"]), int(result.meta.get("nonfinite", 0)),
                              int(result.meta["spp"]), stimulus_id=sid)

    def _tile_meta(self, job: m.JobInfo, params: Params) -> dict[str, Any]:
        """What the agent adds to the render's header. The render states what it did (job, unit, spp as
        Mitsuba took it, depth, band, integrator): writing the plan's values over them had reported a
        stratified sampler's rounded spp as the rules' count."""
        return {"outputs": dict(getattr(params, "outputs", {})), "agent": self.jid, "level": job.level,
                "rules": self._planner_for(job).rules_path.name}

    async def _upload(self, command: Upload) -> UploadDone | UploadFailed:
        """Hash the tile and upload it with the award's token. The master counts the unit done by that
        upload, so nothing else is sent."""
        award = command.award
        try:
            sha256 = await asyncio.to_thread(sha256_file, command.path)
            try:
                await upload_tile(award.upload_url, award.token, command.path, sha256, agent=self.jid,
                                  ssl_context=self._tls)
            except Exception as exc:
                raise UnitStepError(f"tile upload to {award.upload_url} failed: {describe(exc)}") from exc
        except Exception as exc:
            return UploadFailed(command.ticket, describe(exc), stimulus_id=f"upload-{command.ticket}")
        return UploadDone(command.ticket, stimulus_id=f"upload-{command.ticket}")

    def _tile_path(self, job_id: str, index: int) -> Path:
        return self.workdir / "tiles" / f"{_safe(job_id)}-{index}.exr"

    def _remove_tile(self, job_id: str, index: int) -> None:
        self._tile_path(job_id, index).unlink(missing_ok=True)

    async def _scene_for(self, job: m.JobInfo, token: str) -> SceneSpec:
        """The job's scene, unpacked from its bundle (fetched once per bundle hash, with an award's token)."""
        digest = job.scene_hash
        folder = self.workdir / "bundles" / digest
        lock = self._bundle_locks.setdefault(digest, asyncio.Lock())
        async with lock:
            if not (folder / "QUEKARO-MANIFEST.json").is_file():
                try:
                    await fetch_bundle(job.scene_url, digest, folder, self.config.bundle_limits, token=token,
                                       ssl_context=self._tls)
                except Exception as exc:
                    raise UnitStepError(f"scene bundle {job.scene_url} not fetched: {describe(exc)}") from exc
        manifest = read_manifest(folder)
        name = getattr(job, "scene_name", None) or manifest["scene"]
        scene = (folder / name).resolve()
        if not scene.is_file() and name != manifest["scene"]:
            scene = (folder / manifest["scene"]).resolve()
        if not scene.is_relative_to(folder.resolve()) or not scene.is_file():
            raise UnitStepError(f"scene {name!r} not found in the bundle of job {job.job_id}")
        defines = {**manifest.get("defines", {}), **(getattr(job, "defines", None) or {})}
        try:
            check_unpacked(scene, defines)
        except QuekaroError as exc:
            raise UnitStepError(f"scene bundle of job {job.job_id} refused: {exc}") from exc
        return SceneSpec(scene, defines, rfilter=job.rfilter)


# ---- small helpers ---------------------------------------------------------------------------------


def _safe(name: str) -> str:
    """A job id as a file name (ids may hold '/', ':' and '@')."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", name)


def story_line(story: list[Transition]) -> str:
    """A unit's story on one line: each status change, the stimulus that made it, its time from the first."""
    if not story:
        return "forgotten"
    return "; ".join(f"{t.start or 'new'} -> {t.finish} by {t.stimulus_id} at +{t.at - story[0].at:.3f} s"
                     for t in story)


def _stamp() -> str:
    return f"{time.time_ns():x}"


@contextlib.contextmanager
def _logged(what: str):
    """Errors of one send, tick or stimulus are logged, never fatal (the next beat tries again)."""
    try:
        yield
    except Exception:
        log.exception("%s failed", what)


# ---- command line ----------------------------------------------------------------------------------


def at_master(url: str, master_url: str) -> bool:
    """Whether `url` lies under the master's URL: its scheme, host and port, and a path below its own."""
    base = master_url.rstrip("/")
    return bool(base) and url.startswith(base + "/") and "/../" not in url[len(base):]


def url_refusal(url: str, insecure_http: bool) -> str | None:
    """Why a job's data plane is refused: plain HTTP to another host, unless `insecure_http`."""
    parts = urlsplit(url)
    if parts.scheme == "https" or is_loopback(parts.hostname) or insecure_http:
        return None
    return (f"refusing a plain-HTTP data plane ({parts.scheme}://{parts.hostname}) across a network: the "
            "master needs --tls-cert (quekaro ca), or this agent --insecure-http")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="quekaro agent",
                                description="A QUEKARO render agent: bids on units, renders them, uploads tiles.")
    p.add_argument("--server", default=None, help="XMPP server host (default: the JID's domain)")
    p.add_argument("--port", type=int, default=5222, help="XMPP client port (default 5222)")
    p.add_argument("--jid", required=True, help="this agent's JID, e.g. agent-1@localhost (unique per process)")
    p.add_argument("--password", help="XMPP password (better: --password-file or $QUEKARO_XMPP_PASSWORD)")
    p.add_argument("--password-file", help="file holding the XMPP password")
    p.add_argument("--master", required=True, help="the master's JID (only its messages are accepted)")
    p.add_argument("--master-url", required=True,
                   help="the master's URL, e.g. https://master-host:8765: bundles are fetched and tiles uploaded "
                        "there alone, whatever URL a message names")
    p.add_argument("--threads", type=int, default=1, help="Dr.Jit threads of the render process (default 1)")
    p.add_argument("--rules", type=Path, default=None, help="rule file (default rules/pathtracing.xml)")
    p.add_argument("--defuzzifier", default=None, choices=DEFUZZIFIERS,
                   help="default for jobs that name none (default: centroid; centre of sums for MASYRO's dialect)")
    p.add_argument("--workdir", type=Path, default=None,
                   help="bundle cache and tiles, made private (default: ~/.quekaro/agents/JID)")
    p.add_argument("--ca-file", default=None,
                   help="the farm's CA certificate: verifies the XMPP server's TLS and the master's HTTPS")
    p.add_argument("--insecure-http", action="store_true",
                   help="accept a master serving plain HTTP across a network (award tokens and tiles in clear)")
    p.add_argument("--heartbeat", type=float, default=HEARTBEAT_S, help="seconds between heartbeats")
    p.add_argument("--slots", type=int, default=SLOTS,
                   help=f"units held at once (default {SLOTS}): half of them render in one call while the next "
                        "half is awarded; 2: one unit a call, the next awarded while it renders; 1: no overlap")
    p.add_argument("--log-level", default=os.environ.get("QUEKARO_LOG", "INFO"))
    p.add_argument("--log-format", choices=FORMATS, default=os.environ.get("QUEKARO_LOG_FORMAT", "text"),
                   help="text: a sentence a line (default); json: one object a line ($QUEKARO_LOG_FORMAT)")
    p.add_argument("--emulate", type=Path, metavar="COSTS.json",
                   help="emulate the renders: sleep each unit's time from this cost map (agents/emulate.py)")
    p.add_argument("--speed", type=float, default=None, help="with --emulate: this agent's speed factor (default 1)")
    return p


def config_from_args(args: argparse.Namespace) -> AgentConfig:
    password = xmpp_password(args.password, args.password_file)
    if args.threads < 1:
        raise QuekaroError(f"--threads {args.threads}: must be at least 1")
    if not 1 <= args.slots <= m.MAX_CFP_UNITS:
        raise QuekaroError(f"--slots {args.slots}: must be from 1 to {m.MAX_CFP_UNITS} (what a Register holds)")
    if args.speed is not None and (args.emulate is None or not args.speed > 0):
        raise QuekaroError(f"--speed {args.speed}: a factor above 0, and only with --emulate")
    workdir = args.workdir or default_home().parent / "agents" / _safe(args.jid)
    return AgentConfig(jid=args.jid, password=password, master=args.master, master_url=args.master_url,
                       server=args.server,
                       port=args.port, threads=args.threads, rules=args.rules, defuzzifier=args.defuzzifier,
                       workdir=workdir, ca_file=args.ca_file,
                       verify_security=bool(args.ca_file), heartbeat_s=args.heartbeat, slots=args.slots,
                       insecure_http=args.insecure_http, emulate=args.emulate,
                       emulate_speed=args.speed or 1.0)


async def serve(config: AgentConfig) -> None:
    """Run an agent until SIGTERM or SIGINT, then stop it cleanly."""
    agent = RenderAgent(config)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, agent._stop.set)
    await agent.run()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    mark = f"{MARK} " if args.emulate else ""  # every line of an emulated agent says so
    try:
        configure(args.log_level, args.log_format, role=args.jid.split("@")[0], prefix=mark)
        asyncio.run(serve(config_from_args(args)))
    except (QuekaroError, RuleFileError, ValueError) as exc:  # a bad option, rule file or login
        print(f"{mark}render agent: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
