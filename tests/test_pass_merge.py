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
