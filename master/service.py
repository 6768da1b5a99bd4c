"""The master process: job store, auction, HTTP data plane and XMPP agent, wired together.

Every protocol decision is the auction's (`master.auction`); this module turns messages, stored tiles,
submissions, the disk and the clock into its stimuli, and its instructions into I/O: messages over XMPP,
records in the job store and the log, refusals of uploads. It also plans jobs and assembles their images.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import json
import logging
import os
import re
import secrets
import shutil
import socket
import sqlite3
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from core.data import default_rules_path
from core.errors import MessageError, QuekaroError, TileError
from core.home import ADMIN_TOKEN, FARM_FILE, MIN_FREE_BYTES, make_private
from core.image.compose import TileSource
from core.image.passes import WEIGHT
from core.image.tiles import tile_source
from core.logs import fields
from core.model import messages as m
from core.model.hashing import sha256_file
from core.model.job import IMAGE_SUFFIXES, RAW_SUFFIX, JobPlan, JobSpec, RenderOptions, SceneSpec
from core.model.seeds import plan_seed
from core.model.status import JobStatus
from core.model.units import SPP_MAX
from core.render.process import RenderProcess
from core.scene.bundle import (
    BundleLimits,
    bundle_hash,
    check_rules,
    check_unpacked,
    extract_bundle,
    read_manifest,
    submitted_scene,
    submitted_scene_sha256,
)
from core.transport.rates import SenderRates
from core.transport.tls import check_names, is_loopback, server_context
from core.transport.xmpp import FarmAgent
from fuzzy.loader import load_rulebase
from master import auction as au
from master.data_plane import create_app, serve
from master.http_guard import bind_free_port
from master.job_api import add_job_routes
from master.pass_merge import PassMerger, merged_units, passes_so_far, read_verdicts, write_verdicts
from master.sessions import SharedAccounts
from master.store import JobRecord, JobStore, RunningJob
from master.web import add_web_routes
from planning.jobplan import Floors, farm_min_units, plan_job, scene_spp
from planning.pipeline import AOV_PASS_FILE, assemble, kept_aov_pass
from planning.progressive import BUDGET, Goal

log = logging.getLogger(__name__)

TICK_S = 0.2
# What one agent may send: a heartbeat every 2 s, and per unit a proposal (or a refusal) for each auction it
# is called to and an inform or a failure. On units that render in tens of milliseconds that is 25-60 a
# second for seconds on end; a refused proposal stalls its auction for the CFP timeout and the agent's
# pause after it. Several times more is a flood, refused unread (core.transport.rates).
AGENT_RATE, AGENT_BURST = 250.0, 500.0


@dataclass
class MasterConfig:
    """Where the master keeps its state, and how agents and users reach it."""

    home: Path
    jid: str = "master@localhost"
    password: str = ""
    xmpp_host: str | None = None
    xmpp_port: int = 5222
    ca_file: str | None = None
    http_host: str = "127.0.0.1"
    http_port: int = 8765
    public_url: str | None = None  # what agents use to reach the HTTP API (default http(s)://host:port)
    tls_cert: Path | None = None  # the data plane's HTTPS certificate and key (from the farm's CA)
    tls_key: Path | None = None
    insecure_http: bool = False  # plain HTTP although agents reach it over a network (said out loud)
    agent_pattern: str = r"^agent[-\w.]*@{domain}$"  # bare JIDs allowed to bid
    agent_allowlist: Path | None = None  # and, if given, only the bare JIDs listed in this file
    threads: int | None = None  # Dr.Jit threads of the pre-pass
    min_free_bytes: int = MIN_FREE_BYTES  # below this free space in its home the master pauses every job
    auction: au.Config = field(default_factory=au.Config)

    @property
    def url(self) -> str:
        scheme = "https" if self.tls_cert else "http"
        return (self.public_url or f"{scheme}://{self.http_host}:{self.http_port}").rstrip("/")

    def data_plane(self) -> str:
        """How bundles and tiles travel: 'https', 'http (loopback)', or refused (QuekaroError) when plain
        HTTP would cross a network without `insecure_http`, which then reads 'http (insecure: ...)'."""
        public = urlsplit(self.url)
        if self.public_url and not self.http_port:
            raise QuekaroError(f"--public-url {self.public_url} with --http-port 0: the port is chosen at start, "
                               "so the URL agents are given cannot name it; give the port the URL leads to")
        if bool(self.tls_cert) != bool(self.tls_key):
            raise QuekaroError("--tls-cert and --tls-key go together")
        if self.tls_cert:
            if public.scheme != "https":
                raise QuekaroError(f"--public-url {self.url}: the master serves HTTPS (--tls-cert), use https://")
            if public.hostname not in (None, "0.0.0.0", "::"):  # what agents connect to: the certificate's names
                check_names(self.tls_cert, public.hostname, "--public-url" if self.public_url else "--http-host")
            return "https"
        if public.scheme == "https":
            raise QuekaroError(f"--public-url {self.url}: HTTPS needs --tls-cert and --tls-key")
        if is_loopback(self.http_host) and is_loopback(public.hostname):
            return "http (loopback)"
        if self.insecure_http:
            return "http (insecure: award tokens and tiles cross the network in clear, --insecure-http)"
        raise QuekaroError(f"the data plane ({self.url}, bound to {self.http_host}) would be plain HTTP across "
                           "a network: give --tls-cert/--tls-key from the farm's CA (quekaro ca) and an https "
                           "--public-url, or say --insecure-http")

    @property
    def domain(self) -> str:
        return self.jid.split("@", 1)[1].split("/", 1)[0]


class MasterService:
    """The running master. `await start()`, then it serves until `await stop()`."""

    def __init__(self, config: MasterConfig) -> None:
        self.config = config
        self.home = Path(config.home)
        self.jobs_dir = self.home / "jobs"
        if make_private(self.home):
            log.warning("--home %s: others could read it; now only this user can", self.home)
        self.store = JobStore(self.home / "jobs.sqlite")
        self.admin_token = _admin_token(self.home)
        self.auction: au.Auction | None = None
        self.agent = None
        self.data_plane = ""  # how bundles and tiles travel, set by start()
        self._runner = None
        self._http_socket: socket.socket | None = None  # --http-port 0: bound at start (_bind_free_http_port)
        self._ticker: asyncio.Task | None = None
        # Jobs are planned in a child process, one at a time: the pre-pass renders, and a scene that
        # crashes Mitsuba must fail its own job, not the master nor the jobs after it (RenderProcess.call
        # names the crash and starts a new child for the next job).
        self._planner = RenderProcess()
        self._planning = asyncio.Lock()
        # What a job without rules is planned with, as agents tell theirs in Register: what the rules
        # compute (a copy with other comments or layout plans alike), not the file's bytes.
        self._rules_digest = load_rulebase(default_rules_path()).digest()
        self._lock = asyncio.Lock()
        self._assembling: dict[str, asyncio.Task] = {}
        self._aov_passes: set[asyncio.Task] = set()  # denoised jobs' AOV passes under way (`_aov_pass`)
        self._merger = PassMerger()  # progressive jobs' passes, merged as they land (`_merge_later`)
        self._merges: set[asyncio.Task] = set()
        self._agent_re = re.compile(config.agent_pattern.format(domain=re.escape(config.domain)))
        self._unrecorded: list[au.Record] = []  # records the store could not write yet (`_record`)
        self._ticks = itertools.count(1)
        self._tick_due: asyncio.Task | None = None  # the tick after the stimuli waiting (`_tick_soon`)
        self.shared_accounts = SharedAccounts()  # agent JIDs that several clients log in with
        self._allowed: set[str] = set()
        self._allow_stamp: tuple[int, int] | None = None

    # ---- life-cycle ---------------------------------------------------------------------------------

    async def start(self) -> None:
        self.data_plane = self.config.data_plane()  # refuses plain HTTP across a network, before anything
        if self.data_plane.startswith("http (insecure"):
            log.warning("data plane: %s", self.data_plane)
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self._bind_free_http_port()
        now = time.time()
        self._repair_store(now)
        upload = f"{self.config.url}/jobs/{{job}}/units/{{index}}/tile"
        auction_config = dataclasses.replace(self.config.auction, upload_url=upload)
        self.store.resume(now)  # awarded units of running jobs back to pending: the old master's awards are void
        self.auction, records = au.Auction.restore(
            [self._taken_up(job) for job in self.store.running_jobs()],
            lambda job_id: self.job_info(self.store.job(job_id)), self.store.credits(), auction_config, now=now)
        self.store.apply(records, now)
        await self._start_http()
        await self._start_xmpp()
        self._ticker = asyncio.create_task(self._tick_forever(), name="master tick")
        self._write_farm_file()
        for record in self.store.list_jobs("done"):
            if not self.result_path(record.id).with_suffix(".json").exists():
                self._assemble_later(record.id)
        log.info("master %s up: HTTP %s, %d running job(s)", self.config.jid, self.config.url,
                 len(self.store.list_jobs("running")))

    def _taken_up(self, job: RunningJob) -> RunningJob:
        """A running job as the restarted auction takes it up; a progressive one with its goal, its passes so
        far (merged again from their tiles) and the seconds they had run."""
        record = self.store.job(job.job_id)
        if not record.spec.options.in_passes:
            return job
        plan = self.job_plan(record)
        goal = Goal.of(plan.options, plan.spp)
        # A budget job's passes are counted, never merged (PassBook.merges): its tiles are not read here.
        sums = {} if goal.kind == BUDGET else self._merger.restore(job.job_id, len(plan.units),
                                                                     self.store.results(job.job_id))
        so_far = passes_so_far(sums, job.units, set(job.done), len(plan.units))
        attempts = self.store.attempts(job.job_id)  # the time its passes ran: from the first award to the last tile
        ended = [a.finished for a in attempts if a.outcome == "done" and a.finished is not None]
        elapsed = max(ended) - min(a.started for a in attempts) if ended else 0.0
        resumed = au.ResumedPasses(tuple(plan.units), so_far, max(0.0, elapsed))
        return dataclasses.replace(job, channels=_tile_channels(plan),
                                   goal=goal, resumed=resumed)

    def _repair_store(self, now: float) -> None:
        """Units done in the store without their tile on disk go back to auction (jobs not yet assembled)."""
        jobs = [r.id for r in self.store.list_jobs("running")]
        jobs += [r.id for r in self.store.list_jobs("done") if not self.result_path(r.id).with_suffix(".json").exists()]
        for job_id, index in self.store.repair(jobs, now):
            log.warning("job %s unit %d was done without its tile on disk: back to auction", job_id, index)

    async def stop(self) -> None:
        for task in (self._ticker, self._tick_due):
            if task:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        if self.agent is not None:
            await self.agent.stop()
        if self._runner is not None:
            await self._runner.cleanup()
        await asyncio.to_thread(self._planner.stop)
        self.store.close()

    def _bind_free_http_port(self) -> None:
        """--http-port 0: bind a free port now, so that the URL agents and farm.json are given names it
        (a port chosen by a parent and bound here later may be taken in between)."""
        if self.config.http_port:
            return
        try:
            self._http_socket = bind_free_port(self.config.http_host)
        except OSError as exc:
            raise QuekaroError(f"--http-host {self.config.http_host}: cannot bind a free port ({exc})") from None
        self.config = dataclasses.replace(self.config, http_port=self._http_socket.getsockname()[1])

    async def _start_http(self) -> None:
        app = create_app(expected=self._expected_upload, bundle=self._bundle_for, on_tile=self._on_tile,
                         tile_dir=self.jobs_dir, authorize_bundle=self._bundle_allowed)
        add_job_routes(app, self)
        add_web_routes(app, self)  # the web page: same application, same bind address
        tls = server_context(self.config.tls_cert, self.config.tls_key) if self.config.tls_cert else None
        self._runner, _ = await serve(app, self.config.http_host, self.config.http_port, ssl_context=tls,
                                      sock=self._http_socket)

    async def _start_xmpp(self) -> None:
        self.agent = FarmAgent(
            self.config.jid, self.config.password, port=self.config.xmpp_port, server=self.config.xmpp_host,
            ontology=m.ONTOLOGY, accept_sender=self._accepts, validate=m.parse,
            ca_file=self.config.ca_file, verify_security=bool(self.config.ca_file),
            rates=SenderRates(AGENT_RATE, AGENT_BURST),
        )
        self.agent.set_handler(self._on_envelope)
        await self.agent.start()

    def _accepts(self, jid: str) -> bool:
        """Whether a sender may take part: its bare JID matches the agents' pattern and, with an allowlist,
        is listed in it (re-read when the file changes: a supervised farm adds restarted agents)."""
        if not self._agent_re.match(jid):
            return False
        path = self.config.agent_allowlist
        if path is None:
            return True
        try:
            info = path.stat()
            stamp = (info.st_mtime_ns, info.st_size)
            if stamp != self._allow_stamp:
                self._allowed, self._allow_stamp = set(path.read_text().split()), stamp
        except OSError:
            return False  # an allowlist that cannot be read lets nobody in
        return jid in self._allowed

    def _write_farm_file(self) -> None:
        info = {"url": self.config.url, "jid": self.config.jid, "token_file": str(self.home / ADMIN_TOKEN),
                "data_plane": self.data_plane, "ca_file": self.config.ca_file and str(self.config.ca_file)}
        (self.home / FARM_FILE).write_text(json.dumps(info, indent=2))

    # ---- jobs ---------------------------------------------------------------------------------------

    def job_dir(self, job_id: str) -> Path:
        return self.jobs_dir / job_id

    def result_path(self, job_id: str) -> Path:
        """result.exr: its report (.json) and preview (.png) beside it; the image itself is `result_image`."""
        return self.job_dir(job_id) / "result.exr"

    def partial_path(self, job_id: str) -> Path:
        """partial.exr: the tiles so far of a job running or ended without finishing (`assemble_partial`)."""
        return self.job_dir(job_id) / "partial.exr"

    def result_image(self, job_id: str, partial: bool = False) -> Path:
        """The job's composed image: result.exr, or result.pfm / result.rgbe where the film asks for them;
        `partial`: partial.exr ... (`assemble_partial`)."""
        stem = self.partial_path(job_id) if partial else self.result_path(job_id)
        paths = [stem.with_suffix(suffix) for suffix in IMAGE_SUFFIXES]
        return next((path for path in paths if path.exists()), stem)

    def job_plan(self, record: JobRecord) -> JobPlan:
        """A stored job's plan, its scene where the master unpacked the job's bundle."""
        return self.store.plan(record.id, self.job_dir(record.id) / "scene" / record.scene)

    def job_info(self, record: JobRecord) -> m.JobInfo:
        """The job as agents see it in calls for proposals (rebuilt from the store after a restart)."""
        return self._job_info(record.id, record.scene, record.spec.defines, self.job_plan(record),
                              record.spec.options.threads)

    def _job_info(self, job_id: str, scene_name: str, defines: dict[str, str], plan: JobPlan,
                  threads: int | None) -> m.JobInfo:
        """The job as its messages describe it; `threads`: the user's for each agent (`submit -t`), None for
        each agent's own (the plan's are the master's pre-pass's)."""
        return m.JobInfo(
            job_id=job_id, scene_url=f"{self.config.url}/jobs/{job_id}/bundle",
            scene_hash=plan.bundle_sha256, width=plan.width, height=plan.height, spp=plan.spp,
            depth=plan.depth, level=plan.options.level, ranges=plan.ranges(), scene_name=scene_name,
            defines=dict(defines), variant=plan.effects.variant, integrator=plan.effects.override,
            sensor=plan.options.sensor, rules_sha256=plan.rules_sha256, defuzzifier=plan.options.defuzzifier,
            min_band=plan.reach, first_spp=plan.first_spp, rfilter=plan.spec.rfilter,
            passes=plan.options.in_passes, spill=plan.spill, threads=threads,
        )

    async def submit(self, bundle: bytes | Path, spec: JobSpec) -> str:
        """Accept a job (`spec`: its -D parameters, options, name, and its sequence and frame if it is one
        frame of one): keep its bundle (bytes, or a file of the jobs folder, moved), plan it (pre-pass in a
        child process), auction its units. The job is stored as created when its upload had arrived: its
        time includes the planning (pre-pass) it waited for. A frame range is expanded by the job API."""
        if spec.frames is not None:
            raise QuekaroError("a frame range is one job per frame: submit each frame's own spec")
        defines, options = spec.defines, spec.options
        received = time.time()
        job_id = uuid.uuid4().hex[:12]
        job_dir = self.job_dir(job_id)
        job_dir.mkdir(parents=True)
        try:
            if isinstance(bundle, Path):
                os.replace(bundle, job_dir / "bundle.tar")
                bundle = job_dir / "bundle.tar"
            else:
                (job_dir / "bundle.tar").write_bytes(bundle)
            scene = extract_bundle(bundle, job_dir / "scene", BundleLimits())
            scene_name = str(scene.relative_to(job_dir / "scene"))
            m.check_scene_name(scene_name)  # before the pre-pass: refused cheaply
            check_unpacked(scene, defines)
            options, rules_sha256 = _job_rules(job_dir / "scene", options)
            options.check_used()
            digest = bundle_hash(bundle)
            _check_stated_spp(SceneSpec(scene, defines), scene_name, options)  # before the pre-pass
            # Seeded from the scene file as submitted, as `quekaro render` seeds it: a job reads the same
            # pre-pass on a farm as in one process (the bundle's hash would also follow its packing and
            # rule file, and its copy of the scene names the files it packed).
            seed = plan_seed(submitted_scene_sha256(scene), defines, options.to_dict())
            plan = await self._plan(SceneSpec(scene, defines), options, seed)
            plan = dataclasses.replace(plan, bundle_sha256=digest, rules_sha256=rules_sha256)
            m.check_job(self._job_info(job_id, scene_name, defines, plan, options.threads))  # now, not later
        except BaseException as exc:
            shutil.rmtree(job_dir, ignore_errors=True)
            if isinstance(exc, QuekaroError):
                raise _as_submitted(exc, job_dir / "scene") from exc
            raise
        self._create_job(job_id, scene_name, dataclasses.replace(spec, options=options), plan, received)
        if options.denoise:  # rendered while the agents render the units; assembly waits for it
            task = asyncio.get_running_loop().create_task(self._aov_pass(job_id), name=f"AOV pass {job_id}")
            self._aov_passes.add(task)
            task.add_done_callback(self._aov_pass_done)
        return job_id

    async def _plan(self, spec: SceneSpec, options: RenderOptions, seed: int) -> JobPlan:
        """The job's plan, made in the planner's child process (one job at a time), its pre-pass on the
        master's `--threads` unless the job names its own."""
        options = self._on_my_threads(options)
        async with self._planning:
            return await asyncio.to_thread(self._planner.call, plan_job, spec, options, seed,
                                           self._units_for_agents(), self._floors(options), True,  # farm
                                           doing=f"planning {spec.path.name}")

    def _on_my_threads(self, options: RenderOptions) -> RenderOptions:
        """A job's options as the master's planner renders them: on its `--threads` unless the job names its own."""
        if options.threads is None and self.config.threads is not None:
            return dataclasses.replace(options, threads=self.config.threads)
        return options

    def _floors(self, options: RenderOptions) -> Floors:
        """Where the live agents plan the job's units as the master's plan does, its depth floors are measured
        only where its rules cut depth (else every unit is held at the user's depth, for an agent with other
        rules that joins later); otherwise the agents' own rules may cut depth at any level. A progressive
        job's depths are its plan's (planning.jobplan.pin_passes): no agent's rules choose."""
        if options.in_passes:
            return Floors.RULES
        if self.auction is None:
            return Floors.ALWAYS
        mine = None if options.rules is not None else self._rules_digest
        return Floors.HELD if self.auction.plan_alike(mine, options.defuzzifier) else Floors.ALWAYS

    def _units_for_agents(self) -> int:
        """Units a job needs at least so that every live agent gets several (load balance)."""
        return farm_min_units(self.auction.live_agents() if self.auction else 0)

    def _create_job(self, job_id: str, scene_name: str, spec: JobSpec, plan: JobPlan, received: float) -> None:
        now = time.time()
        self.store.create_job(job_id, scene_name, spec, plan, received)
        goal = Goal.of(plan.options, plan.spp) if plan.options.in_passes else None
        submitted = au.JobSubmitted(self.job_info(self.store.job(job_id)), plan.units, _tile_channels(plan),
                                    stimulus_id=f"submit-{job_id}", goal=goal)
        self.store.apply(self.auction.handle(submitted, now), now)

    async def cancel(self, job_id: str) -> bool:
        async with self._lock:
            if self.auction is None or self.auction.job_view(job_id) is None:
                return self.store.cancel(job_id, time.time())
            out = await self._handle(au.JobCancelRequested(job_id, stimulus_id=f"cancel-{job_id}"))
            return any(isinstance(i, au.JobCancelled) for i in out)  # False: it had already ended

    async def retry_unit(self, job_id: str, index: int) -> str | None:
        """Render a done unit again (the auction's `UnitRetryRequested`): None once it is back to the auction,
        else why not. A done job the auction does not know (ended before this master started) is taken up
        first, as a restart takes up a running one; its composed image goes, to be composed again."""
        async with self._lock:
            self._adopt_done(self.store.job(job_id))
            out = await self._handle(au.UnitRetryRequested(job_id, index, stimulus_id=f"retry-{job_id}-{index}"))
        return _refusal(out, job_id)

    async def requeue(self, job_id: str) -> str | None:
        """Run a failed or cancelled job again (the auction's `JobRequeueRequested`): its done units kept, the
        others auctioned. None once it runs, else why not. A job the auction does not know (it ended before
        this master started) comes from the store, as a restart takes up a running one. StoreError: no job."""
        async with self._lock:
            record = self.store.job(job_id)
            if not (self.job_dir(job_id) / "bundle.tar").is_file():
                return "its bundle is no longer on the master: submit the scene again"
            self._adopt_done(record)
            taken_up = None
            if self.auction.job_view(job_id) is None and record.status != JobStatus.RUNNING:
                job = self._taken_up(self.store.taken_up(job_id))
                taken_up = au.JobSubmitted.taken_up(self.job_info(record), job, f"requeue-{job_id}")
            out = await self._handle(au.JobRequeueRequested(job_id, taken_up, stimulus_id=f"requeue-{job_id}"))
        return _refusal(out, job_id)

    def _adopt_done(self, record: JobRecord) -> None:
        """A done job the auction does not know (ended before this master started), taken up as done: a unit of
        it may be retried, and a requeue of it is refused by the auction, saying why."""
        if self.auction.job_view(record.id) is not None or record.status != JobStatus.DONE:
            return
        units = self.store.units(record.id)
        adopt = au.JobSubmitted(self.job_info(record), [u.unit() for u in units],
                                _tile_channels(self.job_plan(record)), frozenset(u.index for u in units),
                                stimulus_id=f"adopt-{record.id}")
        self.auction.handle(adopt, time.time())  # its JobDone restates what the store has

    async def drain(self, agent: str, drain: bool) -> str | None:
        """Drain an agent (no new award; it finishes what it holds), or resume it: None once done, else why not."""
        kind, verb = (au.AgentDrainRequested, "drain") if drain else (au.AgentResumeRequested, "resume")
        async with self._lock:
            out = await self._handle(kind(agent, stimulus_id=f"{verb}-{agent}"))
        return _refusal(out, None)

    async def delete_job(self, job_id: str) -> None:
        """Forget an ended job: its rows and its folder (bundle, tiles, image). StoreError for a running one."""
        async with self._lock:
            self.store.delete_job(job_id)
            self._merger.forget(job_id)
        await asyncio.to_thread(shutil.rmtree, self.job_dir(job_id), True)

    # ---- the data plane's callbacks -----------------------------------------------------------------

    def _expected_upload(self, job_id: str, index: int, token: str) -> tuple[Any, tuple[int, int]] | None:
        """The unit's rectangle and the image's size, if `token` is its current award's."""
        award = self.auction.award_for(job_id, index, token) if self.auction else None
        return None if award is None else (award.rect, award.image)

    def _bundle_allowed(self, job_id: str, token: str) -> bool:
        """A scene goes only to an agent holding a current award of its job (the award's token)."""
        return self.auction is not None and self.auction.holds_award(job_id, token)

    def _bundle_for(self, job_id: str) -> tuple[Path, str] | None:
        path = self.job_dir(job_id) / "bundle.tar"
        if not path.is_file():
            return None
        return path, self.store.job(job_id).plan["bundle_sha256"]

    async def _on_tile(self, job_id: str, index: int, path: Path, sha256: str, token: str,
                       agent: str | None = None) -> None:
        """A tile is on disk (fsynced): the auction says what it means; a refusal is the upload's answer."""
        header = _stored_header(path)
        figures = m.TileFigures.from_header(header.meta)
        stored = au.TileStored(job_id, index, token, str(path), sha256, figures, tuple(header.channels),
                               _extra(header.meta), stimulus_id=f"tile-{job_id}-{index}-{sha256[:8]}")
        async with self._lock:
            out = await self._handle(stored)
        refused = [i for i in out if isinstance(i, au.RefuseTile)]
        if refused:
            raise TileError(refused[0].reason)

    # ---- messages and time --------------------------------------------------------------------------

    async def _on_envelope(self, env: Any) -> None:
        shared = self.shared_accounts.seen(env.sender, env.resource, env.received_at)
        if shared:
            log.warning("%s", shared)
        try:
            msg = m.parse(env.performative, env.body)
        except MessageError as exc:
            log.warning("refused %s from %s: %s", env.performative, env.sender, exc)
            return
        async with self._lock:
            await self._handle(au.MessageReceived(env.sender, msg,
                                                  stimulus_id=f"{env.performative}-{msg.conversation}"))

    async def _handle(self, stimulus: au.Stimulus) -> list[au.Instruction]:
        """The auction's answer to one stimulus, carried out; a tick follows soon (`_tick_soon`)."""
        now = time.time()
        out = self.auction.handle(stimulus, now)
        out += self._drain_again(out, now)
        await self._execute(out)
        self._tick_soon(stimulus.stimulus_id)
        return out

    def _tick_soon(self, after: str) -> None:
        """A tick once the stimuli already waiting for the lock are handled (asyncio's lock is first come,
        first served): an agent that just answered or finished may be free, and waiting for the timer would
        idle it; a burst of stimuli costs one tick, not one each."""
        if self._tick_due is None:
            self._tick_due = asyncio.get_running_loop().create_task(self._tick_after(after), name="tick soon")

    async def _tick_after(self, after: str) -> None:
        async with self._lock:
            self._tick_due = None  # a stimulus handled from now on asks for a tick of its own
            try:
                await self._execute(self.auction.handle(au.Tick(stimulus_id=f"tick-after-{after}"), time.time()))
            except Exception:  # one bad tick must not stop the master
                log.exception("master tick failed")

    def _drain_again(self, out: list[au.Instruction], now: float) -> list[au.Instruction]:
        """An agent the store says the user drained, joining (after a master restart, or forgotten and back),
        is drained again before anything is awarded to it."""
        joined = [i.agent for i in out if isinstance(i, au.AgentJoined)]
        drained = self.store.drained() if joined else set()
        return [item for agent in joined if agent in drained
                for item in self.auction.handle(au.AgentDrainRequested(agent, stimulus_id=f"drained-{agent}"), now)]

    async def _tick_forever(self) -> None:
        while True:
            await asyncio.sleep(TICK_S)
            try:
                async with self._lock:
                    await self._execute(self.check_disk() + self.auction.handle(
                        au.Tick(stimulus_id=f"tick-{next(self._ticks)}"), time.time()))
            except Exception:  # one bad tick must not stop the master
                log.exception("master tick failed")

    def check_disk(self) -> list[au.Instruction]:
        """Tell the auction when the master's home falls below `min_free_bytes` free, or rises above again."""
        free = shutil.disk_usage(self.home).free
        full = free < self.config.min_free_bytes
        if full == bool(self.auction.paused):
            return []
        stimulus = au.DiskFull(free) if full else au.DiskFreed(free)
        return self.auction.handle(stimulus, time.time())

    @property
    def paused(self) -> str | None:
        """Why every job is paused (the disk is full), or None."""
        return self.auction.paused if self.auction else None

    async def _execute(self, instructions: list[au.Instruction]) -> None:
        """Record first (the store is the truth after a crash), then send messages. Where the store cannot
        write them yet (`_record`) the messages still go: a master that crashes meanwhile sends its awarded
        units back to auction when it starts, as after any crash."""
        self._record(instructions)
        for item in instructions:
            if isinstance(item, au.Record):
                log.log(item.level, "%s", item.sentence(), extra=fields(**item.fields()))
                if isinstance(item, au.JobDone):
                    self._merger.forget(item.job_id)
                    self._assemble_later(item.job_id)
                elif isinstance(item, au.PassesSettled):
                    write_verdicts(self.job_dir(item.job_id), item)
                elif isinstance(item, au.UnitDone) and self.auction.merges_passes(item.job_id):
                    self._merge_later(item)
                elif isinstance(item, au.UnitRetried | au.JobRequeued):
                    self._drop_result(item.job_id)
        for to, message in outgoing(instructions):
            try:
                performative, body = m.encode(message)
            except MessageError as exc:  # a job whose messages cannot be sent fails alone
                await self._fail_job(getattr(message, "job_id", None) or message.job.job_id, exc)
                continue
            await self.agent.send(to, performative, body, conversation_id=message.conversation,
                                  protocol=m.PROTOCOL, ontology=m.ONTOLOGY)

    def _record(self, instructions: list[au.Instruction]) -> None:
        """Write the auction's records to the store, after those it could not write before, in order. Where
        it cannot (its disk full), they are kept and written at a later tick: the auction has moved on,
        and a job it ended would otherwise stay running in the store until the master restarts."""
        events = [*self._unrecorded, *(i for i in instructions if isinstance(i, au.Record))]
        if not events:
            return
        try:
            self.store.apply(events, time.time())
        except sqlite3.OperationalError as exc:
            if not self._unrecorded:
                log.error("the job store cannot record the auction's events (%s): kept until it can", exc)
            self._unrecorded = events
            return
        except Exception:
            self._unrecorded = []  # an event the store refuses is refused again: keeping it would stop every later one
            raise
        if self._unrecorded:
            log.warning("the job store recorded %d event(s) it could not before", len(self._unrecorded))
        self._unrecorded = []

    def _merge_later(self, done: au.UnitDone) -> None:
        """Merge a progressive job's pass in a thread; the auction then decides on the unit's new noise."""
        units = self.auction.job_passes(done.job_id)

        async def merge() -> None:
            merged = await asyncio.to_thread(self._merger.merge, done.job_id, units, done.index, done.tile_path)
            async with self._lock:
                await self._handle(merged)

        task = asyncio.get_running_loop().create_task(merge(), name=f"merge {done.job_id}/{done.index}")
        self._merges.add(task)
        task.add_done_callback(self._merge_done)

    def _merge_done(self, task: asyncio.Task) -> None:
        self._merges.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("%s failed: %s", task.get_name(), task.exception())

    async def _fail_job(self, job_id: str, exc: Exception) -> None:
        log.error("job %s: its messages cannot be encoded (%s): the job fails, the others go on", job_id, exc)
        reason = f"cannot send its messages: {exc}"
        self.store.set_status(job_id, JobStatus.FAILED, time.time(), reason)  # first: the cancel below keeps it failed
        cancel = au.JobCancelRequested(job_id, reason, stimulus_id=f"unsendable-{job_id}")
        await self._execute(self.auction.handle(cancel, time.time()))

    # ---- the final image ----------------------------------------------------------------------------

    async def _aov_pass(self, job_id: str) -> np.ndarray:
        """A denoised job's AOV pass (planning.pipeline.aov_job), rendered once by the planner process and
        kept in the job's folder (so a master that restarts renders it only if it had not)."""
        plan = self.job_plan(self.store.job(job_id))
        plan = dataclasses.replace(plan, options=self._on_my_threads(plan.options))
        async with self._planning:
            return await asyncio.to_thread(kept_aov_pass, self._planner, plan, job_id,
                                           self.job_dir(job_id) / AOV_PASS_FILE)

    def _aov_pass_done(self, task: asyncio.Task) -> None:
        """Log an AOV pass that failed (assembly tries it again, and fails the result with the reason)."""
        self._aov_passes.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("%s failed: %s", task.get_name(), task.exception())

    def _drop_result(self, job_id: str) -> None:
        """A job runs again (a unit retried, a job requeued): its composed image, report and preview go, composed
        again at its end (a stale image must not be served meanwhile)."""
        for stem in (self.result_path(job_id), self.partial_path(job_id)):
            _drop_files(stem)

    async def _assemble(self, job_id: str) -> dict[str, Any]:
        """The job's image, after its AOV pass where it is denoised, composed in a thread; its partial image
        (`assemble_partial`), if one was fetched while it ran, goes."""
        _drop_files(self.partial_path(job_id))
        denoised = self.store.job(job_id).spec.options.denoise
        aov_pass = await self._aov_pass(job_id) if denoised else None
        return await asyncio.to_thread(self.assemble, job_id, aov_pass)

    def _assemble_later(self, job_id: str) -> asyncio.Task:
        """Assemble the job's image, once at a time per job."""
        task = self._assembling.get(job_id)
        if task is None or task.done():
            task = self._track(job_id, asyncio.get_running_loop().create_task(self._assemble(job_id),
                                                                            name=f"assemble {job_id}"))
            task.add_done_callback(lambda t: t.cancelled() or t.exception() is None
                                   or log.error("job %s: assembling the image failed: %s", job_id, t.exception()))
        return task

    def _track(self, key: str, task: asyncio.Task) -> asyncio.Task:
        """Hold `task` under `key` in `_assembling` while it runs: one composition at a time per key."""
        def untrack(done: asyncio.Task) -> None:
            if self._assembling.get(key) is done:
                del self._assembling[key]
        self._assembling[key] = task
        task.add_done_callback(untrack)
        return task

    async def ensure_partial(self, job_id: str, follow_tiles: bool = True) -> Path:
        """The report path of the partial image of a job running or ended without finishing
        (`assemble_partial`), composed again where the job's status changed since, or tiles landed
        (`follow_tiles`; not for the report of an image just fetched)."""
        report = self.partial_path(job_id).with_suffix(".json")
        key = f"{job_id} partial"
        task = self._assembling.get(key)
        if task is None or task.done():
            if self._partial_current(job_id, report, follow_tiles):
                return report
            task = self._track(key, asyncio.get_running_loop().create_task(
                asyncio.to_thread(self.assemble_partial, job_id), name=key))
        await asyncio.shield(task)
        return report

    def _partial_current(self, job_id: str, report: Path, follow_tiles: bool) -> bool:
        """Whether the partial image on disk shows the job as it is now: its status, and its tiles."""
        if not report.exists():
            return False
        shown = json.loads(report.read_text()).get("partial", {})
        return (shown.get("status") == self.store.job(job_id).status
                and (not follow_tiles or shown.get("tiles") == len(self.store.results(job_id))))

    async def ensure_assembled(self, job_id: str) -> Path:
        """The job's report path, once its image and report are written (assembling them if needed)."""
        report = self.result_path(job_id).with_suffix(".json")
        task = self._assembling.get(job_id)
        if task is not None and not task.done():
            await asyncio.shield(task)
        if not report.exists():
            await self._assemble_later(job_id)
        return report

    def assemble(self, job_id: str, aov_pass: np.ndarray | None = None) -> dict[str, Any]:
        """Compose the job's tiles into result.exr/.png/.json (again, if asked: it is deterministic);
        `aov_pass`: a denoised job's, which the image is denoised with."""
        record, results, plan = self._stored(job_id)
        return self._compose(record, results, plan, self.result_path(job_id), {}, aov_pass)

    def assemble_partial(self, job_id: str) -> dict[str, Any]:
        """Compose the tiles so far of a job running or ended without finishing (failed, cancelled) into
        partial.exr/.png/.json: the units without a tile black, and not denoised (a denoised job's AOV pass
        renders at its end). The report's `partial` says what the image lacks and what it shows."""
        record, results, plan = self._stored(job_id)
        if record.status == JobStatus.DONE or not results:
            raise QuekaroError(f"job {job_id} is {record.status}" + ("" if results else " and has no tile yet"))
        plan = dataclasses.replace(plan, options=dataclasses.replace(plan.options, denoise=False))
        units = len(plan.units)
        done = {au.pass_origin(r.index, units)[0] if plan.options.in_passes else r.index for r in results}
        partial = {"status": record.status.value, "error": record.error, "units": units,
                   "units_missing": sorted(set(range(units)) - done), "tiles": len(results)}  # a unit's or a pass's
        return self._compose(record, results, plan, self.partial_path(job_id), {"partial": partial}, None)

    def _stored(self, job_id: str) -> tuple[JobRecord, list[Any], JobPlan]:
        """The job's record, stored tiles and plan, read on a connection of this thread's own."""
        with JobStore(self.store.path) as store:
            record = store.job(job_id)
            return record, store.results(job_id), store.plan(job_id, self.job_dir(job_id) / "scene" / record.scene)

    def _compose(self, record: JobRecord, results: list[Any], plan: JobPlan, out: Path, extra: dict[str, Any],
                 aov_pass: np.ndarray | None) -> dict[str, Any]:
        """The stored tiles of the job composed into `out` (.exr, .png, .json), `extra` in its report."""
        job_id = record.id
        # Headers only: each tile's pixels are read while composition needs them. The store, not the
        # header, says which unit a tile is.
        if plan.options.in_passes:  # every stored pass merged into its unit
            reason, verdicts = read_verdicts(self.job_dir(job_id))
            tiles, params = merged_units(results, len(plan.units), verdicts)
            rules = Path(plan.options.rules or default_rules_path()).name  # the plan's, not an agent's
            params = {unit: {**line, "rules": rules} for unit, line in params.items()}
            extra["render_calls"] = {"progressive": {**Goal.of(plan.options, plan.spp).to_dict(),
                                                     "reason": reason, "passes": len(results)}}
        else:
            tiles = [tile_source(r.tile_path, unit_index=r.index, job_id=job_id) for r in results]
            params = {r.index: r.params for r in results}
        # The scene as submitted (its path and -a folders on the submitter's side), not the master's copy,
        # meaningless to the user.
        scene = {**plan.spec.to_dict(), **submitted_scene(self.job_dir(job_id) / "scene" / record.scene)}
        # totals.seconds as `quekaro render` counts it, the whole job: from its upload's arrival to its last
        # tile (the store's created and finished), then this assembly.
        ran = (record.finished or time.time()) - record.created
        report = assemble(plan, tiles, params, out, started=time.perf_counter() - ran,
                          extra={"job_id": job_id, "scene": scene, "created": record.created,
                                 "finished": record.finished, **extra}, aov_pass=aov_pass, partial="partial" in extra)
        return report


def _drop_files(stem: Path) -> None:
    """A composed image's files (`stem` with each suffix it may have) removed."""
    for suffix in (*IMAGE_SUFFIXES, RAW_SUFFIX, ".json", ".png"):
        stem.with_suffix(suffix).unlink(missing_ok=True)


def _tile_channels(plan: JobPlan) -> tuple[str, ...] | None:
    """What every tile of a job carries: its plan's channels, a pass's with its film's weights last
    (core.image.passes); None where the plan does not say."""
    if plan.channels is None:
        return None
    return (*plan.channels, WEIGHT) if plan.options.in_passes else tuple(plan.channels)


def _check_stated_spp(spec: SceneSpec, scene_name: str, options: RenderOptions) -> None:
    """A scene's own sample_count above SPP_MAX: refused naming it (the job message's field would not say
    which option), where `quekaro render`, like plain Mitsuba, renders it."""
    stated = options.spp or scene_spp(spec, options.sensor)
    if stated is not None and stated > SPP_MAX:
        raise QuekaroError(f"{scene_name}: sample_count {stated} (the scene's, or its -D) is above {SPP_MAX}, the "
                           f"most samples per pixel a farm job carries; give --spp (up to {SPP_MAX}), or render "
                           "it with quekaro render")


def _as_submitted(exc: QuekaroError, folder: Path) -> QuekaroError:
    """`exc` with the paths of the job's unpacked bundle (`folder`, removed with the refused job) as the
    submitter's files are named in it: what the user must fix is in their scene, not in the master's home."""
    text = str(exc).replace(f"{folder}{os.sep}", "").replace(str(folder), "the bundle's folder")
    return exc if text == str(exc) else type(exc)(text)


def _job_rules(folder: Path, options: RenderOptions) -> tuple[RenderOptions, str | None]:
    """The job's options with its rule file (from its bundle, validated) and that file's sha256."""
    if options.rules is not None:
        raise QuekaroError("options.rules: a job's rule file travels inside its bundle (quekaro submit --rules)")
    name = read_manifest(folder).get("rules")
    if not name:
        return options, None
    path = folder / name
    check_rules(path, options.defuzzifier, "the job's rule file")
    return dataclasses.replace(options, rules=path), sha256_file(path)


def _extra(meta: dict[str, Any]) -> dict[str, Any]:
    """The rest of a tile's header that its job's report keeps: outputs, the rule file, an emulated render."""
    return {"outputs": meta.get("outputs") if isinstance(meta.get("outputs"), dict) else {},
            "rules": str(meta.get("rules", ""))[:256] or None, "emulated": meta.get("emulated") is True}


def _stored_header(path: Path) -> TileSource:
    """The header of a tile the data plane decoded in full before storing it (master.data_plane._validate),
    so its pixels are not decoded again here. Failing to read it back is the master's fault (its disk), not
    the agent's: a QuekaroError, not a TileError."""
    try:
        return tile_source(path)
    except TileError as exc:
        raise QuekaroError(f"stored tile {path}: {exc}") from exc


def _admin_token(home: Path) -> str:
    """The secret that `quekaro submit/cancel` must present: created once, readable by the owner only."""
    home.mkdir(parents=True, exist_ok=True)
    path = home / ADMIN_TOKEN
    if not path.exists():
        path.touch(mode=0o600)
        path.write_text(secrets.token_hex(24))
    return path.read_text().strip()


def _refusal(out: list[au.Instruction], job_id: str | None) -> str | None:
    """Why the auction refused what the user asked of the job (`job_id`; None: of an agent), or None."""
    ignored = [i for i in out if isinstance(i, au.MessageIgnored) and i.agent is None and i.job_id == job_id]
    return ignored[0].reason if ignored else None


def outgoing(instructions: list[au.Instruction]) -> list[tuple[str, m.Message]]:
    """The messages the instructions send, in order per agent, an agent's awards of one job that follow each
    other (among its own messages) packed into Awards (`m.packed`): one message per round and job, not
    one per unit."""
    per_agent: dict[str, list[m.Message]] = {}
    for item in instructions:
        if isinstance(item, au.SendToAgent):
            per_agent.setdefault(item.to, []).append(item.message)
    out: list[tuple[str, m.Message]] = []
    for to, messages in per_agent.items():
        for _, run in itertools.groupby(messages, key=_award_job):
            run = list(run)
            packed = m.packed(run) if isinstance(run[0], m.Award) else run
            out += [(to, message) for message in packed]
    return out


def _award_job(message: m.Message) -> tuple[str, str] | tuple[str, int]:
    """Groups an agent's messages: awards by their job, every other message alone."""
    return ("award", message.job.job_id) if isinstance(message, m.Award) else ("other", id(message))
