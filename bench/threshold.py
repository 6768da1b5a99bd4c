"""`quekaro bench threshold`: the progressive render to a noise goal (`quekaro render --noise TAU --spp CAP`,
planning.progressive) against plain Mitsuba at the uniform spp that brings its worst unit under the same TAU.

Per scene (the suite's, or files given), in a process of its own: the cached plain-Mitsuba reference; the
progressive job as the whole `quekaro render` process (its wall time, and its report's render seconds);
each of its units' true relative error sqrt(relMSE) over the unit's rectangle against the reference, over
what the unit claims (TAU where it met the goal, its estimate where it stopped at the cap); then plain
Mitsuba in this process (`uniform_to_goal`): a probe render at `--probe-spp`, whose worst unit (the job's
rectangles) gives the spp that unit needs to reach TAU (`needed_spp`: relMSE falls as 1 / spp), never past
the cap; the render at that spp, checked (and predicted again once where it misses TAU by over 10 %); and
a second render at the spp chosen, timed warm. Each side is timed `--repeats` times in turn (job, uniform,
job, uniform: a slow spell of a shared machine hits both), the fastest kept. The two targets: >= 95 % of
the units within 1.2 x their claim, and the suite's median render time progressive / uniform <= 0.6.

The reference's own noise is in every error measured against it: an image of n samples a pixel against a
reference of R (the same renderer, so the same variance a sample) measures relMSE x (1 + n / R). Errors are
scored with that share taken out (`reference_corrected`); the uncorrected ones are kept beside them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.accuracy import DEFAULT_OUT, REPO, distinct
from bench.adaptive import uniform
from bench.args import check_minimums
from bench.report import command_of, publish_markdown
from bench.scaling import default_cache_dir, suite_spec
from bench.suite import BY_NAME, SUITE, scene_from_argument
from core.errors import QuekaroError
from core.image.imageio import read_image
from core.image.metrics import relmse
from core.model.geometry import Rect
from core.scene.scene import load
from planning.accuracy import job_variant, reference

HONEST_FACTOR, HONEST_SHARE = 1.2, 0.95  # a unit's true error within 1.2 x its claim, in 95 % of the units
TIME_RATIO = 0.6  # the suite's median render time, progressive over uniform, at most
WARM_SPP = 1  # the plain render before the probe, untimed
REFINE_TOLERANCE = 0.1  # a uniform render whose worst unit is further than this from TAU (relative) is redone
REFINE_RENDERS = 1  # at most this many times, at the spp it predicts
JOB_TIMEOUT_S = 3600.0
PROBE_SEED, UNIFORM_SEED = 7001, 9001


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenes", nargs="*", help="suite names or scene files (default: the whole suite)")
    parser.add_argument("--noise", type=float, default=0.05, help="TAU: the relative error every unit renders to")
    parser.add_argument("--spp", type=int, default=4096, help="the spp cap, of the job and of uniform sampling")
    parser.add_argument("--res", type=int, default=256,
                        help="image width (each scene keeps its aspect); `--res 512 --ref-spp 1024` reuses the "
                             "references `quekaro bench accuracy` cached, at a reference 4x noisier")
    parser.add_argument("--units", type=int, default=16, help="the job's target unit count (`quekaro render --units`)")
    parser.add_argument("--probe-spp", type=int, default=64,
                        help="spp of the plain render whose worst unit predicts the uniform spp needed")
    parser.add_argument("--ref-spp", type=int, default=4096,
                        help="spp of the reference (cached by content in --cache-dir/references): its noise is "
                             "taken out of the errors by a model, which matters less the more samples it has")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2,
                        help="times each side is timed, in turn (the job, then uniform), the fastest kept")
    parser.add_argument("--cache-dir", type=Path, default=default_cache_dir())
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT / "threshold", help="folder for threshold.md")


# ---- the arithmetic -----------------------------------------------------------------------------------


def unit_relmse(image: np.ndarray, ref: np.ndarray, rects: list[Rect]) -> np.ndarray:
    """Each rectangle's relMSE (core.image.metrics.relmse, its epsilon) of `image` against `ref`."""
    return np.array([relmse(image[r.slices()], ref[r.slices()]) for r in rects], dtype=np.float64)


def reference_corrected(measured: Any, spp: Any, ref_spp: int) -> np.ndarray:
    """relMSE measured against a reference of `ref_spp` samples with the reference's share taken out: an
    image of n samples a pixel, rendered as the reference is (same variance v a sample), measures
    v / n + v / R; its own is v / n = measured x R / (n + R)."""
    spp = np.asarray(spp, dtype=np.float64)
    return np.asarray(measured, dtype=np.float64) * ref_spp / (spp + ref_spp)


def needed_spp(probe_spp: int, worst_relmse: float, tau: float) -> int:
    """The uniform spp at which a unit of relMSE `worst_relmse` at `probe_spp` reaches relative error
    `tau` (relMSE tau^2; relMSE falls as 1 / spp), at least 1. A probe already under tau gives fewer
    samples than the probe; a unit without noise needs one."""
    if tau <= 0 or not math.isfinite(tau):
        raise ValueError(f"relative error goal {tau!r}")
    if worst_relmse <= 0:
        return 1
    return max(1, math.ceil(round(probe_spp * worst_relmse / tau**2, 9)))  # round: 64 x t^2 / t^2 is 64


def next_spp(spp: int, worst_relmse: float, tau: float, cap: int) -> int | None:
    """The spp of one more uniform render after one at `spp` whose worst unit measured `worst_relmse`: the
    spp it predicts (`needed_spp`, under the cap), or None where this one is near enough (its error within
    REFINE_TOLERANCE of TAU), or is at the cap and still short, or the prediction is this spp again."""
    error = math.sqrt(max(worst_relmse, 0.0)) / tau
    if abs(error - 1) <= REFINE_TOLERANCE or (spp >= cap and error > 1):
        return None
    following = min(needed_spp(spp, worst_relmse, tau), cap)
    return None if following == spp else following


def claims(units: list[dict[str, Any]], tau: float) -> np.ndarray:
    """What each unit of a job's report says its relative error is at most: TAU where it met the goal,
    its estimate where it stopped above TAU (at the cap)."""
    return np.array([max(tau, u.get("relative_error_estimate") or 0.0) for u in units], dtype=np.float64)


def spread(values: Any) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    return {"min": float(v.min()), "median": float(np.median(v)), "max": float(v.max())}


# ---- one scene ----------------------------------------------------------------------------------------


def progressive_job(spec: Any, args: argparse.Namespace) -> tuple[dict[str, Any], np.ndarray, float]:
    """`quekaro render SCENE --noise TAU --spp CAP` as a user runs it: (its report, its RGB image, the
    whole process's wall seconds)."""
    with tempfile.TemporaryDirectory(prefix="quekaro-threshold-") as tmp:
        work = Path(tmp)
        out = work / "progressive.exr"
        cmd = [sys.executable, "-m", "quekaro", "render", str(spec.path),
               *(f"-D{k}={v}" for k, v in spec.defines.items()), "--noise", repr(args.noise), "--spp", str(args.spp),
               "-t", str(args.threads), "--units", str(args.units), "-o", str(out), "--no-progress"]
        start = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=work, timeout=JOB_TIMEOUT_S)
        wall = time.perf_counter() - start
        if done.returncode != 0:
            raise QuekaroError(f"quekaro render --noise on {spec.path}: exit {done.returncode}: "
                               f"{done.stderr.strip()[-800:]}")
        report = json.loads(out.with_suffix(".json").read_text())
        return report, read_image(report["image"]["file"])[..., :3].astype(np.float64), wall


def measure_scene(spec: Any, args: argparse.Namespace) -> dict[str, Any]:
    """One scene: the progressive job's time and its units' true errors, and plain Mitsuba at the uniform
    spp its worst unit (the job's rectangles) needs to reach TAU, with that render's time and errors. The
    first job's image is scored; every side's time is its fastest of `args.repeats`, taken in turn."""
    tau, variant = args.noise, job_variant(spec)
    ref = reference(spec, args.ref_spp, args.threads, args.cache_dir, variant).astype(np.float64)
    report, image, wall = progressive_job(spec, args)
    units = report["units"]
    rects = [Rect.from_list(u["rect"]) for u in units]
    spp = np.array([u["spp"] for u in units], dtype=np.float64)
    raw = unit_relmse(image, ref, rects)
    true = np.sqrt(reference_corrected(raw, spp, args.ref_spp))
    claim = claims(units, tau)
    progressive = report["render_calls"]["progressive"]
    loaded = load(spec, variant, threads=args.threads)
    made = uniform_to_goal(loaded, ref, rects, args)
    runs = {"render_s": [float(progressive["seconds"])], "wall_s": [wall], "uniform_s": [made["seconds"]]}
    for again in range(1, args.repeats):
        later, _, wall = progressive_job(spec, args)
        runs["render_s"].append(float(later["render_calls"]["progressive"]["seconds"]))
        runs["wall_s"].append(wall)
        runs["uniform_s"].append(uniform(loaded, made["spp"], UNIFORM_SEED + 100 + again)[1])
    made = {**made, "seconds": min(runs["uniform_s"]), "runs_s": runs["uniform_s"]}
    return {
        "variant": variant, "size": [int(image.shape[1]), int(image.shape[0])], "defines": spec.defines,
        "progressive": {
            "wall_s": min(runs["wall_s"]), "render_s": min(runs["render_s"]), "runs_s": runs["render_s"],
            "units_render_s": float(report["totals"]["render_seconds"]), "rounds": progressive["rounds"],
            "passes": progressive["passes"], "reason": progressive["reason"], "units": len(units),
            "rects": [r.as_list() for r in rects], "spp": spp.astype(int).tolist(), "spp_spread": spread(spp),
            "verdicts": [u["verdict"] for u in units], "at_cap": sum(u["verdict"] == "cap" for u in units),
            "estimate_over_tau": [(u["relative_error_estimate"] or 0.0) / tau for u in units],
            "true_over_tau": (true / tau).tolist(), "raw_over_tau": (np.sqrt(raw) / tau).tolist(),
            "honest": int((true <= HONEST_FACTOR * claim).sum()),
            "honest_raw": int((np.sqrt(raw) <= HONEST_FACTOR * claim).sum()),
            "true_over_tau_spread": spread(true / tau), "raw_over_tau_spread": spread(np.sqrt(raw) / tau),
        },
        "uniform": made,
        "time_ratio": min(runs["render_s"]) / made["seconds"],
    }


def uniform_to_goal(loaded: Any, ref: np.ndarray, rects: list[Rect], args: argparse.Namespace) -> dict[str, Any]:
    """Plain Mitsuba at the uniform spp whose worst unit reaches TAU, under the cap: the spp
    a probe render predicts; where that render's worst unit misses TAU by more than REFINE_TOLERANCE (a
    64-spp probe under-reads a scene of rare bright paths), once more at the spp it predicts in turn
    (`next_spp`). The last render's spp and errors, the seconds of a second render at its spp (warm);
    each render's in `renders`."""
    tau = args.noise
    uniform(loaded, WARM_SPP, 1)  # the scene's first render, untimed
    probe_image, probe_s = uniform(loaded, args.probe_spp, PROBE_SEED)
    probe = reference_corrected(unit_relmse(probe_image, ref, rects), args.probe_spp, args.ref_spp)
    needed = needed_spp(args.probe_spp, float(probe.max()), tau)
    at: int | None = min(needed, args.spp)  # uniform sampling under the job's cap, as the job is
    renders: list[dict[str, Any]] = []
    while at is not None and len(renders) <= REFINE_RENDERS:
        image, seconds = uniform(loaded, at, UNIFORM_SEED + len(renders))
        raw = unit_relmse(image, ref, rects)
        true = reference_corrected(raw, at, args.ref_spp)
        renders.append({"spp": at, "predicted_spp": needed, "seconds": seconds,
                        "worst_over_tau": float(np.sqrt(true.max()) / tau),
                        "worst_raw_over_tau": float(np.sqrt(raw.max()) / tau),
                        "worst_unit": int(np.argmax(true)), "true_over_tau": (np.sqrt(true) / tau).tolist()})
        needed = renders[-1]["says_spp"] = needed_spp(at, float(true.max()), tau)
        at = next_spp(at, float(true.max()), tau, args.spp)
    last = renders[-1]
    # Timed once more at the chosen spp: Mitsuba compiles a kernel for some sample counts and not for
    # others (~0.4 s each), so only a second render at the same spp is sure to be warm.
    _, warm_s = uniform(loaded, last["spp"], UNIFORM_SEED + 100)
    capped = last["spp"] == args.spp and max(last["predicted_spp"], last["says_spp"]) > args.spp
    return {"probe_spp": args.probe_spp, "probe_s": probe_s, "probe_worst_over_tau": float(np.sqrt(probe.max()) / tau),
            "probe_predicted_spp": renders[0]["predicted_spp"], **last, "cold_seconds": last["seconds"],
            "seconds": warm_s, "capped": capped, "renders": renders}


# ---- the suite ----------------------------------------------------------------------------------------


def run(args: argparse.Namespace) -> dict[str, Any]:
    check_minimums(args, res=1, spp=1, units=1, probe_spp=1, ref_spp=1, threads=1, repeats=1)
    if not (args.noise > 0 and math.isfinite(args.noise)):
        raise QuekaroError(f"--noise {args.noise}: a positive relative error")
    started, load_before = time.perf_counter(), os.getloadavg()[0]
    chosen = [scene_from_argument(s) for s in args.scenes] if args.scenes else list(SUITE)
    if len(chosen) == 1:
        entry = chosen[0]
        scenes = {entry.name: {"role": entry.role, **measure_scene(suite_spec(entry, args.res), args)}}
    else:  # one process per scene, one after another: a crash costs one scene, and no two renders overlap
        scenes = {shown.name: _scene_in_child(e, args) for e, shown in zip(chosen, distinct(chosen), strict=True)}
    result = {"noise": args.noise, "spp_cap": args.spp, "res": args.res, "units": args.units,
              "probe_spp": args.probe_spp, "ref_spp": args.ref_spp, "threads": args.threads, "repeats": args.repeats,
              "scenes": scenes,
              **summary(scenes), "seconds": time.perf_counter() - started,
              "load": [load_before, os.getloadavg()[0]]}
    report = format_report(result)
    result["report"] = str(publish_markdown(args.out, "threshold", "Rendering to a noise threshold against uniform spp",
                                            command_of(args, "quekaro bench threshold"), report, show=not args.json))
    return result


def summary(scenes: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The two targets over every scene: the share of units within HONEST_FACTOR of their claim (all
    units pooled) and the median time ratio."""
    units = sum(s["progressive"]["units"] for s in scenes.values())
    honest = sum(s["progressive"]["honest"] for s in scenes.values())
    ratio = float(np.median([s["time_ratio"] for s in scenes.values()]))
    share = honest / units
    return {"honest_share": share, "honest_units": honest, "all_units": units, "median_time_ratio": ratio,
            "targets": [{"name": f"units whose true error is within {HONEST_FACTOR:g} x their claim",
                         "value": share, "limit": HONEST_SHARE, "pass": share >= HONEST_SHARE,
                         "shown": f"{share:.1%} ({honest} of {units}) (target >= {HONEST_SHARE:.0%})"},
                        {"name": "median render time, progressive / uniform", "value": ratio,
                         "limit": TIME_RATIO, "pass": ratio <= TIME_RATIO,
                         "shown": f"{ratio:.2f} (target <= {TIME_RATIO:g})"}]}


def _scene_in_child(entry: Any, args: argparse.Namespace) -> dict[str, Any]:
    """One scene's measurement by `quekaro bench threshold SCENE --json` in a process of its own."""
    name = entry.name if BY_NAME.get(entry.name) == entry else str(entry.path)  # a suite name, else the file
    with tempfile.TemporaryDirectory(prefix="quekaro-threshold-") as tmp:
        cmd = [sys.executable, "-m", "quekaro", "bench", "threshold", name, "--json", "--noise", repr(args.noise),
               "--spp", str(args.spp), "--res", str(args.res), "--units", str(args.units),
               "--probe-spp", str(args.probe_spp), "--ref-spp", str(args.ref_spp), "--threads", str(args.threads),
               "--repeats", str(args.repeats), "--cache-dir", str(args.cache_dir), "--out", tmp]
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if done.returncode != 0:
        raise QuekaroError(f"bench threshold {name}: exit {done.returncode}: {done.stderr.strip()[-800:]}")
    (scene,) = json.loads(done.stdout)["scenes"].values()
    return scene


def format_report(result: dict[str, Any]) -> str:
    tau = result["noise"]
    lines = [
        f"{result['res']} px wide, relative error goal TAU {tau:g}, spp cap {result['spp_cap']}, "
        f"{result['units']} units asked, reference {result['ref_spp']} spp, probe {result['probe_spp']} spp, "
        f"{result['threads']} threads; took {result['seconds']:.0f} s; load average (1 min) "
        f"{result['load'][0]:.1f} at the start, {result['load'][1]:.1f} at the end.",
        "",
        "Progressive: the whole `quekaro render --noise TAU --spp CAP` process (wall) and its render loop (its "
        "report's progressive seconds, with its kernels' compilation). Uniform: plain Mitsuba in one process "
        "at the spp its worst unit (the job's rectangles) needs for TAU as a probe render predicts it (under the "
        f"cap), predicted again from that render where its worst unit missed TAU by over {REFINE_TOLERANCE:.0%} "
        "(the probe's spp and error shown), timed warm (a second render at that spp); its worst unit's true error "
        f"checks the prediction. Times: the fastest of {result['repeats']} of each side, taken in turn (job, uniform, "
        "job, uniform); the first job's image is scored. True errors: sqrt(relMSE) "
        "per unit against the reference, less the reference's own noise (x R / (n + R)); uncorrected in brackets. "
        "A unit's claim: TAU, or its estimate where it stopped at the cap.",
        "",
        "| scene | role | TAU | progressive render s (wall) | its spp min/median/max | uniform spp needed "
        f"| uniform s | uniform worst true/TAU | time ratio | each run s, job / uniform "
        f"| units true <= {HONEST_FACTOR:g} claim | median / max true/TAU |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in result["scenes"].items():
        p, u = s["progressive"], s["uniform"]
        spp = p["spp_spread"]
        needed = str(u["spp"])
        if u["capped"]:
            needed += f" (needs {max(u['predicted_spp'], u['says_spp'])}, capped)"
        if len(u["renders"]) > 1:
            needed += f"; the probe's {u['probe_predicted_spp']} gave {u['renders'][0]['worst_over_tau']:.2f} TAU"
        cap = f", {p['at_cap']} at the cap" if p["at_cap"] else ""
        t, r = p["true_over_tau_spread"], p["raw_over_tau_spread"]
        lines.append(
            f"| {name} | {s['role']} | {tau:g} | {_s(p['render_s'])} ({_s(p['wall_s'])}) | "
            f"{spp['min']:.0f} / {spp['median']:.0f} / {spp['max']:.0f} | {needed} | {_s(u['seconds'])} | "
            f"{u['worst_over_tau']:.2f} ({u['worst_raw_over_tau']:.2f}) | {s['time_ratio']:.2f} | "
            f"{_runs(p['runs_s'])} / {_runs(u['runs_s'])} | "
            f"{p['honest']} of {p['units']}{cap} | {t['median']:.2f} / {t['max']:.2f} "
            f"({r['median']:.2f} / {r['max']:.2f}) |")
    lines.append("")
    lines += [f"target: {t['name']}: {t['shown']}: {'PASS' if t['pass'] else 'MISS'}" for t in result["targets"]]
    return "\n".join(lines)


def _runs(seconds: list[float]) -> str:
    return ", ".join(_s(t) for t in seconds)


def _s(seconds: float) -> str:
    """Seconds as the table shows them: tenths, hundredths under 10 s (a small image renders in 0.04 s)."""
    return f"{seconds:.1f}" if seconds >= 10 else f"{seconds:.2f}"
