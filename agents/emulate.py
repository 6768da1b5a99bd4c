"""An emulated render agent (`quekaro agent --emulate COSTS.json`): the real agent, with its render slept,
so that the real protocol runs at 64 agents on one 2-core machine, where 64 Mitsuba processes would neither
fit nor render at their own speed. `Emulation` swaps two things into `agents.render_agent.RenderAgent`: the
render process (`EmulatedWorker`: sleeps each unit's time from a `CostMap`, then writes a real tile) and the
speed measurement (`Emulation.measure_speed`). Mitsuba and Dr.Jit are never imported on this path
(tests/test_emulate.py checks `sys.modules`).
"""

from __future__ import annotations

import base64
import json
import logging
import os
import sys
import threading
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np

from agents.speed import MIN_SPEED, RAYS_PER_SPEED_UNIT, REF_RAYS_PER_SAMPLE, REF_RES, REF_SPP, SpeedSample
from core.errors import QuekaroError, RenderError
from core.image.passes import WEIGHT
from core.image.tiles import RGB, Tile
from core.model.geometry import Rect
from core.render.process import RenderRequest

log = logging.getLogger(__name__)

COSTS_FORMAT = "quekaro-costs/1"
MARK = "EMULATED"  # starts every log line of an emulated agent (render_agent.main) and its tiles' rules
MAX_STANZAS = 200_000  # (time, direction, performative) kept for the summary


class CostMap:
    """A measured per-pixel cost map: what one sample of each pixel takes on an agent of speed 1.

    COSTS.json (format "quekaro-costs/1"; `from_file`, `write`):
      seconds_per_sample  a grid over the image (an entry per pixel, or per cell): nested lists (rows), or
                          {"encoding": "float32-base64", "shape": [rows, cols], "data": ...}
      fixed_s             the seconds of one render call beyond its samples
      speed               the mega-rays/s an agent of `--speed 1` registers (default: one "ray" per pixel
                          sample, as the master's costs at level off)
      channels            the film's channels (default R, G, B)
      width, height       the image it was measured at: a job of another size maps its windows onto the grid
    """

    def __init__(self, grid: np.ndarray, fixed_s: float = 0.0, speed: float | None = None,
                 channels: tuple[str, ...] = RGB, width: int | None = None, height: int | None = None,
                 info: dict[str, Any] | None = None) -> None:
        grid = np.asarray(grid, dtype=np.float64)
        if grid.ndim != 2 or grid.size == 0 or not np.isfinite(grid).all() or (grid < 0).any():
            raise QuekaroError(f"cost map: seconds_per_sample must be a 2-D grid of seconds >= 0, got {grid.shape}")
        self.grid, self.fixed_s = grid, max(float(fixed_s), 0.0)
        self.channels = tuple(channels)
        self.height, self.width = int(height or grid.shape[0]), int(width or grid.shape[1])
        # Level off's costs are pixels (one "ray" per sample): this speed makes such bids exact.
        self.speed = float(speed) if speed else 1.0 / max(float(grid.mean()), 1e-12) / RAYS_PER_SPEED_UNIT
        self.info = dict(info or {})
        sat = np.zeros((grid.shape[0] + 1, grid.shape[1] + 1))
        sat[1:, 1:] = grid.cumsum(0).cumsum(1)
        self._sat = sat  # summed-area table: exact sums over fractional rectangles of the grid

    @classmethod
    def from_file(cls, path: str | Path) -> CostMap:
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise QuekaroError(f"--emulate {path}: cannot read the cost map ({exc})") from exc
        if data.get("format") != COSTS_FORMAT:
            raise QuekaroError(f"--emulate {path}: format {data.get('format')!r}, expected {COSTS_FORMAT!r}")
        try:
            return cls(_decode(data["seconds_per_sample"]), data.get("fixed_s", 0.0), data.get("speed"),
                       tuple(data.get("channels") or RGB), data.get("width"), data.get("height"),
                       data.get("measured"))
        except QuekaroError as exc:
            raise QuekaroError(f"--emulate {path}: {exc}") from exc
        except (KeyError, TypeError, ValueError) as exc:
            raise QuekaroError(f"--emulate {path}: bad cost map ({type(exc).__name__}: {exc})") from exc

    def to_dict(self) -> dict[str, Any]:
        grid = np.ascontiguousarray(self.grid, dtype=np.float32)
        return {"format": COSTS_FORMAT, "width": self.width, "height": self.height, "fixed_s": self.fixed_s,
                "speed": self.speed, "channels": list(self.channels), "measured": self.info,
                "seconds_per_sample": {"encoding": "float32-base64", "shape": list(grid.shape),
                                       "data": base64.b64encode(grid.tobytes()).decode()}}

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(json.dumps(self.to_dict(), default=str))
        return path

    def sample_seconds(self, window: Rect, width: int, height: int) -> float:
        """Seconds of one sample of every pixel of `window` in a width x height image."""
        rows, cols = self.grid.shape
        sx, sy = cols / width, rows / height
        x0, x1, y0, y1 = window.x * sx, window.x1 * sx, window.y * sy, window.y1 * sy
        s = self._sat_at(y1, x1) - self._sat_at(y0, x1) - self._sat_at(y1, x0) + self._sat_at(y0, x0)
        return max(float(s), 0.0) / (sx * sy)  # each grid cell stands for 1 / (sx sy) image pixels

    def seconds(self, window: Rect, spp: int, width: int, height: int, speed: float = 1.0) -> float:
        """What rendering `window` at `spp` takes on an agent of `speed` (1: the map's own):
        (fixed_s + spp x the seconds per sample summed over the window) / speed. The window is the unit's,
        grown by the band its rules chose (as bench.scaling.TimeMap.unit_seconds)."""
        return (self.fixed_s + max(int(spp), 1) * self.sample_seconds(window, width, height)) / max(speed, 1e-9)

    def _sat_at(self, y: float, x: float) -> float:
        """The summed-area table at a fractional point: bilinear, exact for a grid of constant cells."""
        rows, cols = self.grid.shape
        y, x = min(max(y, 0.0), rows), min(max(x, 0.0), cols)
        iy, ix = min(int(y), rows - 1), min(int(x), cols - 1)
        fy, fx = y - iy, x - ix
        s = self._sat
        return float((1 - fy) * ((1 - fx) * s[iy, ix] + fx * s[iy, ix + 1])
                     + fy * ((1 - fx) * s[iy + 1, ix] + fx * s[iy + 1, ix + 1]))


def _decode(raw: Any) -> np.ndarray:
    if isinstance(raw, dict):
        if raw.get("encoding") != "float32-base64":
            raise ValueError(f"unknown encoding {raw.get('encoding')!r}")
        return np.frombuffer(base64.b64decode(raw["data"]), dtype=np.float32).reshape(raw["shape"])
    return np.asarray(raw, dtype=np.float64)


class EmulatedWorker:
    """Stands in for `core.render.process.RenderProcess`: `render(request, timeout)` sleeps the unit's time from
    the cost map, then returns a real tile of the unit's window (the film's channel count, a real tile's
    header fields plus `"emulated": true`). Renders one unit at a time (an emulated agent renders no batches:
    agents.render_agent gives its state machine batches of one)."""

    def __init__(self, emulation: Emulation) -> None:
        self.emulation = emulation
        self.starts = 0
        self._lock = threading.Lock()

    def start(self) -> None:
        self.starts += 1

    def interrupt(self) -> None:
        """Nothing to kill: a render sleeps on its `abort` event, whose setting ends it (RenderProcess's)."""

    def stop(self) -> None:
        self.emulation.finish()

    def alive(self) -> bool:
        return True

    def render(self, job: RenderRequest, timeout: float | None = None, abort: threading.Event | None = None) -> Tile:
        emu = self.emulation
        abort = abort or threading.Event()
        window = job.window
        sampled = job.unit if job.spill else window  # a spilling pass draws its samples on its unit alone
        planned = emu.costs.seconds(sampled, job.spp, job.width, job.height, emu.factor)
        with self._lock:
            start = time.perf_counter()
            if timeout is not None and planned > timeout and not abort.wait(timeout):
                raise RenderError(f"unit {job.unit_index} {job.unit.as_list()}: timed out after {timeout:.1f} s "
                                  f"(emulated render of {planned:.1f} s)")
            if abort.wait(planned):
                raise RenderError(f"unit {job.unit_index} {job.unit.as_list()}: interrupted (emulated)")
            seconds = time.perf_counter() - start
        rendered_at = time.time()  # the render's end on the wall clock: bench.hosts times the delivery from it
        rng = np.random.default_rng(job.seed)
        # A grey with noise: constant pixels would compress to nothing, and uploads would be unlike a render's.
        pixels = rng.random((window.h, window.w, len(emu.costs.channels)), dtype=np.float32) * np.float32(0.36)
        meta = {"job_id": job.job_id, "unit_index": job.unit_index, "seconds": seconds, "load_seconds": 0.0,
                "nonfinite": 0, "spp": job.spp, "depth": job.max_depth, "integrator": job.integrator,
                "variant": "emulated", "seed": job.seed, "band": job.band, "window_method": "emulated",
                "pid": os.getpid(), "sensor": job.sensor, "emulated": True, "emulated_speed": emu.factor,
                "rendered_at": rendered_at, **({"first_spp": job.first} if job.first is not None else {})}
        log.info("%s render of %s/%d: window %dx%d, %d spp, slept %.3f s (planned %.3f s)", MARK, job.job_id,
                 job.unit_index, window.w, window.h, job.spp, seconds, planned)
        channels = emu.costs.channels
        if job.pass_index is not None:  # a progressive job's pass: the film's weights, one sample a pixel each
            pixels = np.concatenate([pixels, np.full((*pixels.shape[:2], 1), job.spp, np.float32)], axis=-1)
            channels = (*channels, WEIGHT)
            meta["pass"] = job.pass_index
        if job.spill:
            meta["spill"] = True
        return Tile(pixels, window, job.unit, meta, channels)


class Emulation:
    """What `--emulate COSTS.json --speed F` swaps into a render agent: its worker, its speed, and a count of
    the stanzas it sends and receives (by performative, with times)."""

    def __init__(self, costs: CostMap, factor: float = 1.0, workdir: Path | None = None) -> None:
        if not factor > 0:
            raise QuekaroError(f"--speed {factor}: must be above 0")
        self.costs, self.factor, self.workdir = costs, float(factor), workdir
        self.worker = EmulatedWorker(self)
        self.stanzas: list[tuple[float, str, str]] = []
        self.counts: Counter[str] = Counter()
        self._finished = False

    @classmethod
    def load(cls, path: str | Path, factor: float = 1.0, workdir: Path | None = None) -> Emulation:
        return cls(CostMap.from_file(path), factor, workdir)

    def measure_speed(self, _worker: Any = None, _threads: int | None = None) -> SpeedSample:
        """The speed a real agent measured where the map was made, times the factor (`--speed`); no reference
        render."""
        speed = max(self.costs.speed * self.factor, MIN_SPEED)
        samples = REF_RES * REF_RES * REF_SPP
        seconds = samples * REF_RAYS_PER_SAMPLE / (speed * RAYS_PER_SPEED_UNIT)
        return SpeedSample(speed, seconds, samples / seconds, "emulated", 0.0)

    def mark(self, meta: dict[str, Any]) -> dict[str, Any]:
        """A tile's header fields as the report shows them: `emulated`, and the rules named EMULATED."""
        return {**meta, "emulated": True, "rules": f"{MARK} {meta.get('rules') or ''}".strip()}

    def watch(self, farm: Any, handler: Callable[[Any], Awaitable[None]]) -> None:
        """Count the stanzas `farm` (a core.transport.xmpp.FarmAgent) sends, and those its handler receives."""
        send = farm.send

        async def counted_send(to: str, performative: str, body: str, **kw: Any) -> bool:
            self._count("out", performative)
            return await send(to, performative, body, **kw)

        async def counted_handler(env: Any) -> None:
            self._count("in", env.performative)
            await handler(env)

        farm.send = counted_send
        farm.set_handler(counted_handler)

    def _count(self, direction: str, performative: str) -> None:
        self.counts[f"{direction} {performative}"] += 1
        if len(self.stanzas) < MAX_STANZAS:
            self.stanzas.append((time.time(), direction, performative))

    def finish(self) -> None:
        """Log and write (WORKDIR/emulation.json) what was counted; once."""
        if self._finished:
            return
        self._finished = True
        heavy = sorted(m for m in ("mitsuba", "drjit") if m in sys.modules)
        summary = {"speed_factor": self.factor, "counts": dict(self.counts), "stanzas": self.stanzas,
                   "heavy_modules": heavy, "pid": os.getpid()}
        log.info("%s agent stops: stanzas %s; mitsuba/drjit loaded: %s", MARK,
                 ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items())) or "none", heavy or "no")
        if self.workdir is not None:
            try:
                self.workdir.mkdir(parents=True, exist_ok=True)
                (self.workdir / "emulation.json").write_text(json.dumps(summary))
            except OSError as exc:
                log.warning("%s: cannot write %s/emulation.json: %s", MARK, self.workdir, exc)
