"""A progressive job's progress on a real job store: its units are its image's (a budget unit is done once
every pass of it is done; a noise or time goal's only at the job's end), its passes apart (done, ordered,
mean spp), its ETA sensible for each goal; the job API, `quekaro status` and `watch` say so. The records
are the auction's own types, applied as the master applies them (the farm's run of it is in
tests/test_web_page.py)."""

from __future__ import annotations

import io
from pathlib import Path
from types import SimpleNamespace

import pytest
from rich.console import Console

from core.model.geometry import Rect
from core.model.job import Effects, JobPlan, JobSpec, RenderOptions, SceneSpec
from core.model.units import WorkUnit
from master import auction as au
from master.job_api import job_summary
from master.pass_merge import write_verdicts
from master.store import JobStore
from planning.progressive import budget_passes
from quekaro import cmd_farm

JOB, AGENT, N, SPP = "job-p", "agent-0@localhost", 4, 16
REPORT = {"depth": 8, "spp": 1, "band": 0, "nonfinite": 0}


def units() -> list[WorkUnit]:
    return [WorkUnit(index=i, rect=Rect(8 * i, 0, 8, 8), C=0.5, S=64, Nd=0.1, cost=1.0) for i in range(N)]


def new_job(path: Path, **goal: object) -> JobStore:
    """A progressive job of N units (at level off, as a farm renders them) created as the master does."""
    options = RenderOptions(level="off", spp=SPP, **goal)
    plan = JobPlan(SceneSpec(Path("scene.xml")), options, 8 * N, 8, Effects("llvm_ad_rgb", "path", 8, []), SPP, 8,
                   units(), bundle_sha256="ef" * 32)
    store = JobStore(path)
    store.create_job(JOB, "scene.xml", JobSpec({}, options), plan, 100.0)
    return store


def order(store: JobStore, passes: list[tuple[int, int, int]]) -> None:
    """(unit, pass, spp) passes ordered: pass k of unit u is the row k N + u."""
    made = tuple(WorkUnit(index=k * N + u, rect=Rect(8 * u, 0, 8, 8), C=0.5, S=64, Nd=0.1, cost=1.0, spp=spp)
                 for u, k, spp in passes)
    store.apply([au.PassesOrdered(JOB, made, len(made), "a round")], 100.0)


def render(store: JobStore, index: int, started: float, seconds: float | None) -> str:
    """Pass row `index` awarded at `started`, and done `seconds` later (None: still rendering); its token."""
    token = f"token-{index}-{started}"
    store.apply([au.UnitAwarded(JOB, index, AGENT, token, 1.0, 1, started + 60)], started)
    if seconds is not None:
        land(store, index, token, seconds, started + seconds)
    return token


def land(store: JobStore, index: int, token: str, seconds: float, now: float) -> None:
    done = au.UnitDone(JOB, index, AGENT, token, seconds, 1.0, f"/tiles/{index}.exr", "00" * 32, REPORT, 1, True)
    store.apply([done], now)


def budget_job(path: Path) -> JobStore:
    """16 spp a unit in passes of 1, 7, 4, 2, 2, all ordered at once (planning.progressive)."""
    store = new_job(path, progressive=True)
    sizes = budget_passes(SPP)
    order(store, [(u, k, s) for k, s in enumerate(sizes) for u in range(N)])
    return store


def test_a_withdrawn_pass_leaves_the_store_and_its_unit_done_by_the_pass_that_stood_in(tmp_path: Path) -> None:
    """Unit 0's last pass is slow; an idle agent's extra pass of it lands first and the slow one is withdrawn
    (planning.progressive.Withdraw): it goes with its attempt, so the unit is done with every pass it keeps
    done, and nothing reads as failed."""
    store = budget_job(tmp_path / "jobs.sqlite")
    sizes = budget_passes(SPP)
    for k in range(len(sizes) - 1):
        render(store, k * N, 101.0 + k, float(sizes[k]))
    slow = (len(sizes) - 1) * N
    render(store, slow, 110.0, None)
    extra = len(sizes) * N
    order(store, [(0, len(sizes), sizes[-1])])
    render(store, extra, 111.0, 1.0)
    store.apply([au.PassesWithdrawn(JOB, (slow,), 1, "its unit has the samples its round asks from another pass")],
                112.5)
    p = store.progress(JOB, 113.0)
    assert (p.done, p.failed) == (1, 0)
    assert (p.passes.done, p.passes.ordered) == (len(sizes), N * len(sizes))  # the extra in the slow one's place
    assert store.attempts(JOB, slow) == []
    # unit 1's first pass (row 1, the unit's own row) stood in for by an extra one: the image's area holds
    stood_in = len(sizes) * N + 1
    order(store, [(1, len(sizes), sizes[0])])
    render(store, stood_in, 114.0, 8.0)
    store.apply([au.PassesWithdrawn(JOB, (1,), 1, "its unit has the samples its round asks from another pass")],
                122.5)
    p = store.progress(JOB, 123.0)
    # unit 0's 16 spp and unit 1's first pass over 4 equal units, to a tenth as the page writes it
    assert p.passes.spp_mean == round((SPP + sizes[0]) / N, 1)
    plan = store.plan(JOB, Path("scene.xml"))  # as a restarted master and the assembly read it: every unit
    assert [(u.index, u.rect) for u in plan.units] == [(u.index, u.rect) for u in units()]


def test_a_budget_jobs_unit_is_done_once_every_pass_of_it_is_done(tmp_path: Path) -> None:
    store = budget_job(tmp_path / "jobs.sqlite")
    sizes = budget_passes(SPP)
    assert store.progress(JOB, 100.0).done == 0 and store.progress(JOB).total == N
    for k in range(len(sizes)):  # unit 0 whole, one second per spp
        render(store, k * N, 101.0 + k, float(sizes[k]))
    for u in (1, 2, 3):  # the first pass of the others
        render(store, u, 101.0, float(sizes[0]))
    p = store.progress(JOB, 120.0)
    assert (p.done, p.total, p.failed) == (1, N, 0)
    assert (p.passes.done, p.passes.ordered, p.passes.goal) == (len(sizes) + 3, N * len(sizes), "budget")
    assert p.passes.spp_mean == round((SPP + 3 * sizes[0]) / N, 1)
    left = 3 * (SPP - sizes[0])  # seconds of the passes not rendered, at one second per spp
    assert p.eta_s == pytest.approx(left) and not p.eta_at_least
    # unit 1's passes done while an idle agent's extra pass of it is out: done once that one lands too
    order(store, [(1, len(sizes), sizes[-1])])
    extra = render(store, len(sizes) * N + 1, 121.0, None)
    for k in range(1, len(sizes)):
        render(store, k * N + 1, 121.0 + k, float(sizes[k]))
    assert store.progress(JOB, 130.0).done == 1
    land(store, len(sizes) * N + 1, extra, float(sizes[-1]), 130.0)
    assert store.progress(JOB, 131.0).done == 2
    # the job ends: its passes still out are cancelled (failed rows), and no unit is "left unrendered"
    store.apply([au.JobDone(JOB)], 132.0)
    p = store.progress(JOB, 132.0)
    assert (p.done, p.total, p.failed, p.eta_s) == (N, N, 0, 0.0)
    assert p.passes.ordered == N * len(sizes) + 1 and p.passes.done == 2 * len(sizes) + 3


def test_a_cancelled_budget_job_counts_the_units_it_finished_and_those_it_left_short(tmp_path: Path) -> None:
    store = budget_job(tmp_path / "jobs.sqlite")
    sizes = budget_passes(SPP)
    for k in range(len(sizes)):
        render(store, k * N, 101.0 + k, float(sizes[k]))  # unit 0 whole
    render(store, 1, 101.0, float(sizes[0]))  # unit 1 its first pass only
    render(store, 2, 101.0, None)  # unit 2's first pass out when the job ends
    store.apply([au.JobCancelled(JOB, "cancelled by the user")], 110.0)
    p = store.progress(JOB, 110.0)
    assert (p.done, p.total, p.failed, p.passes.done, p.passes.ordered) == (1, N, N - 1, len(sizes) + 1, 5 * N)


def test_a_noise_jobs_units_are_judged_at_its_end_and_its_eta_is_a_lower_bound(tmp_path: Path) -> None:
    store = new_job(tmp_path / "jobs.sqlite", noise=0.05)
    order(store, [(u, k, 1) for k in range(4) for u in range(N)])  # the first round: 4 passes of 1 spp
    for u in range(N):
        for k in range(4):
            render(store, k * N + u, 101.0 + k, 1.0)
    p = store.progress(JOB, 110.0)
    assert (p.done, p.total, p.passes.done, p.passes.spp_mean) == (0, N, 4 * N, 4.0)
    assert p.eta_s == 0.0 and p.eta_at_least  # the round is over; what follows is not known yet
    order(store, [(u, 4, 4) for u in range(N)])  # a second round: 4 spp more each
    render(store, 4 * N, 111.0, None)
    p = store.progress(JOB, 112.0)
    assert p.done == 0 and p.eta_at_least and p.eta_s == pytest.approx(N * 4 * 1.0 - 1.0)  # 1 s a spp, 1 s rendered
    store.apply([au.JobCancelled(JOB, "cancelled by the user")], 113.0)
    p = store.progress(JOB, 113.0)
    assert (p.done, p.failed, p.eta_at_least) == (0, N, False)  # every unit left short of its goal


def test_a_time_jobs_eta_is_its_time_left_from_the_first_award(tmp_path: Path) -> None:
    store = new_job(tmp_path / "jobs.sqlite", time=30.0)
    order(store, [(u, k, 1) for k in range(4) for u in range(N)])
    assert store.progress(JOB, 100.0).eta_s == pytest.approx(30.0)  # no award yet: all of it
    render(store, 0, 101.0, 1.0)
    render(store, N, 102.0, None)
    p = store.progress(JOB, 111.0)
    assert p.eta_s == pytest.approx(20.0) and not p.eta_at_least and p.done == 0
    assert store.progress(JOB, 200.0).eta_s == pytest.approx(4 * N - 1 - 1.0)  # time spent: the passes out
    for u in range(1, N):
        render(store, u, 200.0, 1.0)
    store.apply([au.JobDone(JOB)], 201.0)
    assert store.progress(JOB, 201.0).done == N


def test_the_job_api_status_and_watch_show_units_and_passes_apart(tmp_path: Path, capsys) -> None:
    store = budget_job(tmp_path / "jobs.sqlite")
    render(store, 0, 101.0, 8.0)
    service = SimpleNamespace(store=store, paused=None, job_dir=lambda job_id: tmp_path / job_id,
                              result_path=lambda job_id: tmp_path / job_id / "result.exr")
    job = job_summary(service, JOB)
    assert (job["units_done"], job["units_total"], job["eta_at_least"]) == (0, N, False)
    first = budget_passes(SPP)[0] / N  # pass 0 of unit 0 done, over the 4 units
    share = round(budget_passes(SPP)[0] / (N * SPP), 3)  # the samples done over the job's, its units alike in cost
    assert job["passes"] == {"done": 1, "ordered": 5 * N, "spp_mean": round(first, 1), "goal": "budget",
                             "share": share, "stopped": None}
    assert cmd_farm._passes_text(job) == f", 1/{5 * N} passes, {round(first, 1)} spp"
    assert cmd_farm._eta_text({**job, "eta_s": 12.4, "eta_at_least": True}, " s") == "at least 12 s"
    assert cmd_farm._eta_text({**job, "eta_s": 0.0, "eta_at_least": True}, " s") == "unknown"  # not "at least 0 s"
    plain = {**job, "passes": None, "eta_s": 12.4, "eta_at_least": False}
    assert cmd_farm._passes_text(plain) == "" and cmd_farm._eta_text(plain, " s") == "12 s"

    class Client:  # `quekaro watch` against the job API's answer, the job ending at the second poll
        polls = 0

        def status(self, _job_id: str) -> dict:
            self.polls += 1
            return {**job, "status": "running" if self.polls < 3 else "done", "effects": {}}

    assert cmd_farm.watch(Client(), JOB, poll_s=0.01) == 0
    out = capsys.readouterr().out
    assert f"0/{N} units" in out and f"1/{5 * N} passes, {round(first, 1)} spp" in out, out
    bar = io.StringIO()  # on a terminal of 80 columns: the bar's share is the work's, and it has room
    Client.polls = 0
    cmd_farm._watch_bar(Client(), JOB, job, 0.01, Console(file=bar, width=80, force_terminal=True, color_system=None))
    last = bar.getvalue().split("\r")[-1]
    shown = f"{share * 100:.0f}% 0/{N} units {round(first, 1)} spp"
    assert shown in last and last.index(shown) - last.index("done") >= 20, last  # the bar between them


def test_a_time_goals_share_is_its_seconds_spent(tmp_path: Path) -> None:
    store = new_job(tmp_path / "jobs.sqlite", time=10.0)
    order(store, [(u, 0, 4) for u in range(N)])
    assert store.progress(JOB, 100.0).passes.share == 0.0  # no award yet: its clock has not started
    render(store, 0, 101.0, 1.0)
    assert store.progress(JOB, 105.0).passes.share == 0.4 and store.progress(JOB, 130.0).passes.share == 1.0


def test_a_requeued_pass_is_named_by_its_unit_and_pass_not_its_row(tmp_path: Path) -> None:
    store = new_job(tmp_path / "jobs.sqlite", progressive=True)
    order(store, [(0, 0, 8), (2, 1, 8)])  # pass 1 of unit 2 is row 1 N + 2 = 6
    token = render(store, 6, 101.0, None)
    store.apply([au.UnitRequeued(JOB, 6, AGENT, token, f"agent {AGENT} lost")], 102.0)
    progress = store.progress(JOB, 102.0)
    assert progress.retried == 1 and progress.last_retry == f"unit 2, pass 1 requeued: agent {AGENT} lost"


def test_status_says_why_a_job_in_passes_stopped(tmp_path: Path, capsys) -> None:
    store = budget_job(tmp_path / "jobs.sqlite")
    (tmp_path / JOB).mkdir()
    write_verdicts(tmp_path / JOB, au.PassesSettled(JOB, "every unit has its samples (3.0 s)", {0: "budget"}))
    service = SimpleNamespace(store=store, paused=None, job_dir=lambda job_id: tmp_path / job_id,
                              result_path=lambda job_id: tmp_path / job_id / "result.exr")
    job = job_summary(service, JOB)
    assert job["passes"]["stopped"] == "every unit has its samples (3.0 s)"
    cmd_farm._print_job(job)
    assert "  stopped: every unit has its samples (3.0 s)" in capsys.readouterr().out.splitlines()
