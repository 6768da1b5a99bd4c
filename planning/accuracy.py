"""What a job's accuracy cost: its image against a long plain-Mitsuba reference (`reference`), and against
plain Mitsuba at the uniform spp that takes the same wall time (`uniform_at`, on `spp_timing`'s line).
`accuracy_report` is `quekaro render --report-accuracy`; the benchmark `quekaro bench accuracy` builds on it.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import QuekaroError
from core.image.imageio import read_image, write_exr
from core.image.metrics import all_metrics
from core.image.seams import seam_measure
from core.model.geometry import Rect
from core.model.hashing import sha256_file
from core.model.job import SceneSpec
from core.scene.bundle import scene_members
from core.scene.effects import analyse

REF_SPP = 1024


def job_variant(spec: SceneSpec) -> str:
    """The variant a job of this scene renders in when the user names none (core.scene.effects)."""
    return analyse(spec).variant


@dataclass(frozen=True)
class Asked:
    """What a job was asked to compute beyond its scene file: the sensor (Mitsuba's -s) and the user's
    integrator type and max_depth (None: the scene's own). Plain Mitsuba renders the same, or the
    comparison would count the user's choice as the job's error."""

    sensor: int = 0
    integrator: str | None = None
    depth: int | None = None

    @classmethod
    def of_report(cls, report: dict[str, Any]) -> Asked:
        options = report.get("options") or {}
        depth = options.get("depth")
        return cls(int(options.get("sensor") or 0), options.get("integrator"), None if depth is None else int(depth))

    def args(self) -> list[str]:
        """planning.plain's options for it."""
        return [*(["-s", str(self.sensor)] if self.sensor else []),
                *(["--integrator", self.integrator] if self.integrator else []),
                *(["--depth", str(self.depth)] if self.depth is not None else [])]

    def options(self) -> dict[str, Any]:
        """A job's options for it (those that differ from the scene as written)."""
        return {k: v for k, v in (("sensor", self.sensor), ("integrator", self.integrator), ("depth", self.depth))
                if v != getattr(Asked(), k)}

    def key(self) -> list[Any]:
        """What a cached render depends on (nothing for the scene as written, so older caches hold)."""
        return [] if self == Asked() else [self.sensor, self.integrator, self.depth]


def plain_render(spec: Any, spp: int, threads: int, variant: str, seed: int = 0,
                 asked: Asked = Asked()) -> tuple[np.ndarray, float]:
    """Plain Mitsuba on the whole image at `spp` in `variant`, computing what `asked` says, with the scene's
    -D parameters and search folders, as a user runs it: the whole process timed (`python -m planning.plain`:
    import, load, render, write). Returns (RGB pixels, wall seconds)."""
    with tempfile.TemporaryDirectory(prefix="quekaro-plain-") as tmp:
        out = Path(tmp) / "plain.exr"
        cmd = [sys.executable, "-m", "planning.plain", str(spec.path), "--spp", str(spp), "--seed", str(seed),
               "-t", str(threads), "-m", variant, "-o", str(out), *asked.args(),
               *(f"-D{k}={v}" for k, v in spec.defines.items()),
               *(arg for folder in spec.search_paths for arg in ("-a", str(folder)))]
        start = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=Path.cwd())
        seconds = time.perf_counter() - start
        if done.returncode != 0:
            raise QuekaroError(f"plain Mitsuba on {spec.path} failed: {done.stderr.strip()[-600:]}")
        return read_image(out)[..., :3], seconds


def content_key(spec: Any, *extra: Any) -> str:
    """A hash of every file the scene reads (the scene as rewritten with its -D parameters, meshes,
    textures, includes) and `extra`: what a cached render of it depends on."""
    digest = hashlib.sha256(json.dumps([sorted(spec.defines.items()), *extra], default=str).encode())
    for name, content in sorted(scene_members(spec.path, spec.defines, tuple(spec.search_paths)).items()):
        digest.update(name.encode())
        digest.update(content if isinstance(content, bytes) else sha256_file(content).encode())
    return digest.hexdigest()[:16]


def reference_path(spec: Any, spp: int, cache: Path, variant: str, asked: Asked = Asked()) -> Path:
    """Where `reference` caches the scene's reference: named by content (`content_key`)."""
    return cache / "references" / f"{spec.path.stem}-{content_key(spec, spp, variant, *asked.key())}.exr"


def reference(spec: Any, spp: int, threads: int, cache: Path, variant: str, asked: Asked = Asked()) -> np.ndarray:
    """The scene at `spp` in `variant`, plain Mitsuba computing what `asked` says; cached under `cache` by
    content (`reference_path`)."""
    path = reference_path(spec, spp, cache, variant, asked)
    if path.exists():
        return read_image(path)[..., :3]
    pixels, _ = plain_render(spec, spp, threads, variant, seed=987654, asked=asked)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_exr(path, pixels)
    return pixels


#: The sample count's share of a render's time must exceed this (and MIN_SPP_SECONDS) before the line
#: t0 + k spp is trusted: below it, the two timings differ by noise and k could be ~0, which made the
#: uniform baseline ask Mitsuba for billions of samples on a 32 px image.
MIN_SPP_SHARE = 0.5
MIN_SPP_SECONDS = 0.02
MAX_TIMING_SPP = 1 << 14


def spp_timing(spec: Any, spp: int, threads: int, variant: str, asked: Asked = Asked()) -> tuple[float, float]:
    """(t0, k) of t(spp) = t0 + k spp for the plain Mitsuba process (`fit_spp_line`). Render time is linear
    in spp (docs/design.md section 3), so the spp for a given time follows from the line."""
    size = ", ".join(f"{k}={v}" for k, v in spec.defines.items())
    seeds = itertools.count(1)
    return fit_spp_line(lambda n: plain_render(spec, n, threads, variant, seed=next(seeds), asked=asked)[1],
                        spp, what=f"{spec.path.name} ({size})")


#: How far one step may raise the high spp of `fit_spp_line`: at least 4x, at most 16x its span.
GROWTH_STEPS = (4, 16)


def fit_spp_line(seconds_at: Callable[[int], float], spp: int, what: str = "the scene") -> tuple[float, float]:
    """(t0, k) through the faster of two timings at each of two spp. The higher spp grows until samples
    cost a measurable share of its time (MIN_SPP_SHARE of t0, at least MIN_SPP_SECONDS): each step by
    how far the last one fell short (GROWTH_STEPS), one timing a step, the second only near the goal.
    QuekaroError past MAX_TIMING_SPP."""
    lo = max(1, spp // 4)
    t_lo = min(seconds_at(lo), seconds_at(lo))
    needed = max(MIN_SPP_SECONDS, MIN_SPP_SHARE * t_lo)
    hi = max(spp, lo + 1)
    while True:
        t_hi = seconds_at(hi)
        if t_hi - t_lo >= needed / 2:
            t_hi = min(t_hi, seconds_at(hi))
            if t_hi - t_lo >= needed:
                k = (t_hi - t_lo) / (hi - lo)
                return max(t_lo - k * lo, 0.0), k
        if hi >= MAX_TIMING_SPP:
            raise QuekaroError(
                f"{what}: a render at {hi} spp took {t_hi:.3f} s against {t_lo:.3f} s at {lo} spp; the cost "
                f"of a sample is too small to time, so no uniform spp can be matched to a cell's time "
                f"(a larger image: `quekaro bench accuracy --res`, or the scene's film size)")
        hi = min(MAX_TIMING_SPP, lo + round((hi - lo) * _growth(t_hi - t_lo, needed)))


def _growth(grown: float, needed: float) -> float:
    """The factor for the high spp's span: twice the goal over what the last span grew, within GROWTH_STEPS."""
    low, high = GROWTH_STEPS
    return min(high, max(low, 2 * needed / max(grown, 1e-9)))


def default_cache() -> Path:
    """$XDG_CACHE_HOME/quekaro, else ~/.cache/quekaro: where references and the benches' measurements
    are kept."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "quekaro"


def uniform_at(spec: SceneSpec, seconds: float, line: tuple[float, float], threads: int, ref: np.ndarray,
               variant: str, seed: int = 4242, asked: Asked = Asked()) -> dict[str, Any]:
    """Plain Mitsuba at the spp whose whole-process time, by the line, is `seconds`: spp, its measured
    seconds and its errors against `ref`."""
    t0, k = line
    spp = max(1, round((seconds - t0) / k))
    pixels, took = plain_render(spec, spp, threads, variant, seed=seed + spp, asked=asked)
    return {"spp": spp, "seconds": took, **all_metrics(pixels, ref)}


def accuracy_report(spec: SceneSpec, image: np.ndarray, wall_seconds: float, report: dict[str, Any],
                    threads: int, ref_spp: int = REF_SPP, cache: Path | None = None) -> dict[str, Any]:
    """The job's image (RGB first) against the reference, its seams at the units' borders, and the
    uniform baseline at equal wall time, computing what the job was asked to (its sensor, the user's
    integrator and depth). Plain Mitsuba renders in the job's variant (the effect analysis's, or the
    user's `-m`): a spectral scene against an rgb reference would count the variant's difference as error."""
    variant, asked = report["effects"]["variant"], Asked.of_report(report)
    ref = reference(spec, ref_spp, threads, cache or default_cache(), variant, asked)
    rgb = np.asarray(image[..., :3], dtype=np.float32)
    rects = [Rect.from_list(u["rect"]) for u in report["units"]]
    line = spp_timing(spec, max(1, int(report.get("spp") or 16)), threads, variant, asked)
    uniform = uniform_at(spec, wall_seconds, line, threads, ref, variant, asked=asked)
    width, height = report["image"]["width"], report["image"]["height"]
    compared = max(uniform["spp"], report["totals"]["samples"] / (width * height))
    return {"reference_spp": ref_spp, "variant": variant, "seconds": wall_seconds, **all_metrics(rgb, ref),
            "seams": seam_measure(rgb, ref, rects).to_dict(), "uniform": uniform,
            "line": {"t0": line[0], "k": line[1]}, "reference_warning": reference_warning(ref_spp, compared)}


# The reference's own noise enters every error measured against it: with REF_FACTOR times the samples of
# what it is compared with, it adds at most 1/REF_FACTOR to their relMSE (and pulls their ratio towards 1).
REF_FACTOR = 4


def reference_warning(ref_spp: int, compared_spp: float) -> str | None:
    """Why the reference is too noisy for images of `compared_spp` samples per pixel, or None."""
    if ref_spp >= REF_FACTOR * compared_spp:
        return None
    return (f"the reference ({ref_spp} spp) has under {REF_FACTOR}x the samples of an image compared with it "
            f"({compared_spp:.0f} spp): its own noise is in both errors and pulls their ratio towards 1; "
            f"give --ref-spp {REF_FACTOR * math.ceil(compared_spp)} or more")
