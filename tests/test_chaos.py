"""Chaos (real processes, seeded, bounded in time): a supervised local farm renders 10 small jobs at several
levels while a schedule SIGKILLs random agents, the master twice and the XMPP server once, and a lying
agent (a real account of the farm) answers awards with informs but no tiles and PUTs tiles for units it
does not hold. Every job must complete, no unit count as done twice, no tile of the liar be accepted, and
every image be statistically the one an undisturbed farm makes of the same job (per-pixel test on the
moment integrator's mean and variance, tests/render_check.py)."""

from __future__ import annotations

import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from compat_cases import SCENES
from render_check import compare_moment_renders, least_spp, moment_channels

from core.image.imageio import read_image_channels
from core.scene.bundle import make_bundle
from farm.client import FarmClient
from farm.local import LocalFarm

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
SCENE = SCENES / "chaos.xml"
LEVELS = ("off", "VS", "S", "N", "B")
JOBS = 10
DEFINES: dict[str, str] = {}
DEADLINE_S = 600.0


def _submit_all(client: FarmClient, jobs: int = JOBS) -> list[str]:
    """`jobs` jobs of the scene, their levels in turn."""
    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_bundle(SCENE, DEFINES, Path(tmp) / "b.tar").path.read_bytes()
    return [client.submit(bundle, DEFINES, {"level": LEVELS[i % len(LEVELS)], "units": 4}) for i in range(jobs)]


def _client(home: Path, timeout: float = 60.0) -> FarmClient:
    """A client of the master, waiting while a restarted master comes up."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            client = FarmClient.from_home(home)
            client.jobs()
            return client
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


def _statuses(home: Path, jobs: list[str]) -> dict[str, str]:
    client = _client(home)
    return {j: client.status(j)["status"] for j in jobs}


def _wait_all(home: Path, jobs: list[str], until: float) -> dict[str, str]:
    while time.monotonic() < until:
        statuses = _statuses(home, jobs)
        if all(s != "running" for s in statuses.values()):
            return statuses
        time.sleep(0.5)
    return _statuses(home, jobs)


def _results(home: Path, jobs: list[str], out: Path) -> dict[str, tuple]:
    client = _client(home)
    found = {}
    for i, job in enumerate(jobs):
        exr = client.result(job, out / f"{i}.exr")
        image, names = read_image_channels(exr)
        report = json.loads(exr.with_suffix(".json").read_text())
        mean, variance = moment_channels(image, names)
        found[job] = (mean, variance, least_spp(report), report)
    return found


def _start_liar(farm: LocalFarm, home: Path) -> subprocess.Popen:
    env = dict(os.environ, QUEKARO_XMPP_PASSWORD=farm.add_account("agent-liar"), PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, str(REPO / "tests" / "liar_agent.py"), "--jid", "agent-liar@localhost",
                             "--port", str(farm.server.port), "--master", "master@localhost", "--lies", "4"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=REPO)


def _running(home: Path) -> int:
    with sqlite3.connect(f"file:{home / 'jobs.sqlite'}?mode=ro", uri=True, timeout=30) as db:
        return db.execute("SELECT COUNT(*) FROM jobs WHERE status = 'running'").fetchone()[0]


def _chaos(farm: LocalFarm, rng: random.Random, jobs: list[str], home: Path) -> list[tuple[str, int]]:
    """The schedule: kill an agent, the master, the XMPP server, an agent, the master, 2-4 s apart; each
    event with the number of jobs running when it struck."""
    done = []
    for what in ("agent", "master", "server", "agent", "master"):
        time.sleep(rng.uniform(2.0, 4.0))
        running = _running(home)
        if what == "server":
            farm.server.kill()  # the supervisor restarts it (and ends its workers)
        else:
            names = [c.name for c in farm.children if c.name.startswith(what) and c.state == "running"]
            victim = next(c for c in farm.children if c.name == rng.choice(names))
            os.kill(victim.proc.pid, signal.SIGKILL)
        done.append((what, running))
    return done


def test_jobs_complete_correctly_through_chaos(tmp_path):
    rng = random.Random(20261124)
    chaos_home, calm_home = tmp_path / "chaos", tmp_path / "calm"
    with LocalFarm(chaos_home, agents=2, threads=1, supervise=True) as farm:
        farm.wait_for_agents()
        liar = _start_liar(farm, chaos_home)
        jobs = _submit_all(farm.client())
        events = _chaos(farm, rng, jobs, chaos_home)
        assert all(running > 0 for _, running in events), f"the chaos struck an idle farm: {events}"
        statuses = _wait_all(chaos_home, jobs, time.monotonic() + DEADLINE_S)
        assert set(statuses.values()) == {"done"}, (statuses, events)
        chaotic = _results(chaos_home, jobs, tmp_path)
        liar.kill()
        lies = [json.loads(line) for line in liar.stdout.read().splitlines() if line.startswith("{")]
    db = sqlite3.connect(chaos_home / "jobs.sqlite")
    twice = db.execute("SELECT job_id, idx, COUNT(*) FROM attempts WHERE outcome = 'done' GROUP BY job_id, idx"
                       " HAVING COUNT(*) > 1").fetchall()
    assert twice == [], f"units counted done twice: {twice}"
    assert all(u["agent"] != "agent-liar@localhost" for r in chaotic.values() for u in r[3]["units"])
    lied = [e for e in lies if e["event"] == "lied"]
    assert lied and all(e["foreign_put"] >= 400 for e in lied), lies  # it was heard, and refused
    with LocalFarm(calm_home, agents=2, threads=1) as farm:
        farm.wait_for_agents()
        calm_jobs = _submit_all(farm.client(), len(LEVELS))  # one job a level: the chaotic ones' peers
        assert set(_wait_all(calm_home, calm_jobs, time.monotonic() + DEADLINE_S).values()) == {"done"}
        calm = _results(calm_home, calm_jobs, tmp_path / "calm")
    for i, job in enumerate(jobs):
        calm_job = calm_jobs[i % len(LEVELS)]
        verdict = compare_moment_renders(chaotic[job][:3], calm[calm_job][:3])
        assert verdict.passed, f"job {i} ({LEVELS[i % len(LEVELS)]}): {verdict}"
