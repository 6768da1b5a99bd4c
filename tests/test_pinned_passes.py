"""A progressive job at a rule level: its plan pins each unit's depth and samples once (the rules'), every
pass of the unit carries that depth on the wire and in the store, the auction budgets each unit's own
samples, and a pass tile at another depth is refused (merged, passes of two depths estimate no image)."""

from __future__ import annotations

import dataclasses
import json
import random

import pytest
from auction_support import register, tick

from core.errors import MessageError
from core.image.passes import WEIGHT
from core.model import messages as m
from core.model.geometry import Rect
from core.model.job import JobSpec, RenderOptions, SceneSpec
from core.model.units import WorkUnit
from core.rules.unit_params import Planner
from master import auction as au
from master.auction.passes import PassBook
from master.store import JobStore
from planning.jobplan import plan_job, plan_params
from planning.progressive import BUDGET, Goal, budget_passes
from tests.test_farm import REPO
from tests.test_store import plan_of

CHANNELS = ("R", "G", "B", WEIGHT)


def _unit(index: int, depth: int | None, spp: int | None = 16) -> WorkUnit:
    return WorkUnit(index=index, rect=Rect(8 * index, 0, 8, 8), C=0.1, S=64, Nd=0.0, cost=1.0, spp=spp, depth=depth)


def _job(level: str = "VB", passes: bool = True) -> m.JobInfo:
    return m.JobInfo(job_id="job-1", scene_url="http://127.0.0.1:1/b", scene_hash="a" * 64, width=16, height=8,
                     spp=64, depth=8, level=level, ranges={}, passes=passes)


def test_the_plan_pins_each_units_depth_and_samples_to_the_rules_choice_at_a_rule_level():
    spec = SceneSpec(REPO / "scenes" / "cbox.xml", {"res": "96"})
    plan = plan_job(spec, RenderOptions(level="VS", spp=64, progressive=True, threads=1, units=9), seed=1)
    rules = plan_params(plan, Planner())
    assert [(u.depth, u.spp) for u in plan.units] == [(p.depth, p.spp) for p in rules]
    assert len({u.spp for u in plan.units}) > 1  # the rules' own samples, not the user's
    off = plan_job(spec, RenderOptions(level="off", spp=32, progressive=True, threads=1), seed=1)
    assert {(u.depth, u.spp) for u in off.units} == {(None, None)}  # level off: the job's depth and spp


def test_a_budget_job_renders_each_pinned_units_own_samples_and_its_passes_keep_the_depth():
    book = PassBook.open(Goal(BUDGET, 64), (_unit(0, 5, 16), _unit(1, 8, 3)), 0.0)
    [first] = book.machine.start()
    by_unit = {u: [o.spp for o in first.orders if o.unit == u] for u in (0, 1)}
    assert by_unit == {0: budget_passes(16), 1: budget_passes(3)}
    passes = [book.pass_unit(o) for o in first.orders]
    assert {(p.index % 2, p.depth) for p in passes} == {(0, 5), (1, 8)}
    level_off = PassBook.open(Goal(BUDGET, 64), (_unit(0, None, None),), 0.0)
    assert sum(o.spp for o in level_off.machine.start()[0].orders) == 64  # the job's spp, every unit


def test_a_pass_carries_its_units_depth_on_the_wire_only_at_a_rule_level():
    cfp = m.CallForProposal(conversation="c1", job=_job(), units=(_unit(0, 5),), reply_within_s=1.0)
    assert [u.depth for u in m.parse(*m.encode(cfp)).units] == [5]
    assert WorkUnit.from_dict(_unit(0, 5).to_dict()).depth == 5 and "depth" not in _unit(0, None).to_dict()
    bad = [(_job(), _unit(0, 5), None, "at level VB has depth None"),
           (_job("off"), _unit(0, None), 5, "at level off has depth 5"),
           (_job(passes=False), _unit(0, None, None), 5, "has depth 5 in a job that is not in passes")]
    for job, unit, depth, message in bad:
        performative, body = m.encode(m.CallForProposal(conversation="c1", job=job, units=(unit,),
                                                        reply_within_s=1.0))
        data = json.loads(body)
        data["units"][0]["depth"] = depth
        with pytest.raises(MessageError, match=message):
            m.parse(performative, json.dumps(data))


def test_the_store_keeps_a_passs_depth_and_the_plan_its_units_pins_past_their_passes(tmp_path):
    """The rows of a progressive job's units become its first passes (their spp the pass's): the plan keeps
    what the rules pinned, for the auction to take up after a restart."""
    with JobStore(tmp_path / "jobs.db") as store:
        store.create_job("j", "s.xml", JobSpec(), plan_of([_unit(0, 5), _unit(1, None)]), 0.0)
        assert [u.unit().depth for u in store.units("j")] == [5, None]
        plan = dataclasses.replace(plan_of([_unit(0, 5, 16), _unit(1, 8, 3)]),
                                   options=RenderOptions(level="VS", spp=64, progressive=True))
        store.create_job("p", "s.xml", JobSpec(options=plan.options), plan, 0.0)
        store.apply([au.PassesOrdered("p", (_unit(0, 5, 8), _unit(1, 8, 2)), 2, "a round")], 1.0)
        assert [u.spp for u in store.units("p")] == [8, 2]  # the first passes'
        assert [(u.depth, u.spp) for u in store.plan("p", tmp_path / "s.xml").units] == [(5, 16), (8, 3)]


def _pass_tile_refusal(depth: int) -> str:
    """Why the auction refuses a pass tile of the pinned unit (depth 5) that says `depth` ("" if taken)."""
    a = au.Auction(au.Config(slots=2), rng=random.Random(1))
    a.handle(au.JobSubmitted(_job(), (_unit(0, 5, 2),), CHANNELS, goal=Goal(BUDGET, 64)), 0.0)
    register(a, "agent-1@localhost", 0.0)
    [call] = [i.message for i in tick(a, 0.0) if isinstance(i, au.SendToAgent)]
    estimates = tuple(m.Estimate(index=u.index, seconds=1.0) for u in call.units)
    a.handle(au.MessageReceived("agent-1@localhost", m.Propose(conversation=call.conversation, job_id="job-1",
                                                              estimates=estimates)), 0.0)
    award = next(i.message for i in tick(a, 0.0) if isinstance(i, au.SendToAgent) and isinstance(i.message, m.Award))
    assert award.unit.depth == 5
    figures = m.TileFigures(depth=depth, spp=award.unit.spp, band=2, seconds=1.0, nonfinite=0)
    tile = au.TileStored("job-1", award.unit.index, award.token, "/tiles/t.exr", "cd" * 32, figures, CHANNELS)
    return next((i.reason for i in a.handle(tile, 1.0) if isinstance(i, au.RefuseTile)), "")


def test_a_pass_tile_at_another_depth_than_its_units_is_refused():
    assert _pass_tile_refusal(5) == ""
    assert "a pass's tile header says depth 8; its unit's passes render at depth 5" in _pass_tile_refusal(8)


def _passes_of(config: au.Config, units: tuple[WorkUnit, ...]) -> dict[int, list[int]]:
    """Each unit's first round of passes (their spp) when the auction opens a budget job of `units`."""
    a = au.Auction(config, rng=random.Random(1))
    out = a.handle(au.JobSubmitted(_job(), units, CHANNELS, goal=Goal(BUDGET, 64)), 0.0)
    [ordered] = [i for i in out if isinstance(i, au.PassesOrdered)]
    by_unit: dict[int, list[int]] = {}
    for unit in ordered.units:
        by_unit.setdefault(unit.index % len(units), []).append(unit.spp)
    return by_unit


def test_a_farms_pass_holds_at_least_the_masters_pass_samples_where_its_unit_has_them():
    """Config.pass_samples (the master's --pass-samples): an 8x8 unit of 16 spp is one pass by default,
    a 512x512 one keeps its five; at 1 every unit renders its five passes."""
    small = _unit(0, 5, 16)
    large = WorkUnit(index=1, rect=Rect(8, 0, 512, 512), C=0.1, S=512 * 512, Nd=0.0, cost=1.0, spp=16, depth=5)
    assert _passes_of(au.Config(), (small, large)) == {0: [16], 1: budget_passes(16)}
    assert _passes_of(au.Config(pass_samples=1), (small, large)) == {0: budget_passes(16), 1: budget_passes(16)}
