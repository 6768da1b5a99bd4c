"""`quekaro bench denoise`: what the denoiser (core.image.denoise) gains at the same spp, and why a denoised
job reconstructs with a box filter.

Per scene, in one process: references at `--ref-spp` with the scene's own filter and with a box one, then at
each `--spp` the colour and the denoiser's AOV pass (as a denoised job renders them) under each filter, raw
and denoised, scored by relMSE and FLIP against the reference of the same filter, and the box-filtered
denoised image against the scene's own reference too (what --denoise gives against the scene as written).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.args import check_minimums
from bench.report import DEFAULT_OUT, command_of, publish_markdown
from bench.scaling import default_cache_dir
from bench.suite import SUITE, scene_from_argument
from core.image.denoise import ALBEDO, AOV_SPP, AOVS, DENOISER_FILTER, NORMAL, denoise
from core.image.film import film_channels, sanitize
from core.image.metrics import flip, relmse
from core.model.job import SceneSpec
from core.render.process import aovs_alone
from core.scene.scene import film_info, load
from planning.accuracy import content_key, job_variant

OWN = "own"  # the scene's own reconstruction filter


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenes", nargs="*", help="suite names or scene files (default: the whole suite)")
    parser.add_argument("--res", type=int, default=128, help="image width (each scene keeps its aspect)")
    parser.add_argument("--spp", default="4,16,64", help="comma list of samples per pixel")
    parser.add_argument("--ref-spp", type=int, default=4096)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cache-dir", type=Path, default=default_cache_dir())
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT / "denoise", help="folder for denoise.md")


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
        aux, aov_s = render(loaded, AOV_SPP, 3, aovs=True)
        for spp in args.spp_list:
            render(loaded, spp, 0, aovs=False)
            images, seconds = render(loaded, spp, 1, aovs=False)
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


def run(args: argparse.Namespace) -> dict[str, Any]:
    check_minimums(args, res=1, ref_spp=1, threads=1)
    args.spp_list = [int(s) for s in str(args.spp).split(",")]
    chosen = [scene_from_argument(s) for s in args.scenes] if args.scenes else list(SUITE)
    scenes = {}
    for entry in chosen:
        spec = SceneSpec(entry.path.resolve(), entry.with_size(args.res))
        scenes[entry.name] = {"role": entry.role, **measure_scene(spec, args)}
    result = {"res": args.res, "spp": args.spp_list, "ref_spp": args.ref_spp, "scenes": scenes,
              "summary": summary(scenes, args.spp_list)}
    result["report"] = str(publish_markdown(args.out, "denoise", "The denoiser at the same spp, by filter",
                                            command_of(args, "quekaro bench denoise"), format_report(result),
                                            show=not args.json))
    return result


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


def format_report(result: dict[str, Any]) -> str:
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
    return "\n".join(lines)
