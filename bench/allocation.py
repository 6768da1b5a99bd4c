"""`quekaro bench allocation`: what each optimisation level's sample allocation costs in render time and
buys in error, predicted from measured maps in about a minute, without a farm.

`run` measures each pixel's noise (`noise_map`) and time (`bench.scaling.measure_cached`) once, plans every
level as the farm does, and predicts each plan's render seconds and relMSE (`level_row`) against uniform spp
at the same time (`uniform`), beside the bounds `neyman_ratio`, `pixel_bound` and `first_pass_ratio`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from bench.accuracy import DEFAULT_OUT, HETEROGENEOUS, SCENES
from bench.args import check_minimums
from bench.provenance import rules_for
from bench.report import command_of, publish_markdown
from bench.scaling import measure_cached, measured_spec
from core.errors import RenderError
from core.image.compose import blend_weights
from core.image.metrics import RELMSE_EPSILON
from core.model.geometry import Rect
from core.model.hashing import sha256_file
from core.model.job import RenderOptions
from core.model.levels import RULE_LEVELS
from core.model.seeds import plan_seed
from core.render.adaptive import first_pass, first_spp, neyman_scale
from core.rules.unit_params import Planner
from core.scene.scene import film_info, load, parse_defines
from planning.accuracy import content_key, job_variant, plain_render, reference
from planning.jobplan import plan_job
from planning.pipeline import plan_params

LEVELS = RULE_LEVELS  # every level that runs the rules


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=SCENES[HETEROGENEOUS])
    parser.add_argument("--res", type=int, default=320, help="image side (-D res), unless -D is given")
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                        help="a scene parameter, as Mitsuba's -D; with -D the scene is taken at its film's size "
                             "and --res is not passed")
    parser.add_argument("--spp", type=int, default=128, help="the user's spp (level off)")
    parser.add_argument("--renders", type=int, default=6, help="independent renders for the noise map")
    parser.add_argument("--ref-spp", type=int, default=2048, help="spp of the reference")
    parser.add_argument("--rules", type=Path, help="rule file (default rules/pathtracing.xml)")
    parser.add_argument("--seeds", type=int, default=5,
                        help="pre-pass seeds per level (the farm's plan uses one; the pre-pass is noisy)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cell", type=int, default=32, help="side of the time map's cells (as bench scaling)")
    parser.add_argument("--measure-spp", type=int, default=64, help="spp of the time map's cell renders")
    parser.add_argument("--cache-dir", type=Path, default=Path.home() / ".cache" / "quekaro")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for allocation.md")


def noise_path(spec: Any, spp: int, renders: int, cache: Path, variant: str) -> Path:
    """Where `noise_map` caches the scene's noise map."""
    return cache / f"allocation-noise-{content_key(spec, spp, renders, variant)}.npy"


def noise_map(spec: Any, spp: int, renders: int, threads: int, cache: Path, variant: str) -> np.ndarray:
    """Per-pixel, per-channel variance of one sample in `variant`: the sample variance of `renders`
    independent plain renders at `spp`, times spp (cached by the content of every file the scene reads, its
    defines, spp, renders and variant: planning.accuracy.content_key)."""
    path = noise_path(spec, spp, renders, cache, variant)
    if path.exists():
        return np.load(path)
    if renders < 2:
        raise ValueError(f"--renders {renders}: a variance needs at least 2 renders")
    images = np.stack([plain_render(spec, spp, threads, variant, seed=101 + i)[0] for i in range(renders)])
    sigma2 = spp * images.var(axis=0, ddof=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, sigma2)
    return sigma2


def composed_inverse_spp(plan: Any, spps: Any, bands: Any) -> np.ndarray:
    """Per pixel, the composed image's variance in units of one sample's: sum over the tiles covering it
    of w^2 / n, w its normalised blend weight (core.image.compose) and n the tile's spp. A pixel in one
    tile's core only is 1 / n; where a neighbour's band overlaps, the two independent estimates average
    and the variance falls (a band's samples are not wasted)."""
    geometry = [(u.rect.window(int(b), plan.width, plan.height), u.rect)
                for u, b in zip(plan.units, bands, strict=True)]
    factor = np.zeros((plan.height, plan.width))
    for (rect, _), w, n in zip(geometry, blend_weights(geometry, plan.width, plan.height, plan.reach), spps,
                               strict=True):
        factor[rect.slices()] += w * w / float(n)
    return factor


def level_row(level: str, plan: Any, params: list[Any], weight: np.ndarray, tmap: Any) -> dict[str, Any]:
    """Predicted render seconds, relMSE of the composed image and spp spread of one level's plan. A unit at
    n spp takes fixed + n x (seconds per sample over the unit and its bands); its pixels' expected relMSE
    is their weighted variance / n."""
    seconds = sum(tmap.unit_seconds(u.rect, p.spp, band=p.band) for u, p in zip(plan.units, params, strict=True))
    spp = np.array([p.spp for p in params])
    area = np.array([u.rect.area for u in plan.units])
    factor = composed_inverse_spp(plan, spp, [p.band for p in params])
    return {"level": level, "units": len(plan.units), "render_seconds": seconds,
            "relmse": float((weight * factor[..., None]).mean()), "spp_mean": float((spp * area).sum() / area.sum()),
            "spp_min": int(spp.min()), "spp_max": int(spp.max())}


def uniform(seconds: float, weight: np.ndarray, tmap: Any) -> tuple[float, float]:
    """(spp, relMSE) of plain uniform spp over the whole image in `seconds` of render time."""
    spp = max(1.0, (seconds - tmap.fixed_s) / float(tmap.per_sample.sum()))
    return spp, float(weight.mean() / spp)


def neyman_ratio(plan: Any, params: list[Any], weight: np.ndarray, tmap: Any) -> float:
    """relMSE over uniform's of the best allocation over these units and bands at the same render time:
    each unit's spp proportional to sqrt(error per sample / seconds per sample) (Neyman), with the true
    noise; its error is the composed image's, as for the levels."""
    err = np.array([weight[u.rect.slices()].sum() for u in plan.units])
    per_spp = np.array([tmap.unit_seconds(u.rect, 1, band=p.band) - tmap.fixed_s
                        for u, p in zip(plan.units, params, strict=True)])
    seconds = sum(tmap.unit_seconds(u.rect, p.spp, band=p.band) for u, p in zip(plan.units, params, strict=True))
    budget = seconds - tmap.fixed_s * len(plan.units)
    share = np.sqrt(err / np.maximum(per_spp, 1e-15))
    spp = share * budget / float((share * per_spp).sum())
    factor = composed_inverse_spp(plan, spp, [p.band for p in params])
    return float((weight * factor[..., None]).mean()) / uniform(seconds, weight, tmap)[1]


def pixel_bound(weight: np.ndarray, tmap: Any) -> float:
    """relMSE over uniform's of the best allocation of all: every pixel its own (real-valued) spp in
    proportion to sqrt(error per sample / seconds per sample), with the true noise, no units, no bands
    and no fixed costs. By Cauchy-Schwarz it is (sum sqrt(e t))^2 / (sum e x sum t), at most 1, and 1
    exactly when e is proportional to t: what any adaptive sampling can gain on this scene at equal
    render time, whatever decides it (rules, variance or an oracle). It is optimistic: spp may be
    fractional, and a noise map from a few renders varies more across pixels than the true noise does.
    So where it is above a target, no allocation meets that target on the scene."""
    err = np.asarray(weight, dtype=np.float64).mean(axis=-1)  # (H, W, C) -> per pixel, as relMSE averages
    per = np.asarray(tmap.per_sample, dtype=np.float64)
    if err.shape != per.shape:
        raise ValueError(f"error map {err.shape} and time map {per.shape} differ in shape")
    total = float(err.sum()) * float(per.sum())
    return float(np.sqrt(err * per).sum() ** 2 / total) if total > 0 else 1.0


def first_pass_ratio(weight: np.ndarray, tmap: Any, estimate: np.ndarray, spp: int, first: int) -> float:
    """relMSE over uniform's at equal render time of the allocation a two-pass render makes: `first` samples
    in every pixel, then each pixel max(first, lam sqrt(estimate)) as core.render.adaptive places them (by
    the noise alone), lam such that they take the render time of `spp` everywhere; scored on the true error
    per sample (`weight`, H x W x C). `estimate` is the noise the render knows (its first pass's, blurred:
    core.render.adaptive.first_pass). With the true noise and time even across pixels this is `pixel_bound`; what it
    leaves above that bound is the cost of not knowing the noise beforehand and of spending a first pass."""
    err = np.asarray(weight, dtype=np.float64).mean(axis=-1)
    per = np.asarray(tmap.per_sample, dtype=np.float64)
    if not err.shape == per.shape == estimate.shape:
        raise ValueError(f"error {err.shape}, time {per.shape} and estimate {estimate.shape} maps differ in shape")
    base = np.sqrt(np.maximum(np.asarray(estimate, dtype=np.float64), 0.0))
    if err.sum() <= 0 or spp <= first or not base.any():  # nothing to gain, no samples to move, or no guide
        return 1.0
    counts = np.maximum(first, neyman_scale(base, per, first, spp * float(per.sum())) * base)
    kept = np.divide(err, counts, out=np.zeros(err.shape), where=err > 0)  # a noiseless pixel adds nothing
    return float(kept.sum() / (err / spp).sum())


def rules_file(args: argparse.Namespace) -> Path | None:
    """The rule file every level planned with (bench.commands records its hash)."""
    return rules_for(args, LEVELS)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Every level's predicted ratio against uniform spp. `quekaro bench accuracy` measures the same end to
    end, but one render's relMSE on a caustic swings so much that comparing two rule files there takes many
    runs; here the noise is measured once. Not modelled: depth cuts (levels B and VB render shorter paths:
    less time, some bias), the farm's protocol costs (render time only), and the per-render noise of
    relMSE itself. Every measurement is cached under `--cache-dir` (the reference is bench accuracy's)."""
    # A variance needs two renders; the time map's cells a side; every count at least one.
    check_minimums(args, spp=1, ref_spp=1, renders=2, seeds=1, threads=1, cell=1, measure_spp=1, res=1)
    defines = parse_defines(args.defines) if args.defines else None
    spec = measured_spec(args.scene.resolve(), args.res, defines=defines)  # as `bench accuracy`: one reference
    size = film_info(spec)
    variant = job_variant(spec)
    sigma2 = noise_map(spec, args.spp, args.renders, args.threads, args.cache_dir, variant)
    ref = reference(spec, args.ref_spp, args.threads, args.cache_dir, variant)
    weight = sigma2 / (ref**2 + RELMSE_EPSILON)  # each pixel's variance weighted as relMSE weighs its error
    tmap, _, _ = measure_cached(spec.path, args.res, args.cell, args.measure_spp, args.threads,
                                args.cache_dir, defines=defines)
    off_seconds = tmap.unit_seconds(Rect(0, 0, size.width, size.height), args.spp, band=0)
    planner = Planner(args.rules, "centroid")
    digest = sha256_file(spec.path)
    rows, bounds = [], []
    for level in LEVELS:
        options = RenderOptions(level=level, spp=args.spp, threads=args.threads, rules=args.rules)
        # The rule file and the level shape no pre-pass (core.model.seeds), so two rule files, and the
        # levels, are compared on the same pre-passes (the pre-pass's noise moves a level's ratio by +-0.1).
        base = plan_seed(digest, spec.defines, options.to_dict())
        runs = []
        for k in range(args.seeds):  # k = 0: the plan `quekaro render` makes with the default rules
            plan = plan_job(spec, options, seed=base + k)
            params = plan_params(plan, planner)
            run = level_row(level, plan, params, weight, tmap)
            run["uniform_spp"], run["uniform_relmse"] = uniform(run["render_seconds"], weight, tmap)
            run["ratio"] = run["relmse"] / run["uniform_relmse"]
            run["time_vs_off"] = run["render_seconds"] / off_seconds
            runs.append(run)
            if level == "S":
                bounds.append(neyman_ratio(plan, params, weight, tmap))
        rows.append(_summary(level, runs))
    result = {"scene": str(args.scene), "size": [size.width, size.height], "defines": spec.defines,
              "spp": args.spp, "renders": args.renders,
              "rules": str(planner.rules_path), "seeds": args.seeds, "off_render_seconds": off_seconds,
              "rows": rows, "neyman_ratio_S": float(np.mean(bounds)), "pixel_bound": pixel_bound(weight, tmap),
              "first_pass": first_pass_bound(spec, variant, weight, tmap, args)}
    report = format_report(result)
    result["report"] = str(publish_markdown(args.out, "allocation", "Each level's allocation against uniform spp",
                                            command_of(args, "quekaro bench allocation"), report,
                                            show=not args.json))
    return result


def first_pass_bound(spec: Any, variant: str, weight: np.ndarray, tmap: Any,
                     args: argparse.Namespace) -> dict[str, Any]:
    """`first_pass_ratio` with the first pass's own estimate, one per seed (the pass is as noisy as a
    render), and their mean."""
    ratios, first = [], first_spp(args.spp)
    loaded = load(spec, variant, threads=args.threads)
    for k in range(args.seeds):
        try:
            _, estimate = first_pass(loaded, first, seed=5000 + k)
        except RenderError as exc:  # what `--adaptive` refuses too (core.render.per_pixel.check_renderable)
            return {"first_spp": first, "ratio": None, "ratio_runs": [], "refused": str(exc)}
        ratios.append(first_pass_ratio(weight, tmap, estimate, args.spp, first))
    return {"first_spp": first, "ratio": float(np.mean(ratios)), "ratio_runs": ratios}


def _summary(level: str, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over the pre-pass seeds, with each seed's ratio and time listed."""
    row: dict[str, Any] = {"level": level}
    for key in ("units", "render_seconds", "relmse", "spp_mean", "uniform_spp", "uniform_relmse", "ratio",
                "time_vs_off"):
        row[key] = float(np.mean([r[key] for r in runs]))
    row["spp_min"] = min(r["spp_min"] for r in runs)
    row["spp_max"] = max(r["spp_max"] for r in runs)
    row["ratio_runs"] = [r["ratio"] for r in runs]
    row["time_vs_off_runs"] = [r["time_vs_off"] for r in runs]
    return row


def format_report(result: dict[str, Any]) -> str:
    width, height = result["size"]
    lines = [f"{Path(result['scene']).name} {width}x{height}, user spp {result['spp']}, "
             f"rules {Path(result['rules']).name}; level off renders {result['off_render_seconds']:.2f} s "
             "(predicted)",
             "| level | units | render s | x off | spp mean (min-max) | relMSE | uniform spp | uniform relMSE "
             "| ratio (per seed) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        each = ", ".join(f"{x:.2f}" for x in r["ratio_runs"])
        lines.append(f"| {r['level']} | {r['units']:.0f} | {r['render_seconds']:.2f} | {r['time_vs_off']:.2f} | "
                     f"{r['spp_mean']:.0f} ({r['spp_min']}-{r['spp_max']}) | {r['relmse']:.5f} | "
                     f"{r['uniform_spp']:.0f} | {r['uniform_relmse']:.5f} | {r['ratio']:.3f} ({each}) |")
    lines.append(f"means over {result['seeds']} pre-pass seeds; Neyman allocation over level S's units (true "
                 f"noise known): ratio {result['neyman_ratio_S']:.3f}")
    lines.append(f"bound of any allocation (each pixel its own spp, no units, bands or fixed costs, true "
                 f"noise known): ratio {result['pixel_bound']:.3f}")
    first = result["first_pass"]
    said = f"the same with the noise a two-pass render knows (its first pass of {first['first_spp']} spp"
    if first["ratio"] is None:
        lines.append(f"{said}): none, the two-pass render refuses this scene: {first['refused']}")
    else:
        each = ", ".join(f"{x:.2f}" for x in first["ratio_runs"])
        lines.append(f"{said}, blurred as it blurs it, the rest placed by that noise as it places them; that "
                     f"pass uniform): ratio {first['ratio']:.3f} ({each})")
    return "\n".join(lines)
