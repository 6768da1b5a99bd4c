"""A progressive job's passes merged on the master (core.image.passes): as each pass's tile lands, into its
unit's running sums, whose noise estimate the auction decides on (`PassMerger`); at assembly, every
stored pass again, into one tile per unit (`merged_units`); for the page's live image, one source per unit
that merges its passes so far when it is composed (`merged_sources`); and the passes' verdicts.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from core.files import written_atomically
from core.image.compose import TileSource
from core.image.passes import WEIGHT, UnitPasses, merge_pass
from core.image.tiles import Tile, read_tile, tile_source
from master import auction as au

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
    sums: dict[int, UnitPasses] = {}
    params: dict[int, dict[str, Any]] = {}
    agents: dict[int, set[str]] = {}
    for result in sorted(results, key=lambda r: r.index):
        unit, _ = au.pass_origin(result.index, units)
        merge_pass(sums, unit, read_tile(result.tile_path))
        params.setdefault(unit, dict(result.params))
        agents.setdefault(unit, set()).add(str(result.params.get("agent")))
    tiles, lines = [], {}
    for unit, passes in sorted(sums.items()):
        tiles.append(passes.tile({"unit_index": unit, "seconds": passes.seconds, "window_method": "passes"}))
        lines[unit] = {**params[unit], **passes.account(), "verdict": verdicts.get(unit),
                       "agent": ", ".join(sorted(agents[unit]))}
    return tiles, lines


def merged_sources(results: Iterable[Any], units: int) -> list[TileSource]:
    """One tile source per unit of the stored passes (the store's results: index, tile_path), which merges
    that unit's passes when composition loads it: a unit's pixels are all its samples so far, and the
    passes are read one unit at a time."""
    paths: dict[int, list[str]] = {}
    for result in sorted(results, key=lambda r: r.index):
        if Path(result.tile_path).is_file():
            paths.setdefault(au.pass_origin(result.index, units)[0], []).append(result.tile_path)
    return [_merged_source(unit, files) for unit, files in sorted(paths.items())]


def _merged_source(unit: int, files: list[str]) -> TileSource:
    first = tile_source(files[0])

    def load() -> Tile:
        sums: dict[int, UnitPasses] = {}
        for path in files:
            merge_pass(sums, unit, read_tile(path))
        return sums[unit].tile({"unit_index": unit})

    channels = tuple(c for c in first.channels if c != WEIGHT)
    return TileSource(first.rect, first.core, channels, load, {"unit_index": unit})


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
