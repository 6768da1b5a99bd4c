"""`quekaro bench overhead`: what a `quekaro render` job costs over the `mitsuba` command rendering as many
samples.

Per level (`--levels`, default off; `--adaptive` for the optimised ones), `_level_row` alternates fresh
processes: the whole `quekaro render` process (bench.accuracy's in-process runner) and the `mitsuba` command
at the job's mean spp (`-D spp=N`), in the job's variant, and splits the job's time by its report.
The command runs on every core: its `-t N` hangs at or below the core count (Mitsuba 3.9.1 here), so the
job's threads must be the machine's cores.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.accuracy import inprocess_runner, parse_levels
from bench.provenance import rules_for
from bench.report import DEFAULT_OUT, command_of, publish_markdown
from core.errors import QuekaroError
from core.image.imageio import read_image
from core.model.job import SceneSpec
from core.scene.scene import parse_defines, read
from planning.accuracy import job_variant

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = REPO / "scenes" / "cbox.xml"
DEFAULT_RES = 512
OFF_TARGET = 1.03  # level off: quekaro render / the mitsuba command, whole processes, a render of ~17 s
SPP_PARAMETER = "spp"  # the scene parameter the command's -D sets the spp through


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                        help="a scene parameter, as Mitsuba's -D (after --res)")
    parser.add_argument("--res", type=int, default=None,
                        help=f"scene parameter res (the image side); default {DEFAULT_RES} for the default scene, "
                             "a file's own size otherwise")
    parser.add_argument("--spp", type=int, default=256, help="the user's spp (what level off renders)")
    parser.add_argument("--threads", type=int, default=os.cpu_count(),
                        help="the job's Dr.Jit threads: the machine's cores, as the mitsuba command runs")
    parser.add_argument("--levels", default="off", help="comma list of optimisation levels")
    parser.add_argument("--adaptive", action="store_true", help="the optimised levels as adaptive jobs")
    parser.add_argument("--repeats", type=int, default=2, help="timed runs of each side per level (fastest counts)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for overhead.md")


def rules_file(args: argparse.Namespace) -> Path | None:
    """The rule file the levels planned with (bench.commands records its hash)."""
    return rules_for(args, parse_levels(args.levels))


def run(args: argparse.Namespace) -> dict[str, Any]:
    if args.repeats < 1:
        raise QuekaroError(f"--repeats {args.repeats}: at least one timed run")
    if args.threads != os.cpu_count():
        raise QuekaroError(f"--threads {args.threads}: the mitsuba command renders on all {os.cpu_count()} cores "
                           "(its own -t hangs at or below the core count in Mitsuba 3.9.1), so the job must too")
    res = args.res or (DEFAULT_RES if args.scene == DEFAULT_SCENE else None)
    spec = SceneSpec(args.scene, {**({"res": str(res)} if res else {}), **parse_defines(args.defines)})
    _check_spp_parameter(spec)
    levels = parse_levels(args.levels)
    variant = job_variant(spec)
    with tempfile.TemporaryDirectory(prefix="quekaro-overhead-") as tmp, \
            inprocess_runner(args.threads, adaptive=args.adaptive) as run_job:
        rows = [_level_row(run_job, spec, variant, level, args, Path(tmp)) for level in levels]
    result = {"scene": str(args.scene), "defines": spec.defines, "spp": args.spp, "threads": args.threads,
              "variant": variant, "adaptive": args.adaptive, "repeats": args.repeats, "levels": rows}
    result["report"] = str(publish_markdown(args.out, "overhead", "Pipeline overhead against plain Mitsuba",
                                            command_of(args, _command(args)), format_report(result),
                                            show=not args.json))
    return result


def _check_spp_parameter(spec: SceneSpec) -> None:
    """QuekaroError where the scene takes no `spp` parameter: the command's only way to set the spp."""
    if SPP_PARAMETER not in read(spec).referenced:
        raise QuekaroError(f"{spec.path}: the mitsuba command sets the spp through a scene parameter, and this "
                           f"scene has no ${SPP_PARAMETER} (give its sampler sample_count=\"${SPP_PARAMETER}\")")


def mitsuba_command(spec: SceneSpec, spp: int, variant: str, tmp: Path) -> tuple[Any, float]:
    """The `mitsuba` command beside this Python on the scene at `spp` in `variant`, with the scene's -D
    parameters and search folders, on every core: (the image it wrote, wall seconds of its whole process)."""
    out = tmp / "mitsuba.exr"
    for old in tmp.glob("mitsuba.*"):
        old.unlink()
    command = Path(sys.executable).parent / "mitsuba"
    if not command.is_file():
        raise QuekaroError(f"no mitsuba command at {command} (the mitsuba package installs it beside Python)")
    defines = {**spec.defines, SPP_PARAMETER: str(spp)}
    cmd = [str(command), "-m", variant, "-o", str(out),
           *(f"-D{k}={v}" for k, v in defines.items()),
           *(arg for folder in spec.search_paths for arg in ("-a", str(folder))), str(spec.path)]
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    written = sorted(tmp.glob("mitsuba.*"))  # the film's own format: a PFM film writes mitsuba.pfm
    if done.returncode != 0 or not written:
        raise QuekaroError(f"the mitsuba command on {spec.path} failed: {(done.stderr or done.stdout).strip()[-600:]}")
    return read_image(written[0]), seconds


def _level_row(run_job: Any, spec: SceneSpec, variant: str, level: str, args: argparse.Namespace,
               tmp: Path) -> dict[str, Any]:
    """One level: the job and the mitsuba command at the job's mean spp (its samples over its pixels), each
    run once to warm Dr.Jit's kernel cache, then alternating `--repeats` times; the fastest of each counts.
    The job's time splits into: outside the job (process start, imports, exit), the pre-pass, the units'
    render seconds, and the rest (analysis, planning, the render process's start and variant, composition,
    writing)."""
    out = tmp / f"{level}.exr"
    report, _, _ = run_job(spec, level, args.spp, out)  # warm-up; it also fixes the spp plain renders
    width, height = (int(v) for v in (report["image"]["width"], report["image"]["height"]))
    spp = max(1, round(report["totals"]["samples"] / (width * height)))
    mitsuba_command(spec, spp, variant, tmp)  # warm-up
    ours, plain = [], []
    for _ in range(args.repeats):
        report, wall, _ = run_job(spec, level, args.spp, out)
        ours.append((wall, report))
        plain.append(mitsuba_command(spec, spp, variant, tmp))
    wall, report = min(ours, key=lambda pair: pair[0])
    plain_pixels, plain_s = min(plain, key=lambda pair: pair[1])
    totals = report["totals"]
    job_s, render_s, prepass_s = (float(totals.get(k, 0.0)) for k in ("seconds", "render_seconds", "prepass_seconds"))
    ours_mean = float(read_image(report["image"]["file"])[..., :3].mean())
    plain_mean = float(plain_pixels[..., :3].mean())
    return {
        "level": level, "spp": spp, "units": int(totals["units"]), "plain_seconds": plain_s, "quekaro_seconds": wall,
        "ratio": wall / plain_s, "outside_job_seconds": wall - job_s, "prepass_seconds": prepass_s,
        "render_seconds": render_s, "rest_seconds": job_s - render_s - prepass_s,
        "plain_runs": [s for _, s in plain], "quekaro_runs": [s for s, _ in ours],
        "mean_rel_diff": abs(ours_mean - plain_mean) / max(abs(plain_mean), 1e-12),
    }


def _command(args: argparse.Namespace) -> str:
    parts = ["quekaro bench overhead", f"--levels {args.levels}", f"--spp {args.spp}"]
    parts += [f"--scene {args.scene}"] if args.scene != DEFAULT_SCENE else []
    parts += [f"--res {args.res}"] if args.res else []
    parts += [f"-D {d}" for d in args.defines] + (["--adaptive"] if args.adaptive else [])
    return " ".join(parts)


def format_report(r: dict[str, Any]) -> str:
    """The table, one row per level, and level off's target line when it was measured."""
    name = Path(r["scene"]).name
    lines = [f"{name} {r['defines']}, user spp {r['spp']}, {r['threads']} threads, {r['variant']}"
             f"{', adaptive' if r['adaptive'] else ''}; fastest of {r['repeats']} runs after a warm-up, "
             "each side a whole process", "",
             "| level | spp | units | mitsuba command s | quekaro render s | ratio | outside the job s | pre-pass s "
             "| units' render s | rest of the job s | means' rel. diff |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in r["levels"]:
        lines.append(f"| {row['level']} | {row['spp']} | {row['units']} | {row['plain_seconds']:.2f} | "
                     f"{row['quekaro_seconds']:.2f} | {row['ratio']:.3f} | {row['outside_job_seconds']:.2f} | "
                     f"{row['prepass_seconds']:.2f} | {row['render_seconds']:.2f} | {row['rest_seconds']:.2f} | "
                     f"{row['mean_rel_diff']:.4f} |")
    off = [row for row in r["levels"] if row["level"] == "off"]
    if off:
        ratio = off[0]["ratio"]
        lines += ["", f"target: level off quekaro render / the mitsuba command <= {OFF_TARGET}: {ratio:.3f} "
                      f"{'PASS' if ratio <= OFF_TARGET else 'MISS'}"]
    return "\n".join(lines)
