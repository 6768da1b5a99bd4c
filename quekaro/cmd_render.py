"""`quekaro render`: the whole job in one process, exactly as the farm does it unit by unit, with
Mitsuba's own flags where they mean the same (-m, -t, -a, -s, -o, -D, several scenes in one call)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path

from rich.progress import BarColumn, Progress, ProgressColumn, Task, TextColumn, TimeElapsedColumn
from rich.text import Text

from core.errors import QuekaroError, did_you_mean
from core.image.imageio import read_image
from core.model.frames import FrameRange, frame_name
from core.model.integrators import CATALOGUE
from core.model.job import IMAGE_SUFFIXES, RenderOptions, SceneSpec
from core.model.levels import LEVELS, canonical
from core.scene.scene import check_parameters, parse_defines
from core.wording import count
from fuzzy.engine import DEFUZZIFIERS
from planning import budgets, progressive
from planning.accuracy import REF_SPP, Asked, accuracy_report, default_cache, reference_path
from planning.pipeline import Progress as RenderProgress
from planning.pipeline import render_job, write_json_atomic
from quekaro.cmd_diff import seam_line


def add_job_arguments(parser: argparse.ArgumentParser) -> None:
    """The options a job takes, shared by `render` and `submit`."""
    parser.add_argument("scenes", type=Path, nargs="+", metavar="SCENE",
                        help="Mitsuba 3 scene file(s) (XML); several render (or are submitted) one after another")
    parser.add_argument("-D", "--define", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                        help="set a scene parameter ($NAME), as Mitsuba's -D (repeatable); NAME=FIRST:LAST[:STEP] "
                             "renders a frame sequence, one image a frame (SCENE_0001.exr ...)")
    parser.add_argument("--opt", dest="level", type=canonical, choices=LEVELS, default="off",
                        help="optimisation level of the fuzzy rules, any case (off: the user's spp/depth everywhere)")
    parser.add_argument("--spp", type=int, help="predefined samples per pixel (default: the scene's)")
    add_asked_arguments(parser)
    parser.add_argument("--rules", type=Path,
                        help="rule file for this job (default: rules/pathtracing.xml; a farm job carries it to "
                             "the agents)")
    parser.add_argument("--defuzzifier", choices=DEFUZZIFIERS,
                        help="defuzzification of the rules' outputs (default: centroid; on a farm, each agent's own)")
    parser.add_argument("-m", "--mode", "--variant", dest="variant",
                        help="force the Mitsuba variant (e.g. llvm_ad_spectral; Mitsuba's -m)")
    parser.add_argument("--units", type=int,
                        help="target number of work units (default by size; level off: one, or about 256 px a side "
                             "with --noise or --time)")
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
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more: -v what the planning does, -vv everything (Mitsuba's -v)")


def add_asked_arguments(parser: argparse.ArgumentParser) -> None:
    """What a job computes besides its scene file, and where its files are: --depth, --integrator, -s, -a
    (shared by `render`, `submit` and `bench accuracy`)."""
    parser.add_argument("--depth", type=int, help="predefined path depth (default: from the effect analysis)")
    parser.add_argument("--integrator", type=integrator_type, metavar="TYPE",
                        help="replace the scene's integrator by this type (default: the scene's own, as written): "
                             + ", ".join(sorted(CATALOGUE)))
    parser.add_argument("-s", "--sensor", type=int, default=0, help="index of the sensor to render (Mitsuba's -s)")
    parser.add_argument("-a", dest="search_paths", action="append", default=[], metavar="PATH",
                        help="add folders to the file search path, searched last (Mitsuba's -a: repeatable, "
                             "and several in one separated by ';')")


def integrator_type(name: str) -> str:
    """--integrator's value: a type of Mitsuba's catalogue, or an error naming the closest."""
    if name not in CATALOGUE:
        raise argparse.ArgumentTypeError(f"{name!r} is not one of Mitsuba's integrators{did_you_mean(name, CATALOGUE)} "
                                         f"(known: {', '.join(sorted(CATALOGUE))})")
    return name


def options_from_args(args: argparse.Namespace):
    if args.rules is not None and not args.rules.is_file():  # before any complaint about the level
        raise QuekaroError(f"--rules {args.rules}: " + ("a folder, not a rule file" if args.rules.is_dir()
                                                        else "file not found"))
    options = RenderOptions(level=args.level, spp=args.spp, depth=args.depth,
                            threads=getattr(args, "threads", None), rules=args.rules,
                            defuzzifier=args.defuzzifier, variant=args.variant,
                            integrator=args.integrator, units=args.units, sensor=args.sensor,
                            adaptive=args.adaptive, denoise=args.denoise, noise=args.noise, time=args.time,
                            progressive=args.progressive)
    options.check_used()
    return options


def search_paths(args: argparse.Namespace) -> tuple[Path, ...]:
    """The -a folders (each -a may hold several, separated by ';'), each checked to exist (Mitsuba would
    silently search nothing)."""
    folders = [Path(part) for given in args.search_paths for part in str(given).split(";") if part]
    for folder in folders:
        if not folder.is_dir():
            raise QuekaroError(f"-a {folder}: not a folder")
    return tuple(folders)


def split_range(defines: dict[str, str]) -> tuple[dict[str, str], FrameRange | None]:
    """The -D parameters apart from the one frame range among them (NAME=FIRST:LAST[:STEP]), if any."""
    ranges = [r for r in (FrameRange.parse(name, value) for name, value in defines.items()) if r is not None]
    if len(ranges) > 1:
        raise QuekaroError(f"-D {ranges[0].define} and -D {ranges[1].define}: both are frame ranges; a sequence "
                           "numbers its frames by one parameter (give the other a single value)")
    if not ranges:
        return defines, None
    return {k: v for k, v in defines.items() if k != ranges[0].define}, ranges[0]


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("render", help="render scenes in one process (no agents)",
                            epilog="Ctrl-C in passes (--noise, --time, --progressive) stops the render and writes the "
                                   "image of the passes so far (exit status 130); a second Ctrl-C quits without it.")
    add_job_arguments(parser)
    parser.add_argument("-o", "--output", "--out", dest="out", type=Path, default=Path("out"),
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


def outputs(scenes: list[Path], out: Path, frames: FrameRange | None = None) -> list[Path]:
    """Where each scene's image goes: `out` itself for one scene named *.exr (*.pfm, *.rgbe; the film's
    file_format sets the suffix written), else `out`/SCENE.exr (refused when two scenes would write the
    same file, or when `out` names another image format). A frame range writes a folder's SCENE_0001.exr ..."""
    if out.suffix.lower() in (*OTHER_IMAGE_SUFFIXES, ".json") and not out.is_dir():
        raise QuekaroError(f"-o {out}: the image is written as its film's file_format asks (EXR, PFM or RGBE), "
                           f"with a PNG preview and the report beside it; give -o {out.with_suffix('.exr')} "
                           "or a folder")
    one_file = out.suffix.lower() in IMAGE_SUFFIXES and not out.is_dir()
    if one_file and frames is not None:
        raise QuekaroError(f"-o {out}: -D {frames.define}={frames.first}:{frames.last} renders {len(frames)} "
                           "frames, one image each (SCENE_0001.exr ...): give -o a folder")
    if len(scenes) == 1 and one_file:
        return [out]
    if one_file:
        raise QuekaroError(f"-o {out}: {len(scenes)} scenes need a folder, not one file")
    paths = [out / f"{scene.stem}.exr" for scene in scenes]
    clash = sorted({p.name for p in paths if paths.count(p) > 1})
    if clash:
        raise QuekaroError(f"-o {out}: several scenes would write {', '.join(clash)}; render them one at a time")
    return paths


def writable_outputs(scenes: list[Path], out: Path, frames: FrameRange | None = None) -> list[Path]:
    """`outputs`, each folder checked writable (`check_writable`) before any work: an image must not be
    lost at the end of its render."""
    targets = outputs(scenes, out, frames)
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
    defines, frames = split_range(parse_defines(args.defines))
    paths = search_paths(args)
    options = options_from_args(args)
    if args.ref_spp is not None and not args.report_accuracy:
        raise QuekaroError(f"--ref-spp {args.ref_spp}: the reference is rendered only with --report-accuracy")
    args.ref_spp = REF_SPP if args.ref_spp is None else args.ref_spp
    if args.ref_spp < 1:
        raise QuekaroError(f"--ref-spp {args.ref_spp}: must be at least 1")
    failed, written = [], 0
    wanted = len(args.scenes) * (len(frames.frames()) if frames else 1)
    for scene, out in zip(args.scenes, writable_outputs(args.scenes, args.out, frames), strict=True):
        try:
            for spec, image in frame_jobs(SceneSpec(scene, defines, paths), frames, out):
                render_one(spec, options, image, args, startup)
                startup, written = 0.0, written + 1
        except KeyboardInterrupt as exc:
            if wanted > 1:
                kept = written + isinstance(exc, Stopped)
                print(f"quekaro: Ctrl-C: {kept} of {wanted} images written, the rest not rendered", file=sys.stderr)
            raise
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


def frame_jobs(spec: SceneSpec, frames: FrameRange | None, out: Path) -> list[tuple[SceneSpec, Path]]:
    """The scene's job and image, or with a frame range each frame's (SCENE_0001.exr beside `out`), every -D
    checked against the scene's parameters first."""
    first = spec if frames is None else dataclasses.replace(spec, defines={**spec.defines,
                                                                            frames.define: str(frames.first)})
    check_parameters(first)
    if frames is None:
        return [(spec, out)]
    return [(dataclasses.replace(spec, defines={**spec.defines, frames.define: str(n)}),
             out.with_name(frame_name(spec.path.stem, n) + out.suffix)) for n in frames.frames()]


class Stopped(KeyboardInterrupt):
    """Ctrl-C stopped a job in passes after its image was written."""


def render_one(spec: SceneSpec, options: RenderOptions, out: Path, args: argparse.Namespace,
               startup: float) -> None:
    """One scene's job, its report printed (and its accuracy, with --report-accuracy: `startup` is the
    process's own start, which the first scene's wall time includes). A job in passes stopped by Ctrl-C
    writes its image and then raises Stopped, a KeyboardInterrupt (exit 130, as a shell's loop expects)."""
    started = time.perf_counter()
    with render_progress(spec.path.name, enabled=not args.no_progress) as progress:
        report = render_job(spec, options, out, progress=progress)
    print_report(report, out)
    if (progressive.report_part(report) or {}).get("interrupted"):
        raise Stopped  # its image is written; the scenes and frames after it are not rendered
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


class _Eta(ProgressColumn):
    """The time left: a time goal's own, counting down as the bar refreshes; else rich's estimate from the
    rate so far."""

    def render(self, task: Task) -> Text:
        ends_at = task.fields.get("ends_at")
        left = max(0.0, ends_at - time.monotonic()) if ends_at is not None else task.time_remaining
        return Text("-:--:--" if left is None else str(timedelta(seconds=round(left))), style="progress.remaining")


@contextmanager
def render_progress(name: str, enabled: bool = True) -> Iterator[Callable[[RenderProgress], None]]:
    """A rich progress bar over the samples rendered, with units done, mean spp done and the ETA."""
    if not enabled:
        yield lambda _p: None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[units]} units"),
               TextColumn("{task.fields[spp]} spp"), _Eta(), TimeElapsedColumn())
    with Progress(*columns, transient=False) as bar:
        task = bar.add_task(f"{name} planning", total=None, units="-", spp="-", ends_at=None)

        def update(p: RenderProgress) -> None:
            ends_at = None if p.seconds_left is None else time.monotonic() + p.seconds_left
            bar.update(task, description=name, total=p.samples_total, completed=p.samples_done, ends_at=ends_at,
                       units=f"{p.units_done}/{p.units_total}", spp=f"{p.samples_done / max(1, p.pixels):.0f}")

        yield update


def print_report(report: dict, out: Path) -> None:
    totals, effects = report["totals"], report["effects"]
    print(f"{report['image']['file']}  ({report['image']['width']}x{report['image']['height']}, "
          f"{len(report['image']['channels'])} channels, {count(totals['units'], 'unit')}, {totals['seconds']:.2f} s, "
          f"pre-pass {totals['prepass_seconds']:.2f} s)")
    print(f"effects: {effects['variant']} / {effects['integrator']} / max_depth {effects['max_depth']}")
    for reason in effects["reasons"]:
        print(f"  - {reason}")
    if report.get("adaptive"):
        print(f"adaptive: {budgets.describe(report['adaptive'])}")
    if passes := progressive.report_part(report):
        print(progressive.describe(passes))
    print(f"png: {report['image']['png']}  report: {out.with_suffix('.json')}")
    for line in report["image"].get("lossy", []):
        print(f"note: {line}")
    if totals["nonfinite"]:
        print(f"warning: {totals['nonfinite']} non-finite pixels were replaced (see the report's units)")
