"""Plain Mitsuba, as a user runs it: one process that imports Mitsuba, loads the scene, renders it at a
given spp and writes an EXR. `planning.accuracy` times this whole process for its uniform baseline, as
`quekaro bench accuracy` times the whole `quekaro render` process, so both pay the same start-up.

    python -m planning.plain SCENE.xml -D name=value ... --spp N --seed S -t THREADS -o OUT.exr

The film's RGB is written (the accuracy metrics compare RGB). The scene's own integrator, sensor 0.
"""

from __future__ import annotations

import argparse
import sys

import mitsuba as mi
import numpy as np

from core.model.job import SceneSpec
from core.render.imageio import write_exr
from core.render.scene import load


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m planning.plain", description=__doc__)
    parser.add_argument("scene")
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--spp", type=int, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("-t", "--threads", type=int, default=2)
    parser.add_argument("-m", "--variant", default="llvm_ad_rgb")
    parser.add_argument("-o", "--output", required=True)
    args = parser.parse_args(argv)
    defines = dict(d.split("=", 1) for d in args.defines)
    scene = load(SceneSpec(args.scene, defines), args.variant, args.threads)
    image = np.array(mi.render(scene, spp=args.spp, seed=args.seed), dtype=np.float32)
    write_exr(args.output, np.ascontiguousarray(image[..., :3]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
