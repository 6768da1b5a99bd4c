"""The render agent as a real process (`python -m agents.render_agent`) on SPADE's embedded XMPP server.

This test process plays a scripted master: a FarmAgent of its own, and a real aiohttp server on 127.0.0.1
that serves scene bundles and takes tile uploads. It drives the contract net by hand (CFP, Award, Cancel)
and checks what comes back over XMPP and HTTP: the proposal, the uploaded tile (its rectangle with the
band, finite pixels, the parameters in its header), which is its answer; a refusal while busy; a cancelled unit
that is never delivered; Failures for a broken scene, a bundle with the wrong hash and a refused upload;
units awarded together rendered in one call, and a batch that fails together rendered unit by unit; an
agent that survives a malformed message and stops cleanly on SIGTERM.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.data import default_rules_path
from core.image.tiles import read_tile_bytes
from core.model import messages as m
from core.model.geometry import Rect
from core.model.units import SLOTS, WorkUnit
from core.scene.bundle import make_bundle
from core.transport.xmpp import Envelope, FarmAgent
from core.transport.xmpp_server import ProsodyServer
from fuzzy.loader import load_rulebase

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
CBOX = REPO / "scenes" / "cbox.xml"
MASTER = "master@localhost"
AGENT = "agent-t1@localhost"
PASSWORD = "pw-render-agent-test"
RANGES = {"C": (0.0, 1.0), "S": (64.0, 1024.0), "Nd": (0.0, 0.5)}


class LoopThread:
    """An asyncio loop in a thread, so that module-scoped async parts outlive one test function."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro: Coroutine[Any, Any, Any], timeout: float = 30.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


class ScriptedMaster:
    """A master that sends what the test says and records what the agent sends, over XMPP and HTTP."""

    def __init__(self, port: int, tile_dir: Path) -> None:
        self.farm = FarmAgent(MASTER, PASSWORD, port=port, ontology=m.ONTOLOGY, peers=[AGENT], validate=m.parse)
        self.farm.set_handler(self._on_envelope)
        self.messages: list[tuple[float, m.Message]] = []
        self.arrived = asyncio.Condition()
        self.bundles: dict[str, bytes] = {}
        self.tokens: dict[tuple[str, int], str] = {}
        self.uploads: list[tuple[str, int, bytes]] = []
        self.rects: dict[tuple[str, int], Rect] = {}
        self.job_bundles: dict[str, str] = {}  # job -> bundle sha256
        self.tile_dir = tile_dir
        self.http_port = 0
        self._runner: Any = None

    async def start(self) -> None:
        from master.data_plane import create_app, serve

        # The master's real data plane, fed by this scripted master's tokens, rectangles and bundles.
        app = create_app(expected=self._expected, bundle=self._bundle, on_tile=self._on_tile,
                         tile_dir=self.tile_dir, authorize_bundle=self._bundle_ok)
        self._runner, self.http_port = await serve(app, "127.0.0.1", 0)
        await self.farm.start()

    async def stop(self) -> None:
        await self.farm.stop()
        await self._runner.cleanup()

    # --- HTTP: the data plane's callbacks ---------------------------------------------------------

    def _expected(self, job: str, index: int, token: str) -> tuple[Rect, tuple[int, int]] | None:
        key = (job, index)
        return self.rects[key] if key in self.tokens and self.tokens[key] == token else None

    def _bundle(self, job: str) -> tuple[Path, str] | None:
        sha = self.job_bundles.get(job)
        if sha not in self.bundles:
            return None
        path = self.tile_dir / "bundles" / f"{sha}.tar"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(self.bundles[sha])
        return path, sha

    def _bundle_ok(self, job: str, token: str) -> bool:
        return any(t == token for (j, _), t in self.tokens.items() if j == job)

    def _on_tile(self, job: str, index: int, path: Path, sha256: str, token: str, agent: str | None) -> None:
        self.uploads.append((job, index, path.read_bytes()))

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.http_port}{path}"

    # --- XMPP: the control plane ----------------------------------------------------------------

    async def _on_envelope(self, env: Envelope) -> None:
        async with self.arrived:
            self.messages.append((time.monotonic(), m.parse(env.performative, env.body)))
            self.arrived.notify_all()

    async def send(self, msg: m.Message) -> None:
        performative, body = m.encode(msg)
        assert await self.farm.send(AGENT, performative, body, conversation_id=msg.conversation,
                                    protocol=m.PROTOCOL, ontology=m.ONTOLOGY)

    async def send_raw(self, performative: str, body: str, conversation: str) -> None:
        """A message past the sender's own checks: the agent's gate must refuse it."""
        from spade.message import Message

        meta = {"performative": performative, "ontology": m.ONTOLOGY, "protocol": m.PROTOCOL,
                "conversation-id": conversation}
        Message(to=AGENT, sender=str(self.farm.jid), body=body, metadata=meta).prepare(self.farm.client).send()

    async def expect(self, kind: type[m.Message], timeout: float = 15.0, since: float = 0.0,
                     where: Callable[[Any], bool] = lambda _msg: True) -> Any:
        """The first message of `kind` received after `since` (monotonic) that satisfies `where`."""
        def found() -> Any:
            return next((msg for t, msg in self.messages if t >= since and isinstance(msg, kind) and where(msg)),
                        None)

        async with self.arrived:
            await asyncio.wait_for(self.arrived.wait_for(lambda: found() is not None), timeout)
            return found()

    def received(self, kind: type[m.Message], since: float = 0.0) -> list[Any]:
        return [msg for t, msg in self.messages if t >= since and isinstance(msg, kind)]

    async def expect_upload(self, job: str, index: int, timeout: float = 30.0) -> bytes:
        """The tile of (job, index) once the data plane has taken it: how an agent answers an award."""
        deadline = time.monotonic() + timeout
        while not (found := [data for j, i, data in self.uploads if (j, i) == (job, index)]):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no tile of {job}/{index} within {timeout} s")
            await asyncio.sleep(0.05)
        return found[0]


class Farm:
    def __init__(self, loop: LoopThread, master: ScriptedMaster, agent: subprocess.Popen, log: Path,
                 server: ProsodyServer) -> None:
        self.loop, self.master, self.agent, self.log, self.server = loop, master, agent, log, server

    def run(self, coro: Coroutine[Any, Any, Any], timeout: float = 30.0) -> Any:
        try:
            return self.loop.run(coro, timeout)
        except BaseException:
            tail = self.log.read_text(errors="replace").splitlines()[-25:]
            print("agent log tail:\n" + "\n".join(tail), file=sys.stderr)
            raise

    def job(self, job_id: str, sha: str, scene: str, spp: int = 16, level: str = "N",
            scene_hash: str | None = None, defines: dict[str, str] | None = None) -> m.JobInfo:
        self.master.job_bundles[job_id] = sha
        return m.JobInfo(job_id=job_id, scene_url=self.master.url(f"/jobs/{job_id}/bundle"),
                         scene_hash=scene_hash or sha,
                         width=32, height=32, spp=spp, depth=6, level=level, ranges=RANGES, scene_name=scene,
                         defines={"res": "32"} if defines is None else defines, variant="llvm_ad_rgb",
                         integrator="path")

    def award(self, job: m.JobInfo, unit: WorkUnit, conversation: str, token: str | None = None) -> m.Award:
        token = token or hashlib.sha256(conversation.encode()).hexdigest()[:32]
        self.master.tokens[(job.job_id, unit.index)] = token
        self.master.rects[(job.job_id, unit.index)] = unit.rect, (job.width, job.height)
        return m.Award(conversation=conversation, job=job, unit=unit, token=token,
                       upload_url=self.master.url(f"/jobs/{job.job_id}/units/{unit.index}/tile"),
                       seed=unit.index, estimate_s=1.0)


def unit(index: int, rect: Rect, C: float = 0.4, Nd: float = 0.1) -> WorkUnit:
    return WorkUnit(index=index, rect=rect, C=C, S=rect.area, Nd=Nd, cost=rect.area * 6.67)


def cfp(job: m.JobInfo, conversation: str, *units: WorkUnit) -> m.CallForProposal:
    return m.CallForProposal(conversation=conversation, job=job, units=units, reply_within_s=5.0)


@pytest.fixture(scope="module")
def bundles(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[str, bytes]]:
    """name -> (scene file name in the bundle, bundle bytes): the cbox, and a scene Mitsuba cannot load."""
    if not CBOX.is_file():
        pytest.skip(f"{CBOX} missing")
    out = tmp_path_factory.mktemp("bundles")
    good = make_bundle(CBOX, {"res": "32"}, out / "cbox.tar")
    broken_dir = out / "broken"
    broken_dir.mkdir()
    broken = broken_dir / "broken.xml"
    broken.write_text('<scene version="3.0.0"><shape type="no_such_plugin_here"/></scene>\n')
    bad = make_bundle(broken, {}, out / "broken.tar")
    return {"cbox": (good.scene, good.path.read_bytes()), "broken": (bad.scene, bad.path.read_bytes())}


@pytest.fixture(scope="module")
def farm(tmp_path_factory: pytest.TempPathFactory, bundles: dict[str, tuple[str, bytes]]):
    tmp = tmp_path_factory.mktemp("farm")
    server = ProsodyServer(tmp / "prosody")
    for jid in (MASTER, AGENT):
        server.register(jid.split("@")[0], PASSWORD)
    server.start()
    loop = LoopThread()
    master = ScriptedMaster(server.port, tmp / "master")
    log = tmp / "agent.log"
    agent = None
    try:
        loop.run(master.start())
        for _, data in bundles.values():
            master.bundles[hashlib.sha256(data).hexdigest()] = data
        cmd = [sys.executable, "-m", "agents.render_agent", "--port", str(server.port), "--jid", AGENT,
               "--password", PASSWORD, "--master", MASTER, "--master-url", master.url(""), "--threads", "1",
               "--workdir", str(tmp / "agent"), "--heartbeat", "0.5"]
        with log.open("w") as sink:
            agent = subprocess.Popen(cmd, cwd=REPO, stdout=sink, stderr=subprocess.STDOUT,
                                     env=dict(os.environ, PYTHONPATH=str(REPO)))
        farm = Farm(loop, master, agent, log, server)
        farm.run(master.expect(m.Register, timeout=60), timeout=70)  # online: each test can run alone
        yield farm
    finally:
        if agent is not None and agent.poll() is None:
            agent.kill()
            agent.wait()
        with contextlib.suppress(Exception):
            loop.run(master.stop(), 10)
        loop.close()
        server.stop()


def sha_of(bundles: dict[str, tuple[str, bytes]], name: str) -> str:
    return hashlib.sha256(bundles[name][1]).hexdigest()


def test_registers_with_its_speed_and_beats(farm: Farm) -> None:
    reg = farm.run(farm.master.expect(m.Register, timeout=40.0), 45)
    assert 0.01 < reg.speed < 1e4 and reg.threads == 1 and reg.rules == "pathtracing.xml"
    # What it plans a job without rules with: the master measures depth floors by it
    # (MasterService._floors): what the rules compute, so a copy with other comments plans alike
    assert (reg.rules_sha256, reg.defuzzifier) == (load_rulebase(default_rules_path()).digest(), None)
    beat = farm.run(farm.master.expect(m.Heartbeat, timeout=5.0))
    assert beat.busy == ()


def test_survives_malformed_and_stray_messages(farm: Farm, bundles: dict) -> None:
    scene, _ = bundles["cbox"]
    job = farm.job("job-a", sha_of(bundles, "cbox"), scene)
    since = time.monotonic()
    farm.run(farm.master.send_raw("cfp", "{not json", "bad-1"))
    bad = json.dumps({"v": m.PROTOCOL_VERSION, "conversation": "bad-2", "job": {}})
    farm.run(farm.master.send_raw("cfp", bad, "bad-2"))
    # Valid, but of conversations and jobs the agent never saw: harmless.
    farm.run(farm.master.send(m.Cancel(conversation="stray-1", job_id="nojob", index=7, reason="old")))
    farm.run(farm.master.send(m.Reject(conversation="stray-2", job_id="nojob", reason="old")))
    farm.run(farm.master.send(cfp(job, "alive-1", unit(9, Rect(0, 0, 8, 8)))))
    prop = farm.run(farm.master.expect(m.Propose, since=since, where=lambda p: p.conversation == "alive-1"))
    assert [e.index for e in prop.estimates] == [9]
    assert not farm.master.received(m.Refuse, since) and farm.agent.poll() is None


def test_unit_is_planned_rendered_and_uploaded(farm: Farm, bundles: dict) -> None:
    scene, _ = bundles["cbox"]
    job = farm.job("job-a", sha_of(bundles, "cbox"), scene)
    u3, u4 = unit(3, Rect(8, 8, 16, 16)), unit(4, Rect(0, 24, 32, 8), C=0.9, Nd=0.3)
    since = time.monotonic()
    farm.run(farm.master.send(cfp(job, "cfp-a", u3, u4)))
    prop = farm.run(farm.master.expect(m.Propose, since=since, where=lambda p: p.conversation == "cfp-a"))
    assert prop.job_id == "job-a" and {e.index for e in prop.estimates} == {3, 4}
    assert all(0 < e.seconds < 60 for e in prop.estimates)

    award = farm.award(job, u3, "award-a3")
    farm.run(farm.master.send(award))
    farm.run(farm.master.send(award))  # a duplicate: must not render or upload twice
    data = farm.run(farm.master.expect_upload("job-a", 3), 35)
    time.sleep(1.0)
    uploads = [u for u in farm.master.uploads if u[:2] == ("job-a", 3)]
    assert len(uploads) == 1, "the duplicate award was rendered again"
    # The upload is the answer: the master reads the unit's figures from the tile's header.
    assert not farm.master.received(m.Inform, since)

    tile = read_tile_bytes(data, "upload")
    assert tile.core == u3.rect
    meta = tile.meta
    assert meta["band"] >= 2 and tile.rect == u3.rect.window(meta["band"], 32, 32)
    assert np.isfinite(tile.pixels).all() and tile.pixels.mean() > 0.01
    assert meta["agent"] == AGENT and meta["job_id"] == "job-a" and meta["unit_index"] == 3
    assert meta["nonfinite"] == 0 and meta["seconds"] > 0
    assert set(meta["outputs"]) == {"Rl", "Ls", "Ibs"} and meta["seed"] == 3
    assert 1 <= meta["spp"] <= 16 * 4 and 1 <= meta["depth"] <= 6 * 4
    assert not farm.master.received(m.Failure, since)
    # The unit's real time now corrects the agent's estimates for this job.
    farm.run(farm.master.send(cfp(job, "cfp-a2", u4)))
    again = farm.run(farm.master.expect(m.Propose, since=since, where=lambda p: p.conversation == "cfp-a2"))
    before = next(e.seconds for e in prop.estimates if e.index == 4)
    assert again.estimates[0].seconds != pytest.approx(before, rel=1e-3)


def test_cancelled_units_are_dropped_and_a_full_agent_refuses(farm: Farm, bundles: dict) -> None:
    scene, _ = bundles["cbox"]
    # ~8 M samples, a few seconds on one thread: still rendering while the second award queues and when
    # it is cancelled (2 M ran in 0.8 s on a fast day and ended before the second award).
    job = farm.job("job-b", sha_of(bundles, "cbox"), scene, spp=8192, level="off")
    whole = unit(0, Rect(0, 0, 32, 32))
    since = time.monotonic()
    farm.run(farm.master.send(farm.award(job, whole, "award-b0")))
    farm.run(farm.master.expect(m.Heartbeat, since=since, where=lambda h: len(h.busy) == 1
                                and (h.busy[0].job_id, h.busy[0].index) == ("job-b", 0)))
    # One unit rendering leaves slots (agents hold eight): it bids, and takes the next units to queue.
    farm.run(farm.master.send(cfp(job, "cfp-slot", unit(1, Rect(0, 0, 8, 8)))))
    propose = farm.run(farm.master.expect(m.Propose, since=since))
    assert propose.conversation == "cfp-slot"
    for i in range(1, SLOTS):
        farm.run(farm.master.send(farm.award(job, unit(i, Rect(0, 0, 8, 8)), f"award-b{i}")))
    farm.run(farm.master.expect(m.Heartbeat, since=since, where=lambda h: len(h.busy) == SLOTS))
    farm.run(farm.master.send(cfp(job, "cfp-busy", unit(SLOTS, Rect(8, 0, 8, 8)))))
    refuse = farm.run(farm.master.expect(m.Refuse, since=since))
    assert refuse.conversation == "cfp-busy" and "busy" in refuse.reason

    cancelled_at = time.monotonic()
    farm.run(farm.master.send(m.Cancel(conversation="award-b0", job_id="job-b", index=None, reason="test")))
    farm.run(farm.master.expect(m.Heartbeat, since=cancelled_at + 0.1, where=lambda h: h.busy == ()))
    # Free again once the abandoned render ends: it proposes, and never delivered the cancelled unit.
    deadline = time.monotonic() + 20
    while True:
        conv = f"cfp-free-{time.monotonic_ns()}"
        farm.run(farm.master.send(cfp(job, conv, unit(1, Rect(0, 0, 8, 8)))))
        answer = farm.run(farm.master.expect(m.Message, since=cancelled_at,
                                             where=lambda x, c=conv: getattr(x, "conversation", "") == c))
        if isinstance(answer, m.Propose):
            break
        assert time.monotonic() < deadline, "agent still busy 20 s after the cancel"
        time.sleep(0.5)
    assert not [u for u in farm.master.uploads if u[0] == "job-b"]
    assert not [x for x in farm.master.received(m.Failure, since) if x.job_id == "job-b"]


ELSEWHERE = ("bundle-elsewhere", "upload-elsewhere")  # another loopback port than the master's (a spoofed award)


@pytest.mark.parametrize("case", ["broken-scene", "wrong-hash", "upload-refused", *ELSEWHERE])
def test_failures_are_reported_and_survived(farm: Farm, bundles: dict, case: str) -> None:
    """Each fails its unit with the reason, and the agent serves on. A URL not under --master-url is never
    tried (the reason is the pin's, not a refused connection)."""
    name = "broken" if case == "broken-scene" else "cbox"
    scene, _ = bundles[name]
    job_id = f"job-{case}"
    wrong = "0" * 64 if case == "wrong-hash" else None
    job = farm.job(job_id, sha_of(bundles, name), scene, level="off", scene_hash=wrong,
                   defines={} if name == "broken" else None)
    elsewhere = f"http://127.0.0.1:{farm.master.http_port + 1}/"  # same host, another port
    named = dataclasses.replace(job, scene_url=elsewhere + f"jobs/{job_id}/bundle") if case == ELSEWHERE[0] else job
    u = unit(2, Rect(16, 0, 16, 16))
    award = farm.award(named, u, f"award-{case}")
    if case == "upload-elsewhere":
        award = dataclasses.replace(award, upload_url=elsewhere + f"jobs/{job_id}/units/2/tile")
    if case == "upload-refused":
        farm.master.tokens[(job_id, 2)] = "f" * 32  # the data plane expects another token
    since = time.monotonic()
    farm.run(farm.master.send(award))
    failure = farm.run(farm.master.expect(m.Failure, since=since), 30)
    assert (failure.conversation, failure.job_id, failure.index, failure.token) == \
        (award.conversation, job_id, 2, award.token)
    expected = {"broken-scene": "no_such_plugin_here", "wrong-hash": "sha256", "upload-refused": "403",
                **dict.fromkeys(ELSEWHERE, "is not at the master's URL")}[case]
    assert expected in failure.reason, failure.reason
    assert not [u for u in farm.master.uploads if u[0] == job_id]
    # Still serving: the next call for proposals gets a proposal.
    farm.run(farm.master.send(cfp(job, f"after-{case}", unit(5, Rect(0, 0, 8, 8)))))
    farm.run(farm.master.expect(m.Propose, since=since, where=lambda p: p.conversation == f"after-{case}"))


def test_registers_again_after_the_server_restarts(farm: Farm, bundles: dict) -> None:
    farm.server.restart()
    restarted = time.monotonic()
    # Usually ~2 s; a reconnect that misses the disconnect event waits for SPADE's 55 s keepalive
    # (docs/design.md section 4), seen once in a loaded full run: the bound covers that path.
    reg = farm.run(farm.master.expect(m.Register, since=restarted, timeout=70.0), 75)
    assert reg.speed > 0
    scene, _ = bundles["cbox"]
    job = farm.job("job-a", sha_of(bundles, "cbox"), scene)
    farm.run(farm.master.send(cfp(job, "after-restart", unit(6, Rect(0, 0, 8, 8)))))
    farm.run(farm.master.expect(m.Propose, since=restarted, where=lambda p: p.conversation == "after-restart"))


def test_units_awarded_together_render_in_one_call_and_each_is_delivered(farm: Farm, bundles: dict) -> None:
    scene, _ = bundles["cbox"]
    job = farm.job("job-t", sha_of(bundles, "cbox"), scene, level="S")
    # alike units (the rules give them one depth) in the four quarters of the 32 px image
    units = [unit(i, Rect(16 * (i % 2), 16 * (i // 2), 16, 16)) for i in range(4)]
    for u in units:  # sent back to back: they arrive while the first one's bundle is fetched
        farm.run(farm.master.send(farm.award(job, u, f"award-t{u.index}")))
    for u in units:
        farm.run(farm.master.expect_upload("job-t", u.index, 60), 65)
    tiles = {i: read_tile_bytes(data, "upload") for j, i, data in farm.master.uploads if j == "job-t"}
    assert sorted(tiles) == [0, 1, 2, 3]
    assert all(t.meta["window_method"].startswith("together") for t in tiles.values())
    seeds = [t.meta["seed"] for t in tiles.values()]
    assert max(seeds.count(s) for s in seeds) >= 2, seeds  # units shared a call (its first unit's seed)
    for i, tile in tiles.items():
        assert tile.core == units[i].rect and np.isfinite(tile.pixels).all() and tile.pixels.mean() > 0.01


def test_a_batch_that_fails_together_renders_its_units_alone(tmp_path: Path) -> None:
    """A batch's call fails (here: two integrators, which one call cannot render): each unit is rendered
    alone, so that one bad unit fails by itself and does not take its batch with it."""
    from agents.render_agent import AgentConfig, RenderAgent
    from core.model.job import SceneSpec
    from core.render.process import RenderRequest

    agent = RenderAgent(AgentConfig(jid=AGENT, password=PASSWORD, master=MASTER, workdir=tmp_path))
    try:
        scene = SceneSpec(CBOX, {"res": "32"})
        requests = [RenderRequest(scene, "llvm_ad_rgb", integrator, 4, 4, i, 32, 32, Rect(16 * i, 0, 16, 16),
                                  band=2, threads=1, job_id="job-f", unit_index=i)
                    for i, integrator in enumerate(["path", "direct"])]
        tiles = agent._render_tiles(requests, 120.0, None, True)
        assert [t.core for t in tiles] == [r.unit for r in requests]
        assert not any(t.meta["window_method"].startswith("together") for t in tiles)  # each its own call
        assert all(np.isfinite(t.pixels).all() for t in tiles)
    finally:
        agent.worker.stop()


def test_a_batch_out_of_time_leaves_its_units_none_of_the_step(tmp_path: Path) -> None:
    """The step's timeout is the whole step's: a batch killed at its end fails its units with its reason,
    where each unit rendered alone again would have held the step for another timeout each (a real render
    process)."""
    from agents.render_agent import AgentConfig, RenderAgent
    from core.model.job import SceneSpec
    from core.render.batch import batches
    from core.render.process import RenderRequest

    agent = RenderAgent(AgentConfig(jid=AGENT, password=PASSWORD, master=MASTER, workdir=tmp_path))
    try:
        scene = SceneSpec(CBOX, {"res": "256"})
        # Two 64 px units at 1800 spp: one batch (under core.render.batch.BATCH_SAMPLES), about 9 s
        requests = [RenderRequest(scene, "llvm_ad_rgb", None, 4, 1800, i, 256, 256, Rect(64 * i, 0, 64, 64),
                                  band=2, threads=1, job_id="job-t", unit_index=i) for i in range(2)]
        assert len(batches(requests)) == 1
        timeout = 4.0
        start = time.monotonic()
        results = agent._render_tiles(requests, timeout, None, True)
        took = time.monotonic() - start
        assert all(isinstance(r, Exception) for r in results), results
        assert all("units [0, 1]: timed out" in str(r) for r in results), results  # the batch's call, killed
        assert took < 1.5 * timeout, took  # rendered alone again, the two units would add 2 x 4 s
    finally:
        agent.worker.stop()


def test_a_failed_unit_logs_its_story_on_one_line(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The agent's Failure goes with a WARNING of the unit's status changes and the stimuli that made them."""
    from agents.render_agent import AgentConfig, RenderAgent
    from agents.state import BundleFailed, MessageReceived, SendToMaster

    agent = RenderAgent(AgentConfig(jid=AGENT, password=PASSWORD, master=MASTER, master_url="http://127.0.0.1:1",
                                    workdir=tmp_path))
    try:
        info = m.JobInfo(job_id="job-s", scene_url="http://127.0.0.1:1/jobs/job-s/bundle", scene_hash="ab" * 32,
                         width=32, height=32, spp=4, depth=6, level="N", ranges=RANGES)
        award = m.Award(conversation="award-s", job=info, unit=unit(3, Rect(0, 0, 16, 16)), token="a1" * 16,
                        upload_url="http://127.0.0.1:1/jobs/job-s/units/3/tile", seed=3, estimate_s=1.0)
        agent.state.handle(MessageReceived(award, stimulus_id="accept-proposal:award-s#1"), 10.0)
        out = agent.state.handle(BundleFailed(1, "no bundle", stimulus_id="bundle-1"), 10.25)
        with caplog.at_level(logging.WARNING, logger="agents.render_agent"):
            asyncio.run(agent._execute([c for c in out if isinstance(c, SendToMaster)]))  # offline: not sent
    finally:
        agent.worker.stop()
    (line,) = [r.getMessage() for r in caplog.records if "story" in r.getMessage()]
    assert line == ("unit 3 of job job-s: story: new -> queued by accept-proposal:award-s#1 at +0.000 s; "
                    "queued -> fetching by accept-proposal:award-s#1 at +0.000 s; "
                    "fetching -> failed by bundle-1 at +0.250 s")


def test_the_log_format_is_an_option_defaulting_to_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from agents.render_agent import build_parser

    need = ["--jid", "a@localhost", "--password", "p", "--master", "m@localhost", "--master-url", "http://127.0.0.1:1"]
    monkeypatch.delenv("QUEKARO_LOG_FORMAT", raising=False)
    assert build_parser().parse_args(need).log_format == "text"
    assert build_parser().parse_args([*need, "--log-format", "json"]).log_format == "json"
    monkeypatch.setenv("QUEKARO_LOG_FORMAT", "json")
    assert build_parser().parse_args(need).log_format == "json"


def test_stops_cleanly_on_sigterm(farm: Farm) -> None:
    assert farm.agent.poll() is None
    farm.agent.send_signal(signal.SIGTERM)
    assert farm.agent.wait(timeout=20) == 0
    assert "Traceback" not in farm.log.read_text(errors="replace")
