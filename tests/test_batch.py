"""Units rendered together (core.render.batch): how they are batched, the samples each pixel draws, and
that each unit's tile is plain Mitsuba's render at the unit's own depth and spp (render_check)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from render_check import by_name, compare, reference_renders

from core.errors import RenderError
from core.model.geometry import Rect, filter_reach
from core.model.job import SceneSpec
from core.model.seeds import unit_seed
from core.render.batch import (
    batch_counts,
    batches,
    bounds,
    render_batch_here,
    together_problem_here,
)
from core.render.process import RenderProcess, RenderRequest

SCENES = Path(__file__).resolve().parent / "compat" / "scenes"
W, H = 48, 40


def job(unit: Rect, spp: int = 8, depth: int | None = 4, band: int = 2, index: int = 0, job_id: str = "j",
        scene: Path = SCENES / "rgba.xml", variant: str = "llvm_ad_rgb") -> RenderRequest:
    return RenderRequest(SceneSpec(scene, {}), variant, None, depth, spp, unit_seed(job_id, index, 0), W, H, unit,
                         band=band, threads=2, job_id=job_id, unit_index=index)


def six_units(depths: tuple[int, ...], spps: tuple[int, ...], **kw) -> list[RenderRequest]:
    """The 48x40 image as 3 x 2 units of 16x20, unit i at depths[i % len], spps[i % len]."""
    rects = [Rect(x, y, 16, 20) for y in (0, 20) for x in (0, 16, 32)]
    return [job(r, spps[i % len(spps)], depths[i % len(depths)], index=i, **kw) for i, r in enumerate(rects)]


def test_batches_hold_one_depth_in_order_and_respect_the_cap():
    jobs = six_units((4, 2), (8,))
    assert [[j.unit_index for j in b] for b in batches(jobs)] == [[0, 2, 4], [1, 3, 5]]
    window = jobs[0].window.area * 8  # each unit's window (20x24 with its band) at 8 spp
    assert [[j.unit_index for j in b] for b in batches(jobs, cap=2 * window)] == [[0, 2], [1, 3], [4], [5]]
    # a unit larger than the cap is a batch of its own, and the next unit starts a new one
    assert [[j.unit_index for j in b] for b in batches(jobs, cap=window - 1)] == [[0], [1], [2], [3], [4], [5]]
    assert batches([]) == []
    # the bounding rectangle of a batch's windows is capped too: units 0 and 2 (x 0..20 and 28..48 with
    # their bands) span 48 x 24 pixels, unit 4 (y 16..40) would make it 48 x 40; units 1 and 3 would span
    # 34 x 40, units 3 and 5 span 48 x 24
    assert [[j.unit_index for j in b] for b in batches(jobs, pixels=48 * 24)] == [[1], [0, 2], [3, 5], [4]]
    # what a batch renders: the whole image (one kernel for every batch of a depth), or where the image
    # is larger than the cap, the least rectangle holding its windows
    assert bounds([jobs[0], jobs[2]]) == Rect(0, 0, 48, 40)
    assert bounds([jobs[0], jobs[2]], pixels=48 * 40 - 1) == Rect(0, 0, 48, 24)


def test_each_pixel_draws_its_units_spp_and_band_pixels_of_other_batches_their_windows():
    jobs = six_units((4, 2), (8, 32))  # units 0, 2, 4 at depth 4 and 8 spp; 1, 3, 5 at depth 2, 32 spp
    counts = batch_counts([j for j in jobs if j.max_depth == 4])
    assert counts.shape == (H, W)
    for j in jobs:
        inner = counts[j.unit.y:j.unit.y + j.unit.h, j.unit.x:j.unit.x + j.unit.w]
        if j.max_depth == 4:
            assert (inner == 8).all()
        else:  # another batch's unit: drawn only within 2 px (the band) of a depth-4 unit's rectangle
            assert set(np.unique(inner)) == {0, 8}
            assert (inner[:, 2:-2] == 0).any()
    # a pixel is drawn exactly where a depth-4 unit's window (its rectangle grown by its band, shifted inside
    # at the image's edge) holds it
    held = np.zeros((H, W), dtype=bool)
    for j in jobs:
        if j.max_depth == 4:
            held[j.window.y:j.window.y + j.window.h, j.window.x:j.window.x + j.window.w] = True
    assert ((counts > 0) == held).all()
    # unit 1 (x 16..32, y 0..20) between units 0, 2 and 4: its middle is left to its own batch
    assert (counts[0:16, 20:28] == 0).all() and (counts[0:16, 16:20] == 8).all()


def test_a_batch_of_mixed_depths_is_refused():
    with pytest.raises(RenderError, match="one job, depth and sensor"):
        render_batch_here(six_units((4, 2), (8,))[:2])


@pytest.mark.parametrize(("xml", "reason"), [("sampler_stratified.xml", "independent sampler"),
                                             ("sample_border.xml", "sample_border"),
                                             ("ptracer.xml", "not a sampling integrator"),
                                             ("prb", "Python differentiable"),
                                             ("stokes.xml", "polarized")])
def test_scenes_render_counts_cannot_render_are_named(tmp_path, xml, reason):
    """Each refused with its reason, so that its units render one by one: a prb scene (its sample() has
    another signature) once passed the check and failed in the render, and a stokes scene's render crashed
    its process."""
    scene = SCENES / xml
    if xml == "prb":
        scene = tmp_path / "prb.xml"
        scene.write_text((SCENES / "rgba.xml").read_text().replace('integrator type="path"', 'integrator type="prb"'))
    variant = "llvm_ad_spectral_polarized" if xml == "stokes.xml" else "llvm_ad_rgb"
    with RenderProcess() as worker:
        problem = worker.call(together_problem_here, job(Rect(0, 0, 16, 16), scene=scene, variant=variant),
                              timeout=120)
    assert problem is not None and reason in problem


def _at_depth(tmp_path: Path, scene: Path, depth: int) -> Path:
    """A copy of `scene` whose integrator has max_depth `depth` (for plain Mitsuba's references)."""
    text, n = re.subn(r'(name="max_depth" value=")\d+', rf"\g<1>{depth}", scene.read_text())
    assert n == 1
    out = tmp_path / f"{scene.stem}-d{depth}.xml"
    out.write_text(text)
    return out


@pytest.mark.slow
@pytest.mark.parametrize(("xml", "variant", "depths"), [("rgba.xml", "llvm_ad_rgb", (4, 1)),
                                                        ("spectral_grey_box.xml", "llvm_ad_spectral", (8, 2)),
                                                        ("medium_homogeneous.xml", "llvm_ad_rgb", (8, 2)),
                                                        ("orthographic.xml", "llvm_ad_rgb", (6, 2)),
                                                        ("thinlens.xml", "llvm_ad_rgb", (6, 2)),
                                                        ("lanczos.xml", "llvm_ad_rgb", (6, 2))])
def test_units_rendered_together_are_mitsubas_render_at_each_units_depth_and_spp(tmp_path, xml, variant, depths):
    """Six units at two depths and three spp, bands of 4 px, in two batches (alpha, spectral, a medium, an
    orthographic and a thin-lens camera, a lanczos filter).
    Every pixel that composition takes from a tile (its window but the filter's reach at an inner edge)
    against 32 plain Mitsuba renders of the file at the tile's depth and the spp its batch drew there:
    means and variance. One render is compared, as render_check compares a job: with several, their own
    variance estimate from a few renders at 4 spp made plain Mitsuba's per-unit renders fail it too."""
    spps = (4, 16, 8)
    jobs = six_units(depths, spps, band=4, scene=SCENES / xml, variant=variant)
    groups = batches(jobs)
    assert len(groups) == 2
    with RenderProcess() as worker:
        tiles = {int(t.meta["unit_index"]): t for b in groups for t in worker.call(render_batch_here, b, timeout=300)}
    assert sorted(tiles) == list(range(6))
    refs = {}
    for d in depths:
        path = _at_depth(tmp_path, SCENES / xml, d)
        for spp in spps:
            refs[d, spp], names = reference_renders(path, variant, spp, search_paths=(SCENES,))
    test, ref = [], []
    for batch in groups:
        counts = batch_counts(batch)  # the batch's bounds are the whole 48 x 40 image here
        assert counts.shape == (H, W)
        for u in batch:
            tile = tiles[u.unit_index]
            assert tile.meta["window_method"].startswith("together") and tile.meta["depth"] == u.max_depth
            taken = _taken(u.window, filter_reach(tile.meta["filter_radius"]))
            drawn = counts[u.window.slices()]
            test.append(by_name(tile.pixels, tile.channels, names)[taken])
            ref.append(np.stack([refs[u.max_depth, int(n)][:, u.window.y + y, u.window.x + x]
                                 for y, x, n in zip(*np.nonzero(taken), drawn[taken], strict=True)], axis=1))
    verdict = compare(np.concatenate(test)[None], np.concatenate(ref, axis=1)[:, None])
    assert verdict.passed, f"{xml}: {verdict}"
    # the depths differ where it matters: the two depths' references differ far beyond their noise
    a, b = (refs[d, 16].mean(axis=(1, 2, 3)) for d in depths)
    assert abs(a.mean() - b.mean()) > 10 * np.sqrt(a.var() / 32 + b.var() / 32)


def _taken(window: Rect, reach: int) -> np.ndarray:
    """The window's pixels that composition takes: all but `reach` pixels at each edge inside the image."""
    mask = np.ones((window.h, window.w), dtype=bool)
    if window.x > 0:
        mask[:, :reach] = False
    if window.x1 < W:
        mask[:, window.w - reach:] = False
    if window.y > 0:
        mask[:reach, :] = False
    if window.y1 < H:
        mask[window.h - reach:, :] = False
    return mask


@pytest.mark.slow
def test_a_rule_level_job_renders_together_and_a_stratified_scene_unit_by_unit(tmp_path):
    """`quekaro render --opt S`: an independent-sampler scene's units come from one call per batch; a
    stratified sampler's from Mitsuba's render per unit, and the report says why."""
    from test_cli import quekaro

    for xml, together in (("rgba.xml", True), ("sampler_stratified.xml", False)):
        scene = tmp_path / xml  # at 128x96, room for several units of at least 32 px
        scene.write_text((SCENES / xml).read_text().replace('"width" value="48"', '"width" value="128"')
                         .replace('"height" value="40"', '"height" value="96"'))
        done = quekaro("render", str(scene), "-a", str(SCENES), "--opt", "S", "--units", "6", "-o", str(tmp_path),
                       "--threads", "2",
                       "--no-progress")
        assert done.returncode == 0, done.stderr
        report = json.loads((tmp_path / scene.stem).with_suffix(".json").read_text())
        calls, units = report["render_calls"], len(report["units"])
        assert units >= 4 and calls["together"] is together
        if together:
            assert calls["calls"] < units and calls["why_not"] is None
        else:
            assert calls["calls"] == units and "independent sampler" in calls["why_not"]
