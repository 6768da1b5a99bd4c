"""`quekaro diff A.exr B.exr`: compare an image with a reference (paper metric, RMSE, relMSE, FLIP), and
with `--units REPORT.json` measure seams at the units' borders (core.image.seams)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import QuekaroError
from core.image import imageio, metrics
from core.image.seams import SEAM_WIDTH, seam_measure
from core.model.geometry import Rect


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "diff", help="compare an image with a reference: mean pixel difference %%, RMSE, relMSE, FLIP",
        description="Compare TEST.exr with REFERENCE.exr. The mean pixel difference is the paper's metric "
                    "(mean per-pixel colour difference of the sRGB display values, in percent).",
    )
    parser.add_argument("test", help="the image to judge (EXR)")
    parser.add_argument("reference", help="the reference image (EXR)")
    parser.add_argument("-o", "--output", help="write the per-pixel difference as a grey PNG here")
    parser.add_argument("--json", action="store_true", help="print the metrics as one JSON object")
    parser.add_argument("--units", metavar="REPORT.json",
                        help="a job's report (quekaro render or quekaro result): measure seams at its units' borders")
    parser.add_argument("--seam-width", type=int, default=None,
                        help=f"with --units: pixels on each side of a border (default {SEAM_WIDTH})")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.seam_width is not None and not args.units:
        raise QuekaroError(f"--seam-width {args.seam_width}: seams are measured only at a job's unit borders "
                           "(--units REPORT.json)")
    if args.seam_width is not None and args.seam_width < 1:
        raise QuekaroError(f"--seam-width {args.seam_width}: at least one pixel on each side of a border")
    if args.output and Path(args.output).suffix.lower() != ".png":
        raise QuekaroError(f"-o {args.output}: the difference image is written as a PNG; give a name ending .png")
    (test, kind), (reference, ref_kind) = imageio.read_colour(args.test), imageio.read_colour(args.reference)
    if kind != ref_kind:
        raise QuekaroError(f"{args.test} holds {_colour_words(kind)} and {args.reference} {_colour_words(ref_kind)}: "
                           "the metrics compare channel by channel, so both images must hold the same colour "
                           "(render both with one film pixel format)")
    try:
        results = metrics.all_metrics(test, reference)
    except imageio.ImageError as exc:  # it says which image ("test image", "reference image"), not the file
        raise QuekaroError(f"{args.test} against {args.reference}: {exc}") from exc
    if args.output:
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)  # as render -o and result -o do
        imageio.write_png(args.output, _grey_as_display(metrics.diff_image(test, reference)))
        results["diff_png"] = args.output
    if args.units:
        rects = read_unit_rects(args.units, test.shape[1], test.shape[0])
        results["seams"] = seam_measure(test, reference, rects,
                                        args.seam_width if args.seam_width is not None else SEAM_WIDTH).to_dict()
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(f"mean pixel difference: {results['mean_pixel_diff_percent']:.3f} %")
        print(f"RMSE:                  {results['rmse']:.6g}")
        print(f"relative MSE:          {results['relmse']:.6g}")
        print(f"FLIP (HDR, mean):      {results['flip']:.4f}")
        if "seams" in results:
            print(f"seams:                 {seam_line(results['seams'])}")
    return 0


def _grey_as_display(grey: Any) -> Any:
    """The difference image (display units) as linear values whose sRGB PNG shows that grey."""
    # write_png sRGB-encodes; decode first so the PNG's pixel value equals the difference itself.
    g = np.clip(grey, 0.0, 1.0)
    linear = np.where(g <= 0.04045, g / 12.92, ((g + 0.055) / 1.055) ** 2.4)
    return linear.astype(np.float32)


def _colour_words(kind: str) -> str:
    return {"RGB": "R, G, B", "XYZ": "X, Y, Z", "Y": "luminance (Y) only"}[kind]


def read_unit_rects(path: str, width: int, height: int) -> list[Rect]:
    """The units' rectangles from a job report's `units` list, refused unless the report's image is
    width x height (another image's units would put borders where that image has none)."""
    try:
        report = json.loads(Path(path).read_text())
        rects = [Rect.from_list(u["rect"]) for u in report["units"]]
        size = (int(report["image"]["width"]), int(report["image"]["height"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise QuekaroError(f"--units {path}: not a job report with units, their rects and its image's size "
                           f"({exc})") from exc
    if size != (width, height):
        raise QuekaroError(f"--units {path}: its job's image is {size[0]}x{size[1]}, the images compared are "
                           f"{width}x{height}")
    return rects


def seam_line(seams: dict[str, Any]) -> str:
    verdict = "SEAM" if seams["seam"] else "no seam"
    if seams["worst_unit"] < 0:  # one unit: no border between units to measure
        return f"{verdict} (no border between units)"
    return (f"{verdict} (steps across borders: z^2 {seams['ratio']:.2f}x noise, z {seams['z']:.1f}; "
            f"worst unit {seams['worst_unit']} z {seams['unit_z']:.1f} of {seams['unit_threshold']:.1f})")
