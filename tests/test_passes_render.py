"""A unit rendered in passes and merged (core.image.passes) is Mitsuba's render at the summed spp, with
any reconstruction filter, whether its passes are Mitsuba's own render calls or batched per-pixel renders
(render_check: means and variance against 32 plain Mitsuba renders of the file)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from render_check import by_name, compare, reference_renders

from core.image.compose import compose, image_channels
from core.image.metrics import RELMSE_EPSILON
from core.image.passes import WEIGHT, UnitPasses, merge_pass
from core.model.geometry import Rect, filter_reach
from core.model.job import RenderOptions, SceneSpec
from core.model.seeds import unit_seed
from core.render.batch import render_batch_here
from core.render.process import RenderProcess, RenderRequest
from planning.jobplan import plan_job

SCENES = Path(__file__).resolve().parent / "compat" / "scenes"
W, H = 48, 40
SPPS = (4, 8, 4)  # three passes: 16 spp in all


def _scene(tmp_path: Path, rfilter: str) -> Path:
    """rgba.xml (alpha, gaussian filter) or a copy with another filter in its film."""
    source = SCENES / "rgba.xml"
    if rfilter == "gaussian":
        return source
    out = tmp_path / f"rgba-{rfilter}.xml"
    film = '<film type="hdrfilm">'
    out.write_text(source.read_text().replace(film, f'{film}<rfilter type="{rfilter}"/>'))
    return out


def _pass(scene: Path, spp: int, index: int) -> RenderRequest:
    return RenderRequest(SceneSpec(scene, {}), "llvm_ad_rgb", None, None, spp, unit_seed("p", 0, index), W, H,
                         Rect(0, 0, W, H), threads=2, job_id="p", unit_index=0, pass_index=index)


def _merged(worker: RenderProcess, scene: Path, spps: tuple[int, ...], batched: bool) -> UnitPasses:
    merged = None
    for index, spp in enumerate(spps):
        request = _pass(scene, spp, index)
        tile = (worker.call(render_batch_here, [request], timeout=300)[0] if batched
                else worker.render(request, timeout=300))
        assert tile.channels[-1] == WEIGHT and tile.meta["pass"] == index and tile.meta["spp"] == spp
        if merged is None:
            merged = UnitPasses.first(tile)
        else:
            merged.add(tile)
    return merged


@pytest.mark.slow
@pytest.mark.parametrize("rfilter", ["gaussian", "box", "lanczos"])
@pytest.mark.parametrize("batched", [False, True], ids=["mitsuba-render", "batched"])
def test_passes_merged_are_one_render_at_the_summed_spp(tmp_path, rfilter, batched):
    scene = _scene(tmp_path, rfilter)
    ref, names = reference_renders(scene, "llvm_ad_rgb", sum(SPPS))
    with RenderProcess() as worker:
        merged = _merged(worker, scene, SPPS, batched)
        fewer = _merged(worker, scene, SPPS[:1], batched)
    assert merged.spp == 16 and merged.passes == 3
    image = by_name(merged.pixels(), merged.channels, names)
    verdict = compare(image, ref)
    assert verdict.passed, f"{rfilter}: {verdict}"
    # the check can fail: the first pass alone (4 spp) is too noisy for a 16-spp render
    short = compare(by_name(fewer.pixels(), fewer.channels, names), ref)
    assert not short.passed and short.variance_ratio > 2, short
    # the between-pass noise is the merge's: its mean over pixel channels, and the unit's relMSE, are within
    # 20 % of what the 32 references give at 16 spp (a median would not do: with 3 passes, 2 degrees of
    # freedom per pixel and skewed path contributions, a pixel's estimate is usually low and sometimes high)
    true = ref[..., :3].var(axis=0, ddof=1)
    assert 0.8 < merged.variance().mean() / true.mean() < 1.2
    mean = ref[..., :3].mean(axis=0)
    assert 0.8 < merged.relmse() / float(np.mean(true / (mean * mean + RELMSE_EPSILON))) < 1.2


FILTER_RADII = {"gaussian": 2.0, "box": 0.5, "tent": 1.0}  # Mitsuba's defaults


@pytest.mark.slow
@pytest.mark.parametrize("rfilter", ["gaussian", "box", "tent"])
def test_units_whose_passes_spill_add_up_to_one_render(tmp_path, rfilter):
    """Four units, each in its own passes (16 spp each, split unlike), every sample drawn on its unit alone
    and its band holding the spill (RenderRequest.spill): their merged tiles, added up by composition, are
    one Mitsuba render at 16 spp, seams included."""
    scene = _scene(tmp_path, rfilter)
    ref, names = reference_renders(scene, "llvm_ad_rgb", 16)
    reach = filter_reach(FILTER_RADII[rfilter])
    units = [Rect(0, 0, 24, 20), Rect(24, 0, 24, 20), Rect(0, 20, 24, 20), Rect(24, 20, 24, 20)]
    splits = [(4, 8, 4), (8, 8), (16,), (2, 2, 4, 8)]
    tiles = []
    with RenderProcess() as worker:
        for index, (unit, spps) in enumerate(zip(units, splits, strict=True)):
            sums: dict[int, UnitPasses] = {}
            for k, spp in enumerate(spps):
                request = RenderRequest(SceneSpec(scene, {}), "llvm_ad_rgb", None, None, spp,
                                        unit_seed("s", index, k), W, H, unit, band=reach, threads=2, job_id="s",
                                        unit_index=index, pass_index=k, spill=True)
                merge_pass(sums, index, worker.render(request, timeout=300))
            tiles.append(sums[index].tile({"unit_index": index}))
    assert all(t.channels[-1] == WEIGHT and t.meta["spill"] for t in tiles)
    image, report = compose(tiles, W, H, reach=reach)
    verdict = compare(by_name(image, image_channels(tiles[0].channels), names), ref)
    assert verdict.passed, f"{rfilter}: {verdict}"
    assert report.filled == 0 and report.uncovered == 0


def test_a_farms_level_off_job_in_passes_spills_where_the_film_adds_up(tmp_path):
    """JobPlan.spill: a farm's level-off job in passes over several units; not in one process (a round
    renders in one call there), not at a rule level, and not where the tiles could not add up: a filter
    with negative lobes, a stratified sampler, a user's integrator. The plan says why it spills."""
    cbox = Path(__file__).resolve().parent.parent / "scenes" / "cbox.xml"
    stratified = tmp_path / "stratified.xml"
    stratified.write_text(cbox.read_text().replace('<sampler type="independent">', '<sampler type="stratified">'))

    def spills(scene: Path, farm: bool = True, **options) -> bool:
        opts = RenderOptions(**{"level": "off", "spp": 16, "progressive": True, "threads": 1, "units": 4, **options})
        plan = plan_job(SceneSpec(scene, {"res": "64"} if "rgba" not in scene.name else {}), opts, farm=farm)
        said = any(r.startswith("bands: each unit's samples are drawn on its own pixels") for r in plan.effects.reasons)
        assert said == plan.spill
        return plan.spill

    assert spills(cbox)
    assert not spills(cbox, farm=False)
    assert not spills(cbox, level="S")
    assert not spills(cbox, integrator="path")
    assert not spills(stratified)
    assert spills(_scene(tmp_path, "gaussian")) and not spills(_scene(tmp_path, "lanczos"))
