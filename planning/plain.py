"""Plain Mitsuba, as a user runs it: one process that imports Mitsuba, loads the scene, renders it at a
given spp and writes an EXR. `planning.accuracy` times this whole process for its uniform baseline, so that
it pays the same start-up as the `quekaro render` process it is compared with.

    python -m planning.plain SCENE.xml -D name=value ... -a FOLDER ... --spp N --seed S -t THREADS \\
        [-s SENSOR] [--integrator TYPE] [--depth N] -o OUT.exr
"""

from __future__ import annotations

import argparse
import sys

import mitsuba as mi
import numpy as np

from core.errors import QuekaroError
from core.image.film import film_channels
from core.image.imageio import write_exr
from core.model import integrators
from core.model.job import SceneSpec
from core.scene.scene import expand, load, sensor_of


def main(argv: list[str] | None = None) -> int:
    """Render what the job was asked to: the scene with its -D parameters and search folders, the sensor
    (Mitsuba's -s), and the user's integrator type and max_depth where the job overrode them, built as each
    unit builds them (core.render.process.integrator_for)."""
    parser = argparse.ArgumentParser(prog="python -m planning.plain", description=__doc__)
    parser.add_argument("scene")
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("-a", dest="search_paths", action="append", default=[], metavar="FOLDER")
    parser.add_argument("--spp", type=int, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("-t", "--threads", type=int, default=2)
    parser.add_argument("-m", "--variant", default="llvm_ad_rgb")
    parser.add_argument("-s", "--sensor", type=int, default=0)
    parser.add_argument("--integrator", default=None)
    parser.add_argument("--depth", type=int, default=None)
    parser.add_argument("-o", "--output", required=True)
    args = parser.parse_args(argv)
    spec = SceneSpec(args.scene, dict(d.split("=", 1) for d in args.defines), tuple(args.search_paths))
    scene = load(spec, args.variant, args.threads)
    try:
        sensor_of(scene, args.sensor, args.scene)
    except QuekaroError as exc:  # as `quekaro render -s` says it, not an IndexError from mi.render
        print(f"error: {exc}", file=sys.stderr)
        return 2
    integrator = None  # the scene's own, as a user's plain render takes it
    if args.integrator or args.depth is not None:
        # Imported only here (~60 ms): the timed process imports what a user's plain render needs.
        from core.render.process import integrator_for

        elem = integrators.scene_element(expand(spec).root)
        integrator = integrator_for(args.integrator, args.depth, elem, integrators.depth_of(elem))
    mi.render(scene, sensor=args.sensor, integrator=integrator, spp=args.spp, seed=args.seed)
    # R, G, B as a job's image is read back (core.image.film.film_channels: a luminance film's Y thrice).
    image, _ = film_channels(scene.sensors()[args.sensor].film())
    write_exr(args.output, np.ascontiguousarray(image[..., :3]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
