"""A progressive job's passes merged on the master (core.image.passes): as each pass's tile lands, into its
unit's running sums, whose noise estimate the auction decides on (`PassMerger`, which takes the stored
passes up again after a master restart: `passes_so_far`); at assembly, every stored pass again, into one
tile per unit (`merged_units`); for the page's live image, one source per unit that merges its passes so
far when it is composed (`merged_sources`); and the passes' verdicts.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from core.files import written_atomically
from core.image.compose import TileSource
from core.image.passes import WEIGHT, UnitPasses, merge_pass
from core.image.tiles import Tile, read_tile, tile_source
from core.model.units import WorkUnit
from master import auction as au
from planning.progressive import UnitSoFar

VERDICTS_FILE = "passes.json"  # a progressive job's end: why, and each unit's verdict


class PassMerger:
    """The running sums of the progressive jobs' units, one lock a job (tiles land in parallel)."""

    def __init__(self) -> None:
        self._sums: dict[str, dict[int, UnitPasses]] = {}
        self._locks: dict[str, threading.Lock] = {}
        self._ended: set[str] = set()  # jobs forgotten: a late pass merges alone, its sums not kept
        self._guard = threading.Lock()

    def merge(self, job_id: str, units: int, index: int, tile_path: str) -> au.PassMerged:
        """Merge pass `index` (a pass's work unit of a job of `units` units) from its tile; what the auction
        hears of it. Runs in a worker thread."""
        unit, _ = au.pass_origin(index, units)
        tile = read_tile(tile_path)
        with self._lock(job_id):
            sums = self._sums.setdefault(job_id, {}) if job_id not in self._ended else {}
            done = merge_pass(sums, unit, tile)
            return au.PassMerged(job_id, index, done.spp, done.seconds, done.relmse(),
                                 stimulus_id=f"merged-{job_id}-{index}")

    def restore(self, job_id: str, units: int, results: Iterable[Any]) -> dict[int, UnitPasses]:
        """After a master restart: the job's stored passes (the store's results) merged again, as the sums
        the passes to come merge into; each unit's sums."""
        sums = {unit: _merge(unit, passes) for unit, passes in _passes_by_unit(results, units).items()}
        with self._lock(job_id):
            self._sums[job_id] = sums
        return dict(sums)

    def forget(self, job_id: str) -> None:
        """The job has ended: its sums go (assembly merges the stored passes again)."""
        with self._guard:
            self._sums.pop(job_id, None)
            self._locks.pop(job_id, None)
            self._ended.add(job_id)

    def _lock(self, job_id: str) -> threading.Lock:
        with self._guard:
            return self._locks.setdefault(job_id, threading.Lock())


def merged_units(results: Iterable[Any], units: int, verdicts: dict[int, str]
                 ) -> tuple[list[Tile], dict[int, dict[str, Any]]]:
    """Every stored pass (the store's results: index, tile_path, params) merged into one tile per unit, and
    each unit's report line's parameters: the passes' depth and band, all their spp, the estimated error
    and the verdict."""
    tiles, lines = [], {}
    for unit, passes in _passes_by_unit(results, units).items():
        merged = _merge(unit, passes)
        tiles.append(merged.tile({"unit_index": unit, "seconds": merged.seconds, "window_method": "passes"}))
        agents = ", ".join(sorted({str(r.params.get("agent")) for r in passes}))
        lines[unit] = {**passes[0].params, **merged.account(), "verdict": verdicts.get(unit), "agent": agents}
    return tiles, lines


def passes_so_far(sums: dict[int, UnitPasses], rows: Sequence[WorkUnit], done: set[int], units: int
                  ) -> tuple[UnitSoFar, ...]:
    """Each unit's passes as a restarted master finds them: merged (`sums`: none for a budget job, which
    only counts them), their samples as ordered (the store's `rows` of the `done` passes), still out (the
    other rows), and the next pass index."""
    credited, out, next_pass = [0] * units, [dict() for _ in range(units)], [0] * units
    for row in rows:
        unit, pass_index = au.pass_origin(row.index, units)
        next_pass[unit] = max(next_pass[unit], pass_index + 1)
        if row.index in done:
            credited[unit] += row.spp or 0
        else:
            out[unit][pass_index] = row.spp or 0
    return tuple(UnitSoFar(s.spp, credited[u], s.passes, s.seconds, s.relmse(), out[u], next_pass[u])
                 if (s := sums.get(u)) is not None else
                 UnitSoFar(credited=credited[u], out=out[u], next_pass=next_pass[u])
                 for u in range(units))


def merged_sources(results: Iterable[Any], units: int) -> list[TileSource]:
    """One tile source per unit of the stored passes whose tiles are on disk, which merges that unit's
    passes when composition loads it: a unit's pixels are all its samples so far, and the passes are read
    one unit at a time."""
    stored = [r for r in results if Path(r.tile_path).is_file()]
    return [_merged_source(unit, passes) for unit, passes in _passes_by_unit(stored, units).items()]


def _passes_by_unit(results: Iterable[Any], units: int) -> dict[int, list[Any]]:
    """The results grouped by the unit each pass is of (au.pass_origin), units and passes in index order."""
    grouped: dict[int, list[Any]] = {}
    for result in sorted(results, key=lambda r: r.index):
        grouped.setdefault(au.pass_origin(result.index, units)[0], []).append(result)
    return dict(sorted(grouped.items()))


def _merge(unit: int, passes: list[Any]) -> UnitPasses:
    """The unit's passes (results) read and merged."""
    sums: dict[int, UnitPasses] = {}
    for result in passes:
        merge_pass(sums, unit, read_tile(result.tile_path))
    return sums[unit]


def _merged_source(unit: int, passes: list[Any]) -> TileSource:
    first = tile_source(passes[0].tile_path)
    # A spill pass's merged tile keeps its weight, by which composition adds it up (UnitPasses.tile).
    channels = first.channels if first.meta.get("spill") else tuple(c for c in first.channels if c != WEIGHT)
    return TileSource(first.rect, first.core, channels, lambda: _merge(unit, passes).tile({"unit_index": unit}),
                      {"unit_index": unit})


def write_verdicts(job_dir: Path, settled: au.PassesSettled) -> None:
    data = {"reason": settled.reason, "verdicts": {str(k): v for k, v in settled.verdicts.items()}}
    written_atomically(job_dir / VERDICTS_FILE, lambda tmp: tmp.write_text(json.dumps(data)), "JSON")


def read_verdicts(job_dir: Path) -> tuple[str | None, dict[int, str]]:
    """(why the passes ended, each unit's verdict), or (None, {}) where they were not written."""
    path = job_dir / VERDICTS_FILE
    if not path.is_file():
        return None, {}
    data = json.loads(path.read_text())
    return data["reason"], {int(k): v for k, v in data["verdicts"].items()}
