"""`quekaro bench denoise`: what the denoiser (core.image.denoise) gains, what it costs a job, and whether a
per-unit blend of it with the raw image gains more. Four parts (`--parts`), in one process:

- filters: per scene, references at `--ref-spp` with the scene's own filter and with a box one; at each
  `--spp` the colour and the AOV pass under each filter, raw and denoised, scored by relMSE and FLIP against
  the reference of the same filter (and the box-filtered denoised image against the scene's own reference).
- cost: real `quekaro render --denoise` jobs at `--cost-res` and `--cost-spp`, as a user runs them: their
  reports' AOV pass and denoise seconds over the job's (the target, `COST_TARGET`); then, at the same size,
  each AOV spp's pass (warm, in a render process) and each OIDN quality's denoise (a fresh process, as a job
  pays it).
- settings: each AOV spp and quality, the denoised relMSE and FLIP at `--res` and `--compare-spp` against
  the box reference, over the best setting's (the first of each list); `TOLERANCE` says which keep the image.
- blend: the experiment of issue 64: per unit, how much raw image to keep, by a monotone rule of the unit's
  C and Nd (`unit_scores`, `raw_weights`), feathered across unit borders, against one global denoise.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.args import check_minimums
from bench.report import DEFAULT_OUT, command_of, publish_markdown
from bench.scaling import default_cache_dir
from bench.suite import SUITE, SuiteScene, scene_from_argument
from core.errors import QuekaroError
from core.image.denoise import (
    ALBEDO,
    AOV_SPP,
    AOVS,
    DENOISER_FILTER,
    NORMAL,
    QUALITIES,
    QUALITY,
    denoise,
)
from core.image.film import film_channels, sanitize
from core.image.metrics import flip, relmse
from core.model.job import RenderOptions, SceneSpec
from core.model.units import WorkUnit
from core.render.process import RenderProcess, aovs_alone
from core.scene.scene import film_info, load
from planning.accuracy import content_key, job_variant
from planning.jobplan import plan_job
from planning.pipeline import UNIT_TIMEOUT_S, aov_job, plan_for_units_here

OWN = "own"  # the scene's own reconstruction filter
PARTS = ("filters", "cost", "settings", "blend")
COST_TARGET = 0.05  # issue 64: the AOV pass and the denoise together, of a 512 px, 64 spp job's time
SHARE_TIE = 0.005  # estimated shares closer than this are a tie (the timings' noise): the better setting is chosen
# A setting keeps the image when, against the best one's, the suite medians of its denoised FLIP and relMSE
# rise by at most 1 % and 3 % and no scene's FLIP by more than 3 % (another AOV seed moves them ~0.5 %).
TOLERANCE = {"flip": 1.01, "relmse": 1.03, "worst_flip": 1.03}
BLEND_SPREAD = 3.0  # a unit's raw weight: strength ** (1 + BLEND_SPREAD * (1 - its score))
FEATHER = 32  # weights blurred over a box of (image width / FEATHER) pixels each side
WIN_MARGIN = 0.01  # the blend wins where its median FLIP is this far under the global denoise's
COLOUR_SEED, AOV_SEED, CONTROL_SEED = 1, 3, 5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenes", nargs="*", help="suite names or scene files (default: the whole suite)")
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma list of {', '.join(PARTS)}")
    parser.add_argument("--res", type=int, default=128, help="image width (each scene keeps its aspect)")
    parser.add_argument("--spp", default="4,16,64", help="filters: comma list of samples per pixel")
    parser.add_argument("--ref-spp", type=int, default=4096)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cost-res", type=int, default=512, help="cost: the jobs' image width")
    parser.add_argument("--cost-spp", type=int, default=64, help="cost: the jobs' samples per pixel")
    parser.add_argument("--cost-runs", type=int, default=2, help="cost: timed jobs per scene, after one unscored")
    parser.add_argument("--aov-spp", default="16,8,4,2,1", help="cost, settings: AOV pass spp, best first")
    parser.add_argument("--qualities", default=",".join(QUALITIES), help="cost, settings: OIDN qualities")
    parser.add_argument("--compare-spp", default="16,64", help="settings, blend: the colour's spp")
    parser.add_argument("--strengths", default="0.1,0.25,0.5", help="blend: strengths between 0 and 1")
    parser.add_argument("--blend-level", default="N", help="blend: the rule level whose plan gives the units")
    parser.add_argument("--cache-dir", type=Path, default=default_cache_dir())
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT / "denoise", help="folder for denoise.md")


def _ints(text: str) -> list[int]:
    return [int(s) for s in str(text).split(",")]


def _parsed(args: argparse.Namespace) -> None:
    """The comma lists as lists, refused where they name an unknown part or quality."""
    check_minimums(args, res=1, ref_spp=1, threads=1, cost_res=1, cost_spp=1, cost_runs=1)
    args.part_list = str(args.parts).split(",")
    args.quality_list = str(args.qualities).split(",")
    args.spp_list, args.aov_list, args.compare_list = _ints(args.spp), _ints(args.aov_spp), _ints(args.compare_spp)
    args.strength_list = [float(s) for s in str(args.strengths).split(",")]
    for name, given, known in (("--parts", args.part_list, PARTS), ("--qualities", args.quality_list, QUALITIES)):
        if set(given) - set(known):
            raise QuekaroError(f"{name} {','.join(given)}: expected some of {', '.join(known)}")
    if not all(0.0 <= s <= 1.0 for s in args.strength_list):
        raise QuekaroError(f"--strengths {args.strengths}: each between 0 and 1")


def run(args: argparse.Namespace) -> dict[str, Any]:
    _parsed(args)
    chosen = [scene_from_argument(s) for s in args.scenes] if args.scenes else list(SUITE)
    result: dict[str, Any] = {"res": args.res, "spp": args.spp_list, "ref_spp": args.ref_spp,
                              "parts": args.part_list, "load": [os.getloadavg()[0]]}
    if "filters" in args.part_list:
        result["scenes"] = {e.name: {"role": e.role, **measure_scene(_spec(e, args.res), args)} for e in chosen}
        result["summary"] = summary(result["scenes"], args.spp_list)
    if "cost" in args.part_list:
        result["cost"] = measure_cost(chosen, args)
    if {"settings", "blend"} & set(args.part_list):
        settings, blends = {}, {}
        for entry in chosen:  # one scene at a time: the next may load in another variant
            box = BoxScene.make(entry, args)
            if "settings" in args.part_list:
                settings[entry.name] = measure_settings(box, args)
            if "blend" in args.part_list:
                blends[entry.name] = measure_blend(box, args)
        if settings:
            result["settings"] = settings_summary(settings, result.get("cost"), args)
        if blends:
            result["blend"] = blend_summary(blends, args)
    result["load"].append(os.getloadavg()[0])
    result["report"] = str(publish_markdown(args.out, "denoise", "The denoiser: its gain, its cost, a blend by rules",
                                            command_of(args, "quekaro bench denoise"), format_report(result),
                                            show=not args.json))
    return result


def _spec(entry: SuiteScene, res: int, rfilter: str | None = None) -> SceneSpec:
    return SceneSpec(entry.path.resolve(), entry.with_size(res), rfilter=rfilter)


# ---- filters: the scene's own against a box one ---------------------------------------------------------


def render(loaded: Any, spp: int, seed: int, aovs: bool) -> tuple[dict[str, np.ndarray], float]:
    """The loaded scene at `spp`: its colour, or with `aovs` the denoiser's pass alone (albedo, normal), and the
    seconds the render took, readback included."""
    import mitsuba as mi

    start = time.perf_counter()
    mi.render(loaded, spp=spp, seed=seed, integrator=aovs_alone(AOVS) if aovs else None)
    pixels, channels = film_channels(loaded.sensors()[0].film())
    pixels = sanitize(pixels)[0]
    index = {n: i for i, n in enumerate(channels)}
    out = {"albedo": pixels[..., [index[c] for c in ALBEDO]], "normal": pixels[..., [index[c] for c in NORMAL]]} \
        if aovs else {"colour": pixels[..., :3]}
    return out, time.perf_counter() - start


def refiltered(image: np.ndarray, stddev: float) -> np.ndarray:
    """The (H x W x 3) image convolved with Mitsuba's gaussian filter at pixel offsets (exp(-x^2 / 2s^2) less
    its value at the radius 4s, edges repeated): a box-filtered image brought towards the scene's own look."""
    reach = 4.0 * stddev
    offsets = np.arange(-int(np.ceil(reach)), int(np.ceil(reach)) + 1)
    weights = np.clip(np.exp(-offsets**2 / (2 * stddev**2)) - np.exp(-reach**2 / (2 * stddev**2)), 0.0, None)
    weights /= weights.sum()
    out = image.astype(np.float64)
    for axis in (0, 1):
        pad = [(0, 0)] * 3
        pad[axis] = (len(offsets) // 2, len(offsets) // 2)
        padded = np.pad(out, pad, mode="edge")
        out = sum(w * np.take(padded, np.arange(i, i + image.shape[axis]), axis=axis) for i, w in enumerate(weights))
    return out.astype(np.float32)


def cached_reference(spec: SceneSpec, loaded: Any, spp: int, variant: str, cache: Path) -> np.ndarray:
    """The scene at `spp` with its spec's filter, cached by content and filter."""
    path = cache / "denoise" / f"{spec.path.stem}-{content_key(spec, spp, variant, spec.rfilter)}.npy"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, render(loaded, spp, 987654, aovs=False)[0]["colour"])
    return np.load(path)


def measure_scene(spec: SceneSpec, args: argparse.Namespace) -> dict[str, Any]:
    """One scene's rows: per filter and spp, raw and denoised errors and the times."""
    variant = job_variant(spec)
    info = film_info(spec)
    stddev = info.filter_radius / 4.0 if info.filter_type == "gaussian" else None
    rows, references = [], {}
    for name in (OWN, DENOISER_FILTER):
        filtered = dataclasses.replace(spec, rfilter=None if name == OWN else name)
        loaded = load(filtered, variant, threads=args.threads)
        references[name] = cached_reference(filtered, loaded, args.ref_spp, variant, args.cache_dir)
        render(loaded, AOV_SPP, 0, aovs=True)  # each render's kernel compiled (the spp is in it) before it is timed
        aux, aov_s = render(loaded, AOV_SPP, AOV_SEED, aovs=True)
        for spp in args.spp_list:
            render(loaded, spp, 0, aovs=False)
            images, seconds = render(loaded, spp, COLOUR_SEED, aovs=False)
            start = time.perf_counter()
            denoised = denoise(images["colour"], aux["albedo"], aux["normal"])
            rows.append({"filter": name, "spp": spp, "render_s": seconds, "aov_share": aov_s / seconds,
                         "denoise_s": time.perf_counter() - start, "raw": images["colour"], "denoised": denoised,
                         "refiltered": refiltered(denoised, stddev) if stddev and name != OWN else None})
    return {"variant": variant, "own_filter": info.filter_type, "rows": [_scored(r, references) for r in rows]}


def _scored(row: dict[str, Any], references: dict[str, np.ndarray]) -> dict[str, Any]:
    ref = references[row["filter"]]
    raw, den, again = row.pop("raw"), row.pop("denoised"), row.pop("refiltered")
    return {**row, "relmse_raw": relmse(raw, ref), "relmse_denoised": relmse(den, ref),
            "flip_raw": flip(raw, ref), "flip_denoised": flip(den, ref),
            "relmse_denoised_vs_own": relmse(den, references[OWN]),
            "relmse_refiltered_vs_own": None if again is None else relmse(again, references[OWN])}


def summary(scenes: dict[str, Any], spps: list[int]) -> dict[str, Any]:
    """Medians over the scenes, per spp: denoised / raw relMSE under each filter, and the box-filtered
    denoised image against the scene's own reference over the raw image with the scene's own filter."""
    out = {}
    for spp in spps:
        rows = {f: [r for s in scenes.values() for r in s["rows"] if r["filter"] == f and r["spp"] == spp]
                for f in (OWN, DENOISER_FILTER)}
        own_raw = [r["relmse_raw"] for r in rows[OWN]]
        out[str(spp)] = {f"{f}_ratio": float(np.median([r["relmse_denoised"] / r["relmse_raw"] for r in rows[f]]))
                         for f in rows} | {
            "box_denoised_over_own_raw": float(np.median([b["relmse_denoised_vs_own"] / o for b, o in
                                                          zip(rows[DENOISER_FILTER], own_raw, strict=True)]))}
    return out


# ---- cost: real jobs, and each setting's parts at their size -------------------------------------------


def measure_cost(entries: list[SuiteScene], args: argparse.Namespace) -> dict[str, Any]:
    """Per scene, `--cost-runs` real denoised jobs (after one unscored: kernels compiled) and each setting's
    parts at the jobs' size; the median share over the scenes against the target."""
    scenes = {}
    with tempfile.TemporaryDirectory(prefix="quekaro-bench-denoise-") as folder:
        for entry in entries:
            runs = [run_job(entry, args, Path(folder)) for _ in range(args.cost_runs + 1)][1:]
            raw = Path(folder) / f"{entry.name}.raw.exr"
            scenes[entry.name] = {"runs": runs, "share": float(np.median([r["share"] for r in runs])),
                                  "aov_s": aov_seconds(entry, args), "denoise_s": {
                                      q: denoise_seconds(raw, q) for q in args.quality_list}}
    share = float(np.median([s["share"] for s in scenes.values()]))
    parts = float(np.median([r["aov_s"] + r["denoise_s"] for s in scenes.values() for r in s["runs"]]))
    return {"res": args.cost_res, "spp": args.cost_spp, "aov_spp": AOV_SPP, "quality": QUALITY, "scenes": scenes,
            "share": share, "met": share <= COST_TARGET, "parts_s": parts,
            "job_s": float(np.median([r["total_s"] for s in scenes.values() for r in s["runs"]]))}


def run_job(entry: SuiteScene, args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    """One `quekaro render --denoise` job of the scene, as a user runs it: its report's seconds."""
    out = folder / f"{entry.name}.exr"
    defines = [a for k, v in entry.with_size(args.cost_res).items() for a in ("-D", f"{k}={v}")]
    command = [sys.executable, "-m", "quekaro", "render", str(entry.path), *defines, "--spp", str(args.cost_spp),
               "--denoise", "-o", str(out), "-t", str(args.threads), "--no-progress"]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, timeout=UNIT_TIMEOUT_S)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise QuekaroError(f"{entry.name}: quekaro render --denoise failed: {done.stderr.strip()[-500:]}")
    report = json.loads(out.with_suffix(".json").read_text())
    aov, den, total = (report["render_calls"]["aov_pass_seconds"], report["denoise"]["seconds"],
                       report["totals"]["seconds"])
    return {"aov_s": aov, "denoise_s": den, "total_s": total, "wall_s": wall, "share": (aov + den) / total,
            "size": [report["image"]["width"], report["image"]["height"]]}


def aov_seconds(entry: SuiteScene, args: argparse.Namespace) -> dict[str, float]:
    """Seconds of the AOV pass at each `--aov-spp`, rendered as a denoised job renders it (its render order, in
    a render process, the tile back in this one), each spp's kernel compiled before it is timed."""
    options = RenderOptions(spp=args.cost_spp, threads=args.threads, denoise=True)
    with RenderProcess() as worker:
        plan = worker.call(plan_for_units_here, _spec(entry, args.cost_res), options, 0, doing="planning",
                           timeout=UNIT_TIMEOUT_S)
        out = {}
        for spp in args.aov_list:
            request = dataclasses.replace(aov_job(plan, "bench", args.threads), spp=spp)
            worker.render(request, UNIT_TIMEOUT_S)
            start = time.perf_counter()
            worker.render(request, UNIT_TIMEOUT_S)
            out[str(spp)] = time.perf_counter() - start
    return out


_DENOISE_TIMED = """
import json, sys, time
import numpy as np
from core.image.denoise import DENOISER_CHANNELS, denoise_planar
from core.image.imageio import read_image_channels
pixels, names = read_image_channels(sys.argv[1])
index = {n: i for i, n in enumerate(names)}
planar = np.ascontiguousarray(np.moveaxis(pixels[..., :3], -1, 0))
aux = np.stack([pixels[..., index[n]] for n in DENOISER_CHANNELS])
seconds = []
for _ in range(2):
    start = time.perf_counter()
    denoise_planar(planar, ("R", "G", "B"), aux, sys.argv[2])
    seconds.append(time.perf_counter() - start)
print(json.dumps(seconds))
"""


def denoise_seconds(raw: Path, quality: str) -> dict[str, float]:
    """The denoise of a job's raw image at `quality` in a fresh process: its first call, as a job pays it
    (OIDN's import and first filter included), and a second one."""
    done = subprocess.run([sys.executable, "-c", _DENOISE_TIMED, str(raw), quality], capture_output=True,
                          text=True, timeout=600, cwd=Path(__file__).resolve().parent.parent)
    if done.returncode != 0:
        raise QuekaroError(f"denoising {raw} at {quality} failed: {done.stderr.strip()[-500:]}")
    first, second = json.loads(done.stdout)
    return {"first": first, "warm": second}


def estimated_share(scene: dict[str, Any], aov_spp: int, quality: str) -> float:
    """The share of the scene's job with one setting in place of the product's: each timed job's AOV pass and
    denoise, and its total, changed by the measured difference between the two settings' parts (AOV pass
    warm, denoise's first call); the runs' median. The product's own setting gives the jobs' share."""
    delta = (scene["aov_s"][str(aov_spp)] - scene["aov_s"][str(AOV_SPP)]
             + scene["denoise_s"][quality]["first"] - scene["denoise_s"][QUALITY]["first"])
    return float(np.median([(r["aov_s"] + r["denoise_s"] + delta) / (r["total_s"] + delta) for r in scene["runs"]]))


# ---- settings: what each AOV spp and quality gives -----------------------------------------------------


@dataclasses.dataclass
class BoxScene:
    """A scene at `--res` with the box filter a denoised job takes: its reference, its colour at each
    `--compare-spp`, and its AOV passes (cached by spp and seed)."""

    entry: SuiteScene
    loaded: Any
    reference: np.ndarray
    colours: dict[int, np.ndarray]
    aovs: dict[tuple[int, int], dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)

    @classmethod
    def make(cls, entry: SuiteScene, args: argparse.Namespace) -> BoxScene:
        spec = _spec(entry, args.res, DENOISER_FILTER)
        variant = job_variant(spec)
        loaded = load(spec, variant, threads=args.threads)
        reference = cached_reference(spec, loaded, args.ref_spp, variant, args.cache_dir)
        colours = {spp: render(loaded, spp, COLOUR_SEED, aovs=False)[0]["colour"] for spp in args.compare_list}
        return cls(entry, loaded, reference, colours)

    def aov(self, spp: int, seed: int = AOV_SEED) -> dict[str, np.ndarray]:
        if (spp, seed) not in self.aovs:
            self.aovs[(spp, seed)] = render(self.loaded, spp, seed, aovs=True)[0]
        return self.aovs[(spp, seed)]

    def scored(self, image: np.ndarray) -> dict[str, float]:
        return {"relmse": relmse(image, self.reference), "flip": flip(image, self.reference)}


def measure_settings(box: BoxScene, args: argparse.Namespace) -> list[dict[str, Any]]:
    """The scene's denoised errors per colour spp, AOV spp and quality, and the control: the best setting
    with its AOV pass at another seed."""
    rows = []
    for spp, colour in box.colours.items():
        for aov_spp in args.aov_list:
            aux = box.aov(aov_spp)
            for quality in args.quality_list:
                den = denoise(colour, aux["albedo"], aux["normal"], quality)
                rows.append({"spp": spp, "aov_spp": aov_spp, "quality": quality, "seed": AOV_SEED, **box.scored(den)})
        aux = box.aov(args.aov_list[0], CONTROL_SEED)
        den = denoise(colour, aux["albedo"], aux["normal"], args.quality_list[0])
        rows.append({"spp": spp, "aov_spp": args.aov_list[0], "quality": args.quality_list[0], "seed": CONTROL_SEED,
                     **box.scored(den)})
    return rows


def settings_summary(scenes: dict[str, list[dict[str, Any]]], cost: dict[str, Any] | None,
                     args: argparse.Namespace) -> dict[str, Any]:
    """Per setting (and the control), over the scenes: the medians of its FLIP and relMSE over the best
    setting's at each colour spp, its worst scene's FLIP ratio, its estimated job share (where the cost part
    ran), whether it keeps the image; the cheapest setting that does, and the cheapest that meets the target."""
    best = (args.aov_list[0], args.quality_list[0], AOV_SEED)
    keys = [(a, q, AOV_SEED) for a in args.aov_list for q in args.quality_list] + [(*best[:2], CONTROL_SEED)]
    rows = [_setting_row(key, best, scenes, cost, args) for key in keys]
    kept = [r for r in rows if r["keeps"] and r["seed"] == AOV_SEED and r["share"] is not None]
    cheapest = kept[0] if kept else None  # rows go best first: a later one must be cheaper by more than a tie
    for row in kept[1:]:
        cheapest = row if row["share"] < cheapest["share"] - SHARE_TIE else cheapest
    meeting = [r for r in rows if r["seed"] == AOV_SEED and r["share"] is not None and r["share"] <= COST_TARGET]
    return {"scenes": scenes, "rows": rows, "tolerance": TOLERANCE, "cheapest_kept": cheapest,
            "best_meeting": min(meeting, key=lambda r: r["flip_worst"], default=None),
            "product": {"aov_spp": AOV_SPP, "quality": QUALITY}}


def _setting_row(key: tuple[int, str, int], best: tuple[int, str, int], scenes: dict[str, list[dict[str, Any]]],
                 cost: dict[str, Any] | None, args: argparse.Namespace) -> dict[str, Any]:
    aov_spp, quality, seed = key

    def pick(rows: list[dict[str, Any]], k: tuple[int, str, int], spp: int) -> dict[str, Any]:
        return next(r for r in rows if (r["aov_spp"], r["quality"], r["seed"], r["spp"]) == (*k, spp))

    ratios = {m: {spp: [pick(rows, key, spp)[m] / pick(rows, best, spp)[m] for rows in scenes.values()]
                  for spp in args.compare_list} for m in ("flip", "relmse")}
    med = {m: {str(spp): float(np.median(v)) for spp, v in by.items()} for m, by in ratios.items()}
    worst = float(max(max(v) for v in ratios["flip"].values()))
    keeps = (max(med["flip"].values()) <= TOLERANCE["flip"] and max(med["relmse"].values()) <= TOLERANCE["relmse"]
             and worst <= TOLERANCE["worst_flip"])
    timed = cost is not None and all({str(aov_spp), str(AOV_SPP)} <= set(s["aov_s"]) and
                                     {quality, QUALITY} <= set(s["denoise_s"]) for s in cost["scenes"].values())
    return {"aov_spp": aov_spp, "quality": quality, "seed": seed, "flip": med["flip"], "relmse": med["relmse"],
            "flip_worst": worst, "keeps": keeps,
            "aov_s": float(np.median([s["aov_s"][str(aov_spp)] for s in cost["scenes"].values()])) if timed else None,
            **{f"denoise_{k}_s": float(np.median([s["denoise_s"][quality][k] for s in cost["scenes"].values()]))
               if timed else None for k in ("first", "warm")},
            "share": float(np.median([estimated_share(s, aov_spp, quality) for s in cost["scenes"].values()]))
            if timed else None}


# ---- blend: the rules keeping raw detail per unit ------------------------------------------------------


def unit_scores(units: list[WorkUnit]) -> np.ndarray:
    """Each unit's complexity score in [0, 1]: the mean of its C and its Nd, each over the job's largest (1:
    the job's most complex and most contrasted unit; a job whose units all have 0 scores 0)."""
    def scaled(values: np.ndarray) -> np.ndarray:
        return values / values.max() if values.max() > 0 else np.zeros_like(values)

    return 0.5 * (scaled(np.array([u.C for u in units])) + scaled(np.array([u.Nd for u in units])))


def raw_weights(units: list[WorkUnit], scores: np.ndarray, strength: float, height: int, width: int) -> np.ndarray:
    """The (H x W) weight of the raw image: each unit's strength ** (1 + BLEND_SPREAD (1 - score)) (monotone: more
    raw where the unit is more complex; 0 at strength 0, 1 at strength 1), box-blurred over width / FEATHER
    pixels each side, so that the blend is feathered across the units' borders."""
    weights = np.zeros((height, width))
    for unit, score in zip(units, scores, strict=True):
        r = unit.rect
        weights[r.y:r.y + r.h, r.x:r.x + r.w] = strength ** (1.0 + BLEND_SPREAD * (1.0 - score))
    return feathered(weights, max(1, round(width / FEATHER)))


def feathered(weights: np.ndarray, reach: int) -> np.ndarray:
    """The map's mean over a (2 reach + 1)^2 box, edges repeated, by running sums (a constant map stays
    exactly constant)."""
    out = weights.astype(np.float64)
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (reach + 1, reach)
        sums = np.cumsum(np.pad(out, pad, mode="edge"), axis=axis)
        ahead, behind = (np.take(sums, np.arange(2 * reach + 1, sums.shape[axis]), axis=axis),
                         np.take(sums, np.arange(0, sums.shape[axis] - 2 * reach - 1), axis=axis))
        out = (ahead - behind) / (2 * reach + 1)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def blended(denoised: np.ndarray, raw: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(1 - w) denoised + w raw, per pixel: exactly the denoised image where w is 0, the raw one where 1."""
    w = weights[..., None]
    return ((1.0 - w) * denoised + w * raw).astype(np.float32)


def measure_blend(box: BoxScene, args: argparse.Namespace) -> list[dict[str, Any]]:
    """The scene's FLIP and relMSE per colour spp: the global denoise, the raw image, and at each strength the
    rules' blend (by the units of the `--blend-level` plan) and a uniform blend of the same strength."""
    options = RenderOptions(level=args.blend_level, spp=max(args.compare_list), threads=args.threads, denoise=True)
    plan = plan_job(_spec(box.entry, args.res), options, seed=0)
    scores = unit_scores(plan.units)
    aux = box.aov(AOV_SPP)
    rows = []
    for spp, raw in box.colours.items():
        den = denoise(raw, aux["albedo"], aux["normal"])
        rows += [{"spp": spp, "mode": "global", "strength": 0.0, **box.scored(den)},
                 {"spp": spp, "mode": "raw", "strength": 1.0, **box.scored(raw)}]
        for strength in args.strength_list:
            for mode, by in (("rules", scores), ("uniform", np.ones_like(scores))):
                weights = raw_weights(plan.units, by, strength, plan.height, plan.width)
                rows.append({"spp": spp, "mode": mode, "strength": strength,
                             **box.scored(blended(den, raw, weights))})
    return rows


def blend_summary(scenes: dict[str, list[dict[str, Any]]], args: argparse.Namespace) -> dict[str, Any]:
    """Per colour spp, mode and strength: the suite medians of FLIP and relMSE over the global denoise's; the
    verdict: the rules' blend wins where, at one strength, its median FLIP is under the global's by
    WIN_MARGIN at every spp, and under the uniform blend's."""
    medians = []
    for spp in args.compare_list:
        for mode, strength in [("raw", 1.0)] + [(m, s) for s in args.strength_list for m in ("rules", "uniform")]:
            ratios = {m: [_blend_row(rows, spp, mode, strength)[m] / _blend_row(rows, spp, "global", 0.0)[m]
                          for rows in scenes.values()] for m in ("flip", "relmse")}
            medians.append({"spp": spp, "mode": mode, "strength": strength,
                            **{m: float(np.median(v)) for m, v in ratios.items()}})

    def median_of(spp: int, mode: str, strength: float) -> float:
        return next(m["flip"] for m in medians if (m["spp"], m["mode"], m["strength"]) == (spp, mode, strength))

    best = min(args.strength_list, key=lambda s: max(median_of(spp, "rules", s) for spp in args.compare_list))
    wins = all(median_of(spp, "rules", best) <= 1.0 - WIN_MARGIN and
               median_of(spp, "rules", best) < median_of(spp, "uniform", best) for spp in args.compare_list)
    return {"scenes": scenes, "medians": medians, "best_strength": best, "wins": wins,
            "best_flip": {str(spp): median_of(spp, "rules", best) for spp in args.compare_list},
            "uniform_flip": {str(spp): median_of(spp, "uniform", best) for spp in args.compare_list}}


def _blend_row(rows: list[dict[str, Any]], spp: int, mode: str, strength: float) -> dict[str, Any]:
    return next(r for r in rows if (r["spp"], r["mode"], r["strength"]) == (spp, mode, strength))


# ---- the report --------------------------------------------------------------------------------------------


def format_report(result: dict[str, Any]) -> str:
    load = ", ".join(f"{x:.2f}" for x in result["load"])
    lines = [f"Load average (1 min) at the start and end: {load} (2 cores; the machine is shared)."]
    if "scenes" in result:
        lines += ["", "## The filter: the scene's own against a box one", "", *format_filters(result)]
    if "cost" in result:
        lines += ["", "## Cost: real denoised jobs", "", *format_cost(result["cost"])]
    if "settings" in result:
        lines += ["", "## AOV spp and OIDN quality", "", *format_settings(result["settings"], result)]
    if "blend" in result:
        lines += ["", "## Rules-controlled blend (issue 64's experiment)", "", *format_blend(result["blend"], result)]
    return "\n".join(lines)


def format_filters(result: dict[str, Any]) -> list[str]:
    lines = [f"{result['res']} px wide; references {result['ref_spp']} spp, one per filter; relMSE and FLIP "
             "against the reference of the same filter, and (last column) the box-filtered denoised image "
             "against the scene's own reference, over the raw image with the scene's own filter; re-filtered: that "
             "image convolved with the scene's gaussian. AOV pass: the denoiser's albedo and normal at "
             f"{AOV_SPP} spp, its seconds over the colour's. One process, kernels warm.", "",
             "| scene | filter | spp | relMSE raw | denoised | denoised / raw | FLIP raw | denoised "
             "| box denoised vs own ref / own raw | same, re-filtered | render s | AOV pass / render | denoise s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, scene in result["scenes"].items():
        own = {r["spp"]: r for r in scene["rows"] if r["filter"] == OWN}
        for r in scene["rows"]:
            base = own[r["spp"]]["relmse_raw"]
            cross = f"{r['relmse_denoised_vs_own'] / base:.3f}" if r["filter"] == DENOISER_FILTER else ""
            again = f"{r['relmse_refiltered_vs_own'] / base:.3f}" if r.get("relmse_refiltered_vs_own") else ""
            cells = [name, r["filter"], r["spp"], f"{r['relmse_raw']:.5f}", f"{r['relmse_denoised']:.5f}",
                     f"{r['relmse_denoised'] / r['relmse_raw']:.3f}", f"{r['flip_raw']:.4f}",
                     f"{r['flip_denoised']:.4f}",
                     cross, again, f"{r['render_s']:.2f}", f"{r['aov_share']:.0%}", f"{r['denoise_s']:.2f}"]
            lines.append("| " + " | ".join(map(str, cells)) + " |")
    lines += ["", "Medians over the scenes (denoised / raw relMSE):", ""]
    for spp, s in result["summary"].items():
        own, box = s[f"{OWN}_ratio"], s[f"{DENOISER_FILTER}_ratio"]
        lines.append(f"- {spp} spp: scene's own filter {own:.3f}, box {box:.3f}; box denoised against the scene's "
                     f"own reference, over its own raw image: {s['box_denoised_over_own_raw']:.3f}")
    return lines


def cost_line(cost: dict[str, Any]) -> str:
    """The line the target is read from."""
    verdict = "met" if cost["met"] else "missed"
    return (f"**Cost: (AOV pass + denoise) / job, {cost['res']} px {cost['spp']} spp `quekaro render --denoise` "
            f"(AOV pass {cost['aov_spp']} spp, OIDN {cost['quality']}), median of {len(cost['scenes'])} scene(s): "
            f"{cost['share']:.1%}; target <= {COST_TARGET:.0%}: {verdict}**")


def format_cost(cost: dict[str, Any]) -> list[str]:
    lines = [f"Each scene {cost['res']} px wide at {cost['spp']} spp, rendered by `quekaro render --denoise` as a "
             "user runs it, once unscored (kernels compiled) and then timed; seconds from each job's report "
             "(`render_calls.aov_pass_seconds`, `denoise.seconds`, `totals.seconds`; wall: the process, start "
             "included). Share: the median of the timed jobs'.", "",
             "| scene | size | job s | wall s | AOV pass s | denoise s | (AOV pass + denoise) / job |",
             "|---|---|---|---|---|---|---|"]
    for name, s in cost["scenes"].items():
        runs = s["runs"]
        cells = [name, "x".join(map(str, runs[0]["size"])), *(" / ".join(f"{r[k]:.2f}" for r in runs)
                 for k in ("total_s", "wall_s", "aov_s", "denoise_s")), f"{s['share']:.1%}"]
        lines.append("| " + " | ".join(cells) + " |")
    return [*lines, "", cost_line(cost), "",
            f"The AOV pass and the denoise take {cost['parts_s']:.2f} s (median of the jobs): {COST_TARGET:.0%} of "
            f"a job from {cost['parts_s'] / COST_TARGET:.1f} s on (the median job here: {cost['job_s']:.2f} s)."]


def _setting_name(row: dict[str, Any]) -> str:
    return f"{row['aov_spp']} spp, {row['quality']}"


def format_settings(settings: dict[str, Any], result: dict[str, Any]) -> list[str]:
    rows = settings["rows"]
    spps = list(rows[0]["flip"])
    tol = settings["tolerance"]
    lines = [f"Quality: {result['res']} px wide, the colour at {', '.join(spps)} spp (box filter) denoised with each "
             f"AOV pass spp and OIDN quality, FLIP and relMSE against the {result['ref_spp']} spp box reference, "
             "over the best setting's (the first row's), suite medians; worst: the largest scene ratio of FLIP. "
             "Cost (where the cost part ran): at the jobs' size, the AOV pass warm in a render process, the denoise's "
             "first call in a fresh process as a job pays it (OIDN's import and first filter; warm: a second call), "
             "medians over the scenes; share: of each scene's job with this setting's parts in place of its own, "
             "median. The control row renders the best setting's AOV pass with another seed: the measurement's "
             f"own noise. Keeps the image: FLIP median <= {tol['flip']:.2f}x, relMSE median <= "
             f"{tol['relmse']:.2f}x at every spp, worst FLIP <= {tol['worst_flip']:.2f}x.", "",
             "| AOV pass | " + " | ".join(f"FLIP ratio {s} spp" for s in spps) + " | "
             + " | ".join(f"relMSE ratio {s} spp" for s in spps)
             + " | worst FLIP | keeps the image | AOV pass s | denoise s (first call) | warm | est. share of job |",
             "|---|" + "---|" * (2 * len(spps) + 6)]
    for r in rows:
        name = _setting_name(r) + (" (control: another seed)" if r["seed"] != AOV_SEED else "")
        cost = [f"{r[k]:.3f}" if r[k] is not None else "" for k in ("aov_s", "denoise_first_s", "denoise_warm_s")] + \
               [f"{r['share']:.1%}" if r["share"] is not None else ""]
        cells = [name, *(f"{r['flip'][s]:.3f}" for s in spps), *(f"{r['relmse'][s]:.3f}" for s in spps),
                 f"{r['flip_worst']:.3f}", "yes" if r["keeps"] else "no", *cost]
        lines.append("| " + " | ".join(cells) + " |")
    return [*lines, "", *settings_verdict(settings)]


def settings_verdict(settings: dict[str, Any]) -> list[str]:
    product = settings["product"]
    lines = [f"- The product's setting (core.image.denoise): {product['aov_spp']} spp, {product['quality']}."]
    cheapest, meeting = settings["cheapest_kept"], settings["best_meeting"]
    if cheapest is not None:
        verdict = "met" if cheapest["share"] <= COST_TARGET else "missed"
        lines.append(f"- Cheapest setting that keeps the image (shares within {SHARE_TIE:.1%} tie, the better "
                     f"setting chosen): {_setting_name(cheapest)}, estimated {cheapest['share']:.1%} of a job: target "
                     f"<= {COST_TARGET:.0%} {verdict}.")
    if meeting is not None:
        flips, errors = (", ".join(f"{v:.3f}x" for v in meeting[m].values()) for m in ("flip", "relmse"))
        lines.append(f"- Meeting the target takes {_setting_name(meeting)} (estimated {meeting['share']:.1%}), the "
                     f"least worse of those that meet it: FLIP {flips} (worst scene {meeting['flip_worst']:.3f}x), "
                     f"relMSE {errors}.")
    elif any(r["share"] is not None for r in settings["rows"]):
        least = min((r for r in settings["rows"] if r["share"] is not None), key=lambda r: r["share"])
        lines.append(f"- No setting measured meets the target of {COST_TARGET:.0%}: the cheapest, "
                     f"{_setting_name(least)}, takes an estimated {least['share']:.1%} (worst scene's FLIP "
                     f"{least['flip_worst']:.3f}x).")
    return lines


def format_blend(blend: dict[str, Any], result: dict[str, Any]) -> list[str]:
    strengths = sorted({m["strength"] for m in blend["medians"] if m["mode"] == "rules"})
    lines = [f"{result['res']} px wide, box filter, the colour at each spp denoised as the product does "
             f"({AOV_SPP} spp AOV pass, OIDN {QUALITY}); per unit of the plan (its C and Nd), the raw image's weight "
             f"is strength ^ (1 + {BLEND_SPREAD:g} (1 - score)), score = (C / max C + Nd / max Nd) / 2, feathered over "
             f"width / {FEATHER} px; uniform: the strength everywhere. FLIP against the box reference.", "",
             "| scene | spp | FLIP global denoise | raw | " + " | ".join(f"rules {s:g}" for s in strengths) + " | "
             + " | ".join(f"uniform {s:g}" for s in strengths) + " |",
             "|---|---|---|---|" + "---|" * (2 * len(strengths))]
    for name, rows in blend["scenes"].items():
        for spp in sorted({r["spp"] for r in rows}):
            cells = [f"{_blend_row(rows, spp, m, s)['flip']:.4f}" for m, s in
                     [("global", 0.0), ("raw", 1.0)] + [(m, s) for m in ("rules", "uniform") for s in strengths]]
            lines.append(f"| {name} | {spp} | " + " | ".join(cells) + " |")
    lines += ["", "Suite medians over the global denoise's:", "",
              "| spp | blend | strength | FLIP ratio | relMSE ratio |", "|---|---|---|---|---|"]
    lines += [f"| {m['spp']} | {m['mode']} | {m['strength']:g} | {m['flip']:.3f} | {m['relmse']:.3f} |"
              for m in blend["medians"]]
    best = ", ".join(f"{v:.3f}x at {spp} spp" for spp, v in blend["best_flip"].items())
    uniform = ", ".join(f"{v:.3f}x" for v in blend["uniform_flip"].values())
    verdict = "wins" if blend["wins"] else "does not win"
    return [*lines, "", f"**Blend verdict: the rules' blend {verdict} over one global denoise: at its best strength "
                        f"({blend['best_strength']:g}) its median FLIP is {best} the global's (a win needs <= "
                        f"{1 - WIN_MARGIN:.2f}x at every spp and under the uniform blend's: {uniform}).**"]
