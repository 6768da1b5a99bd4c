"""master.pass_merge: passes merged as their tiles land, what the auction hears, and a job's end."""

from __future__ import annotations

import numpy as np

from core.image.passes import WEIGHT
from core.image.tiles import Tile, write_tile
from core.model.geometry import Rect
from master.pass_merge import PassMerger


def _pass(path, index: int, value: float, spp: int = 4):
    pixels = np.concatenate([np.full((4, 4, 3), value, np.float32), np.full((4, 4, 1), spp, np.float32)], axis=-1)
    tile = Tile(pixels, Rect(0, 0, 4, 4), Rect(0, 0, 4, 4), {"unit_index": index, "spp": spp, "seconds": 0.5},
                ("R", "G", "B", WEIGHT))
    return str(write_tile(path / f"unit-{index}.exr", tile))


def test_passes_of_a_unit_merge_and_a_job_that_ended_keeps_no_sums(tmp_path):
    merger = PassMerger()
    first = merger.merge("j", 2, 1, _pass(tmp_path, 1, 1.0))  # unit 1, pass 0 of a 2-unit job
    assert (first.index, first.spp, first.relmse) == (1, 4, None)  # one pass: its noise unknown
    second = merger.merge("j", 2, 3, _pass(tmp_path, 3, 3.0))  # unit 1, pass 1
    assert second.spp == 8 and second.seconds == 1.0 and second.relmse > 0
    merger.forget("j")
    late = merger.merge("j", 2, 5, _pass(tmp_path, 5, 2.0))  # after the end: merged alone, not kept
    assert late.spp == 4 and merger._sums == {}


def test_the_live_image_shows_each_unit_with_all_its_passes_merged(tmp_path):
    """The page composes a progressive job's stored passes as one source per unit (`merged_sources`): its
    pixels the passes' weighted mean, as the final assembly's, not the first pass alone (duplicates of a
    core were dropped, so the live image stayed at the first pass)."""
    from core.image.compose import compose_shrunk
    from master.pass_merge import merged_sources, merged_units
    from master.store import ResultRecord

    results = [ResultRecord("j", i, _pass(tmp_path, i, value, spp), "", {})
               for i, value, spp in ((0, 1.0, 4), (1, 4.0, 12), (2, 3.0, 8))]  # 1 unit, 3 passes
    (source,) = merged_sources(results, 1)
    assert source.channels == ("R", "G", "B") and source.core == Rect(0, 0, 4, 4)
    live = compose_shrunk([source], 4, 4, 1)
    (final,), _ = merged_units(results, 1, {})
    expected = (1.0 * 4 + 4.0 * 12 + 3.0 * 8) / 24
    assert np.allclose(live, expected) and np.allclose(final.pixels, expected)
    assert merged_sources(results[:1], 1)[0].load().pixels[0, 0, 0] == 1.0  # one pass so far: itself
    gone = ResultRecord("j", 3, str(tmp_path / "missing.exr"), "", {})
    assert len(merged_sources([*results, gone], 1)) == 1  # a tile not on disk (yet) is left out
