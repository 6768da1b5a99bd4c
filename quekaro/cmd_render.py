"""`quekaro render`: the whole job in one process, exactly as the farm does it unit by unit, with
Mitsuba's own flags where they mean the same (-m, -t, -a, -s, -o, -D, several scenes in one call)."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from core.errors import QuekaroError
from core.image.imageio import read_image
from core.model.integrators import CATALOGUE
from core.model.job import IMAGE_SUFFIXES, RenderOptions, SceneSpec
from core.model.levels import LEVELS
from core.scene.scene import parse_defines
from fuzzy.engine import DEFUZZIFIERS
from planning import budgets
from planning.accuracy import REF_SPP, Asked, accuracy_report, default_cache, reference_path
from planning.pipeline import Progress as RenderProgress
from planning.pipeline import render_job, write_json_atomic
from quekaro.cmd_diff import seam_line


def add_job_arguments(parser: argparse.ArgumentParser) -> None:
    """The options a job takes, shared by `render` and `submit`."""
    parser.add_argument("scenes", type=Path, nargs="+", metavar="SCENE",
                        help="Mitsuba 3 scene file(s) (XML); several render (or are submitted) one after another")
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                        help="set a scene <default> parameter, as Mitsuba's -D (repeatable)")
    parser.add_argument("--opt", dest="level", choices=LEVELS, default="off",
                        help="optimisation level of the fuzzy rules (off: the user's spp/depth everywhere)")
    parser.add_argument("--spp", type=int, help="predefined samples per pixel (default: the scene's)")
    add_asked_arguments(parser)
    parser.add_argument("--rules", type=Path,
                        help="rule file for this job (default: rules/pathtracing.xml; a farm job carries it to "
                             "the agents)")
    parser.add_argument("--defuzzifier", choices=DEFUZZIFIERS,
                        help="defuzzification of the rules' outputs (default: centroid; on a farm, each agent's own)")
    parser.add_argument("-m", "--variant", help="force the Mitsuba variant (e.g. llvm_ad_spectral)")
    parser.add_argument("--units", type=int, help="target number of work units")
    parser.add_argument("--adaptive", action="store_true",
                        help="at a rule level: the rules set the level's samples, the pre-pass's noise shares them "
                             "among the units, and each unit renders half its share uniformly and the rest "
                             "per pixel where that first pass measured noise")
    parser.add_argument("--noise", type=float, metavar="TAU",
                        help="render in passes until every unit's estimated relative error (RMS, as relMSE's "
                             "square root) is under TAU, or it reaches --spp (the cap; default the scene's)")
    parser.add_argument("--time", type=float, metavar="SECONDS",
                        help="render in passes for SECONDS of rendering, each next pass where the measured noise "
                             "falls most per second; --spp caps every unit")
    parser.add_argument("--progressive", action="store_true",
                        help="render each unit's samples (yours, or the rules' at a rule level) in passes: on a farm "
                             "idle agents take extra passes of the last units, and the page's image fills as they land")
    parser.add_argument("--denoise", action="store_true",
                        help="denoise the image with Intel Open Image Denoise: the render reconstructs with a box "
                             "filter and adds the denoiser's albedo and normal; the raw image is kept as SCENE.raw.exr")


def add_asked_arguments(parser: argparse.ArgumentParser) -> None:
    """What a job computes besides its scene file, and where its files are: --depth, --integrator, -s, -a
    (shared by `render`, `submit` and `bench accuracy`)."""
    parser.add_argument("--depth", type=int, help="predefined path depth (default: from the effect analysis)")
    parser.add_argument("--integrator", choices=sorted(CATALOGUE),
                        help="replace the scene's integrator by this type (default: the scene's own, as written)")
    parser.add_argument("-s", "--sensor", type=int, default=0, help="index of the sensor to render (Mitsuba's -s)")
    parser.add_argument("-a", dest="search_paths", action="append", default=[], type=Path, metavar="PATH",
                        help="add a folder to the file search path, searched last (Mitsuba's -a; repeatable)")


def options_from_args(args: argparse.Namespace):
    options = RenderOptions(level=args.level, spp=args.spp, depth=args.depth,
                            threads=getattr(args, "threads", None), rules=args.rules,
                            defuzzifier=args.defuzzifier, variant=args.variant,
                            integrator=args.integrator, units=args.units, sensor=args.sensor,
                            adaptive=args.adaptive, denoise=args.denoise, noise=args.noise, time=args.time,
                            progressive=args.progressive)
    options.check_used()
    return options


def search_paths(args: argparse.Namespace) -> tuple[Path, ...]:
    """The -a folders, each checked to exist (Mitsuba would silently search nothing)."""
    for folder in args.search_paths:
        if not folder.is_dir():
            raise QuekaroError(f"-a {folder}: not a folder")
    return tuple(args.search_paths)


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("render", help="render scenes in one process (no agents)")
    add_job_arguments(parser)
    parser.add_argument("-o", "--out", type=Path, default=Path("out"),
                        help="output image file, or a folder for SCENE.exr (default: out/): its suffix is the "
                             "film's file_format's (.exr, .pfm, .rgbe), as Mitsuba names it; the PNG and the JSON "
                             "report go beside it; several scenes need a folder")
    parser.add_argument("-t", "--threads", type=int, help="Dr.Jit threads (Mitsuba's -t; default: all cores)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (e.g. in logs)")
    parser.add_argument("--report-accuracy", action="store_true",
                        help="afterwards, compare the image with a long plain-Mitsuba reference (cached) and with "
                             "plain Mitsuba at the spp taking the same wall time; printed and in the report")
    parser.add_argument("--ref-spp", type=int, default=None,
                        help=f"with --report-accuracy: the reference's spp (default {REF_SPP})")
    parser.set_defaults(func=run)


# Image formats no film writes (core.model.job.IMAGE_SUFFIXES are those it does): `-o picture.png`
# would otherwise become a folder named picture.png.
OTHER_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".hdr", ".tga", ".bmp", ".tif", ".tiff", ".webp")


def outputs(scenes: list[Path], out: Path) -> list[Path]:
    """Where each scene's image goes: `out` itself for one scene named *.exr (*.pfm, *.rgbe; the film's
    file_format sets the suffix written), else `out`/SCENE.exr (refused when two scenes would write the
    same file, or when `out` names another image format)."""
    if out.suffix.lower() in (*OTHER_IMAGE_SUFFIXES, ".json") and not out.is_dir():
        raise QuekaroError(f"-o {out}: the image is written as its film's file_format asks (EXR, PFM or RGBE), "
                           f"with a PNG preview and the report beside it; give -o {out.with_suffix('.exr')} "
                           "or a folder")
    if len(scenes) == 1 and out.suffix.lower() in IMAGE_SUFFIXES and not out.is_dir():
        return [out]
    if out.suffix.lower() in IMAGE_SUFFIXES and not out.is_dir():
        raise QuekaroError(f"-o {out}: {len(scenes)} scenes need a folder, not one file")
    paths = [out / f"{scene.stem}.exr" for scene in scenes]
    clash = sorted({p.name for p in paths if paths.count(p) > 1})
    if clash:
        raise QuekaroError(f"-o {out}: several scenes would write {', '.join(clash)}; render them one at a time")
    return paths


def writable_outputs(scenes: list[Path], out: Path) -> list[Path]:
    """`outputs`, each folder checked writable (`check_writable`) before any work: an image must not be
    lost at the end of its render."""
    targets = outputs(scenes, out)
    for folder in dict.fromkeys(path.parent for path in targets):
        check_writable(folder, out)
    return targets


def check_writable(folder: Path, out: Path) -> None:
    """Create `folder` if needed and write a file in it, or say why -o `out` cannot be written."""
    if folder.exists() and not folder.is_dir():
        raise QuekaroError(f"-o {out}: {folder} is a file, not a folder (an image's name ends .exr, .pfm or .rgbe)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".quekaro-write-check-"):
            pass
    except OSError as exc:
        raise QuekaroError(f"-o {out}: cannot write in {folder} ({exc.strerror or exc})") from exc


def run(args: argparse.Namespace) -> int:
    startup = process_age()  # the interpreter's start and imports, paid once, by the first scene
    defines, paths = parse_defines(args.defines), search_paths(args)
    options = options_from_args(args)
    if args.ref_spp is not None and not args.report_accuracy:
        raise QuekaroError(f"--ref-spp {args.ref_spp}: the reference is rendered only with --report-accuracy")
    args.ref_spp = REF_SPP if args.ref_spp is None else args.ref_spp
    if args.ref_spp < 1:
        raise QuekaroError(f"--ref-spp {args.ref_spp}: must be at least 1")
    failed = []
    for scene, out in zip(args.scenes, writable_outputs(args.scenes, args.out), strict=True):
        try:
            render_one(SceneSpec(scene, defines, paths), options, out, args, startup)
        except QuekaroError as exc:
            if len(args.scenes) == 1:
                raise
            print(f"quekaro: error: {exc}", file=sys.stderr)  # one bad scene does not stop the others
            failed.append(str(scene))
        startup = 0.0
    if failed:
        print(f"quekaro: error: {len(failed)} of {len(args.scenes)} scenes failed: {', '.join(failed)}",
              file=sys.stderr)
        return 2
    return 0


def render_one(spec: SceneSpec, options: RenderOptions, out: Path, args: argparse.Namespace,
               startup: float) -> None:
    """One scene's job, its report printed (and its accuracy, with --report-accuracy: `startup` is the
    process's own start, which the first scene's wall time includes)."""
    started = time.perf_counter()
    with render_progress(spec.path.name, enabled=not args.no_progress) as progress:
        report = render_job(spec, options, out, progress=progress)
    print_report(report, out)
    if args.report_accuracy:
        add_accuracy(report, spec, out, time.perf_counter() - started + startup, args)


def process_age() -> float:
    """Seconds since this process started (Linux /proc), 0 where that cannot be read."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return max(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 0.0)
    except (OSError, ValueError, IndexError):
        return 0.0


def add_accuracy(report: dict, spec: SceneSpec, out: Path, wall: float, args: argparse.Namespace) -> None:
    """`planning.accuracy`'s comparison, printed and written into OUT.json under "accuracy"."""
    cached = reference_path(spec, args.ref_spp, default_cache(), report["effects"]["variant"],
                            Asked.of_report(report)).exists()
    print(f"accuracy: reference {args.ref_spp} spp ({'cached' if cached else 'rendering it, then cached'}), "
          f"uniform spp for {wall:.2f} s ...")
    image = read_image(report["image"]["file"])
    try:
        accuracy = accuracy_report(spec, image, wall, report, args.threads or os.cpu_count() or 1, args.ref_spp)
    except QuekaroError as exc:  # the job's image and report are written: say whose comparison failed
        raise QuekaroError(f"{spec.path}: --report-accuracy: {exc}") from exc
    report["accuracy"] = accuracy
    write_json_atomic(out.with_suffix(".json"), report)
    uniform, seams = accuracy["uniform"], accuracy["seams"]
    print(f"  this job   {wall:7.2f} s  mean pixel diff {accuracy['mean_pixel_diff_percent']:.3f} %  "
          f"relMSE {accuracy['relmse']:.5f}")
    print(f"  uniform    {uniform['seconds']:7.2f} s  mean pixel diff {uniform['mean_pixel_diff_percent']:.3f} %  "
          f"relMSE {uniform['relmse']:.5f}  ({uniform['spp']} spp, plain Mitsuba)")
    print(f"  relMSE ratio {accuracy['relmse'] / max(uniform['relmse'], 1e-30):.3f} (below 1: the job wins); seams: "
          + seam_line(seams))
    if accuracy["reference_warning"]:
        print(f"warning: {accuracy['reference_warning']}")


@contextmanager
def render_progress(name: str, enabled: bool = True) -> Iterator[Callable[[RenderProgress], None]]:
    """A rich progress bar over the samples rendered, with units done, mean spp done and the ETA."""
    if not enabled:
        yield lambda _p: None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[units]} units"),
               TextColumn("{task.fields[spp]} spp"), TimeRemainingColumn(), TimeElapsedColumn())
    with Progress(*columns, transient=False) as bar:
        task = bar.add_task(f"{name} planning", total=None, units="-", spp="-")

        def update(p: RenderProgress) -> None:
            bar.update(task, description=name, total=p.samples_total, completed=p.samples_done,
                       units=f"{p.units_done}/{p.units_total}", spp=f"{p.samples_done / max(1, p.pixels):.0f}")

        yield update


def print_report(report: dict, out: Path) -> None:
    totals, effects = report["totals"], report["effects"]
    print(f"{report['image']['file']}  ({report['image']['width']}x{report['image']['height']}, "
          f"{len(report['image']['channels'])} channels, {totals['units']} units, {totals['seconds']:.2f} s, "
          f"pre-pass {totals['prepass_seconds']:.2f} s)")
    print(f"effects: {effects['variant']} / {effects['integrator']} / max_depth {effects['max_depth']}")
    for reason in effects["reasons"]:
        print(f"  - {reason}")
    if report.get("adaptive"):
        print(f"adaptive: {budgets.describe(report['adaptive'])}")
    print(f"png: {report['image']['png']}  report: {out.with_suffix('.json')}")
    for line in report["image"].get("lossy", []):
        print(f"note: {line}")
    if totals["nonfinite"]:
        print(f"warning: {totals['nonfinite']} non-finite pixels were replaced (see the report's units)")
