"""Adaptive jobs (planning.budgets, `--adaptive`): the whole job against plain Mitsuba rendering the same
file (the same means in every channel the film writes), the plan's shares and the report, the shares at
their edges, the worker's two-pass orders, and the refusals that say why."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from auction_support import refusal
from compat_cases import CASES, adaptive_args, check_adaptive_report, compare_files, quekaro, reference
from render_check import by_name

from core.errors import MessageError, QuekaroError, RenderError
from core.image.imageio import read_image_channels
from core.model import messages as m
from core.model.geometry import Rect
from core.model.hashing import sha256_file
from core.model.job import RenderOptions, SceneSpec
from core.model.levels import RULE_LEVELS
from core.model.seeds import plan_seed
from core.model.units import SPP_MAX, WorkUnit
from core.render.process import RenderRequest, render_job_here
from core.rules.unit_params import RenderParams, adaptive_params
from planning.budgets import level_spp, shares
from planning.jobplan import plan_job

BY_CASE = {c.name: c for c in CASES}
REPO = Path(__file__).resolve().parent.parent
RUNS = 8  # adaptive images per case: their own variance enters the test on the means (with 4 its
# estimate from 3 degrees of freedom made a few pixels look significant that 8 runs did not)


def _render(case, out, units: int = 1) -> subprocess.CompletedProcess:
    return quekaro("render", *adaptive_args(case, units), "-o", str(out), "--threads", "2", "--no-progress")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["rgba", "aov", "spectral-spiky", "medium-homogeneous", "moment", "film-crop",
                                  "film-xyza"])
def test_an_adaptive_job_keeps_mitsubas_means(name, tmp_path):
    """RUNS jobs (each its own job id, so its own seeds) against 32 of plain Mitsuba's renders: no pixel
    channel's mean differs beyond the fireflies render_check tolerates; the channels are the film's.
    Four units, so that bands meet at unit borders (composition cuts each band's filter reach:
    core.image.compose) and the shares may differ."""
    case = BY_CASE[name]
    ref_names = reference(case)[1]
    images = []
    for k in range(RUNS):
        out = tmp_path / f"job{k}.exr"
        done = _render(case, out, units=4)
        assert done.returncode == 0, done.stderr[-2000:]
        image, names = read_image_channels(out)
        assert sorted(names) == sorted(ref_names)
        images.append(by_name(image, names, ref_names))
    verdict = compare_files(case, images)
    assert verdict.only_fireflies, f"{name}: {verdict}"
    check_adaptive_report(json.loads((tmp_path / "job0.json").read_text()), units=4)


def test_an_adaptive_job_renders_its_units_in_two_passes(tmp_path):
    out = tmp_path / "job.exr"
    done = _render(BY_CASE["aov"], out, units=4)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.with_suffix(".json").read_text())
    check_adaptive_report(report, units=4)
    assert f"adaptive: {report['adaptive']['mean_spp']} spp per pixel from the rules" in done.stdout
    _, names = read_image_channels(out)
    assert len(names) == 11  # the film's channels, nothing added


def test_an_adaptive_jobs_budget_is_the_same_on_a_farm_as_in_one_process():
    """The rules ran on a partition cut into at least the farm's minimum units (or a farm's larger units),
    and the rules weigh a unit's size: this job's level spent 50 spp per pixel with a farm's 8-unit minimum,
    83 alone."""
    spec = SceneSpec(REPO / "scenes" / "cbox.xml", {"res": "96", "spp": "128"})
    options = RenderOptions(level="S", adaptive=True, units=3)
    alone, farm = plan_job(spec, options, seed=5), plan_job(spec, options, seed=5, min_units=8, farm=True)
    assert alone.shares["mean_spp"] == farm.shares["mean_spp"], (alone.shares, farm.shares)
    assert alone.shares["rule_units"] == farm.shares["rule_units"] and len(farm.units) == 3


def test_the_levels_of_a_scene_read_one_pre_pass_and_spend_in_the_rules_order():
    """Seeded as `quekaro render` seeds it (core.model.seeds.plan_seed). A level's budget moves with the
    pre-pass's noise (here the sunlit glossy units'), so levels seeded apart could spend in another order
    than the rules' (this scene and size did, with a seed per level)."""
    spec = SceneSpec(REPO / "bench" / "scenes" / "outdoor.xml", {"res": "128"})
    spent = []
    for level in RULE_LEVELS:
        options = RenderOptions(level=level, spp=64, threads=2, adaptive=True)
        plan = plan_job(spec, options, seed=plan_seed(sha256_file(spec.path), spec.defines, options.to_dict()))
        spent.append(plan.shares["mean_spp"])
    assert spent == sorted(spent, reverse=True) and spent[0] > spent[-1], dict(zip(RULE_LEVELS, spent, strict=True))


def _rects(n: int) -> list[Rect]:
    return [Rect(8 * i, 0, 8, 8) for i in range(n)]


def test_shares_go_where_the_noise_is_and_keep_the_budget():
    noise = np.full((8, 32), 0.01)
    noise[:, :8] = 10.0  # the first unit is far noisier
    split = shares(noise, _rects(4), 16)
    assert split.adapted and split.predicted < 0.95 and split.first == 8
    assert split.spp[0] > 16 and min(split.spp[1:]) == 8  # the quiet ones keep only the first pass
    assert sum(split.spp) == pytest.approx(4 * 16, abs=2)
    flat = shares(np.full((8, 32), 0.2), _rects(4), 16)
    assert not flat.adapted and flat.spp == (16, 16, 16, 16) and flat.predicted == pytest.approx(1.0)
    silent = shares(np.zeros((8, 32)), _rects(4), 16)  # nothing measured: equal
    assert not silent.adapted and silent.spp == (16, 16, 16, 16)
    one = shares(noise, _rects(4), 1)  # one sample each: no room to move any
    assert one.spp == (1, 1, 1, 1) and one.first == 1
    with pytest.raises(QuekaroError, match="not a finite non-negative image"):
        shares(np.full((8, 32), np.nan), _rects(4), 16)


def test_no_share_passes_the_most_spp_a_unit_may_carry():
    noise = np.full((8, 32), 0.01)
    noise[:, :8] = 10.0
    split = shares(noise, _rects(4), SPP_MAX)
    assert split.adapted and max(split.spp) == SPP_MAX
    WorkUnit(index=0, rect=Rect(0, 0, 8, 8), C=1.0, S=64, Nd=0.0, cost=1.0, spp=max(split.spp))


def test_the_level_spends_the_rules_samples_by_area():
    units = [WorkUnit(index=i, rect=r, C=0.0, S=r.area, Nd=0.0, cost=1.0)
             for i, r in enumerate([Rect(0, 0, 8, 8), Rect(8, 0, 24, 8)])]
    assert level_spp(units, [RenderParams(4, 10, 2), RenderParams(4, 30, 2)]) == 25  # (10 x 64 + 30 x 192) / 256
    params = adaptive_params([dataclasses.replace(u, spp=7) for u in units], depth=5, band=3)
    assert [(p.depth, p.spp, p.band) for p in params] == [(5, 7, 3), (5, 7, 3)]
    with pytest.raises(ValueError, match=r"units \[0, 1\] of an adaptive or progressive job carry no planned spp"):
        adaptive_params(units, depth=5, band=3)


def _request(**extra) -> RenderRequest:
    case = BY_CASE["rgba"]
    return RenderRequest(SceneSpec(case.scene), case.variant, None, None, 8, 5, 48, 40, Rect(16, 8, 24, 16),
                         band=2, threads=2, **extra)


def test_a_two_pass_order_renders_the_window_and_says_what_it_did():
    tile = render_job_here(_request(first=4))
    assert tile.pixels.shape == (20, 28, len(tile.channels))  # the unit grown by its band
    assert tile.meta["first_spp"] == 4 and tile.meta["spp"] == 8 and len(tile.meta["pass_seconds"]) == 2
    assert isinstance(tile.meta["adapted"], bool) and tile.meta["predicted_relmse_ratio"] > 0
    spent = render_job_here(_request(first=8))  # the first pass is the whole share: no second
    assert spent.meta["pass_seconds"][1] == 0.0 and not spent.meta["adapted"]


def test_a_first_pass_must_fit_the_share():
    with pytest.raises(RenderError, match=r"first=9 \(the first pass's spp: must be in 1..spp=8\)"):
        _request(first=9)
    with pytest.raises(RenderError, match="first=0"):
        _request(first=0)
    assert RenderRequest.from_dict(_request(first=3).to_dict()).first == 3


def test_adaptive_needs_a_rule_level_and_a_boolean():
    with pytest.raises(QuekaroError, match="adaptive sampling places a rule level"):
        RenderOptions(level="off", adaptive=True)
    with pytest.raises(QuekaroError, match="not true or false"):
        RenderOptions(level="S", adaptive="yes")
    assert RenderOptions.from_dict(RenderOptions(level="S", adaptive=True).to_dict()).adaptive is True


def test_an_adaptive_job_on_a_stratified_sampler_is_refused_before_its_pre_pass(tmp_path):
    """Per-pixel counts need the independent sampler: `quekaro render --adaptive` says so at planning,
    naming the file and the sampler, and writes nothing (it had failed at unit 0, after the pre-pass)."""
    case = BY_CASE["lanczos"]
    shutil.copytree(case.scene.parent, tmp_path / "scenes")
    scene = tmp_path / "scenes" / case.scene.name
    scene.write_text(scene.read_text().replace('sampler type="independent"', 'sampler type="stratified"'))
    assert 'sampler type="stratified"' in scene.read_text()
    out = tmp_path / "out.exr"
    done = quekaro("render", str(scene), "--opt", "S", "--adaptive", "-o", str(out), "--no-progress")
    assert done.returncode == 2
    assert f"{scene}: --adaptive: sampler StratifiedSampler" in done.stderr and "independent" in done.stderr
    assert not out.exists()


def _job(first_spp: int | None) -> m.JobInfo:
    return m.JobInfo(job_id="job-1", scene_url="http://127.0.0.1:1/b", scene_hash="a" * 64, width=16, height=8,
                     spp=64, depth=4, level="S", ranges={}, first_spp=first_spp)


def _unit(spp: int | None, index: int = 0) -> WorkUnit:
    return WorkUnit(index=index, rect=Rect(8 * index, 0, 8, 8), C=0.0, S=64, Nd=0.0, cost=1.0, spp=spp)


def test_messages_carry_an_adaptive_jobs_shares_and_refuse_mismatches():
    """A call for proposals or award of an adaptive job carries each unit's share, at least the first pass;
    a job whose rules choose carries none. Either mismatch is refused naming the field."""
    cfp = m.CallForProposal(conversation="c1", job=_job(8), units=(_unit(20), _unit(8, 1)), reply_within_s=1.0)
    award = m.Award(conversation="c1", job=_job(8), unit=_unit(20), token="b" * 32,
                    upload_url="http://127.0.0.1:1/t", seed=1, estimate_s=1.0)
    back = m.parse(*m.encode(cfp))
    assert [u.spp for u in back.units] == [20, 8] and back.job.first_spp == 8
    assert m.parse(*m.encode(award)).unit.spp == 20
    for first, spp, said in ((8, None, "needs spp >= first_spp 8, has None"), (8, 7, "needs spp >= first_spp 8, has 7"),
                             (None, 20, "has spp 20 in a job whose rules choose it")):
        for msg, units, field in ((cfp, "units", "units.spp"), (award, "unit", "unit.spp")):
            performative, body = m.encode(msg)
            data = json.loads(body)
            data["job"]["first_spp"] = first
            target = data[units][0] if units == "units" else data[units]
            target.pop("spp", None)
            if spp is not None:
                target["spp"] = spp
            with pytest.raises(MessageError, match=said) as err:
                m.parse(performative, json.dumps(data))
            assert err.value.field == field


def test_the_master_refuses_a_tile_that_did_not_render_its_share():
    """A peer that renders fewer samples than the plan gave its unit, or one pass, is found out by its
    tile header: its image would be averaged with the others' as if it had rendered the share."""
    good = {"spp": 20, "first_spp": 8, "depth": 4, "band": 2}
    figures = m.TileFigures.from_header
    assert refusal(_job(8), _unit(20), figures(good)) == ""
    assert refusal(_job(None), _unit(None), figures({"spp": 5})) == ""  # rules jobs: the agent's choice
    for meta, said in (({**good, "spp": 10}, "says spp 10, first pass 8; the plan gives spp 20, first pass 8"),
                       ({"spp": 20}, "says spp 20, first pass None")):
        assert said in refusal(_job(8), _unit(20), figures(meta))
    with pytest.raises(QuekaroError, match="first_spp 'x' is not a sample count"):
        figures({**good, "first_spp": "x"})
