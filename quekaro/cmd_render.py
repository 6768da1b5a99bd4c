"""`quekaro render`: the whole job in one process, exactly as the farm does it unit by unit."""

from __future__ import annotations

import argparse
from pathlib import Path

from core.errors import QuekaroError
from core.model.integrators import CATALOGUE
from core.model.job import RenderOptions, SceneSpec
from core.render.scene import parse_defines
from fuzzy.engine import DEFUZZIFIERS
from fuzzy.levels import LEVELS
from planning.pipeline import render_job


def add_job_arguments(parser: argparse.ArgumentParser) -> None:
    """The options a job takes, shared by `render` and `submit`."""
    parser.add_argument("scene", type=Path, help="Mitsuba 3 scene file (XML)")
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                        help="set a scene <default> parameter, as Mitsuba's -D (repeatable)")
    parser.add_argument("--opt", dest="level", choices=LEVELS, default="off",
                        help="optimisation level of the fuzzy rules (off: the user's spp/depth everywhere)")
    parser.add_argument("--spp", type=int, help="predefined samples per pixel (default: the scene's)")
    parser.add_argument("--depth", type=int, help="predefined path depth (default: from the effect analysis)")
    parser.add_argument("--rules", type=Path,
                        help="rule file for this job (default: rules/pathtracing.xml; a farm job carries it to "
                             "the agents)")
    parser.add_argument("--defuzzifier", choices=DEFUZZIFIERS,
                        help="defuzzification of the rules' outputs (default: centroid; on a farm, each agent's own)")
    parser.add_argument("-m", "--variant", help="force the Mitsuba variant (e.g. llvm_ad_spectral)")
    parser.add_argument("--integrator", choices=sorted(CATALOGUE),
                        help="replace the scene's integrator by this type (default: the scene's own, as written)")
    parser.add_argument("--units", type=int, help="target number of work units")
    parser.add_argument("-s", "--sensor", type=int, default=0, help="index of the sensor to render (Mitsuba's -s)")
    parser.add_argument("-a", dest="search_paths", action="append", default=[], type=Path, metavar="PATH",
                        help="add a folder to the file search path, searched last (Mitsuba's -a; repeatable)")


def options_from_args(args: argparse.Namespace):
    return RenderOptions(level=args.level, spp=args.spp, depth=args.depth,
                         threads=getattr(args, "threads", None), rules=args.rules,
                         defuzzifier=args.defuzzifier, variant=args.variant,
                         integrator=args.integrator, units=args.units, sensor=args.sensor)


def search_paths(args: argparse.Namespace) -> tuple[Path, ...]:
    """The -a folders, each checked to exist (Mitsuba would silently search nothing)."""
    for folder in args.search_paths:
        if not folder.is_dir():
            raise QuekaroError(f"-a {folder}: not a folder")
    return tuple(args.search_paths)


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("render", help="render a scene in one process (no agents)")
    add_job_arguments(parser)
    parser.add_argument("-o", "--out", type=Path, default=Path("out/render.exr"),
                        help="output EXR; the PNG and the JSON report go beside it")
    parser.add_argument("--threads", type=int, help="Dr.Jit threads (default: QUEKARO_THREADS or all cores)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:

    spec = SceneSpec(args.scene, parse_defines(args.defines), search_paths(args))
    report = render_job(spec, options_from_args(args), args.out)
    totals, effects = report["totals"], report["effects"]
    print(f"{report['image']['exr']}  ({report['image']['width']}x{report['image']['height']}, "
          f"{len(report['image']['channels'])} channels, {totals['units']} units, {totals['seconds']:.2f} s, "
          f"pre-pass {totals['prepass_seconds']:.2f} s)")
    print(f"effects: {effects['variant']} / {effects['integrator']} / max_depth {effects['max_depth']}")
    for reason in effects["reasons"]:
        print(f"  - {reason}")
    print(f"png: {report['image']['png']}  report: {Path(args.out).with_suffix('.json')}")
    if totals["nonfinite"]:
        print(f"warning: {totals['nonfinite']} non-finite pixels were replaced (see the report's units)")
    return 0
