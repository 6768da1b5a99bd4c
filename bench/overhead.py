"""`quekaro bench overhead`: what the pipeline costs over one plain Mitsuba render.

Both sides run as fresh processes, alternating, in one run: (a) a plain render (load the scene,
`mi.render` the whole image with the same integrator, depth, spp and threads, write an EXR), and
(b) `quekaro render --opt off` of the same job (effect analysis, units in a child process,
composition, EXR + PNG + report). The ratio is min(b) / min(a) over the repeats; the images must
agree up to noise. Target: ratio <= 1.05 for a ~20 s render.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.report import DEFAULT_OUT, write_report
from core.model.job import SceneSpec
from core.render.effects import analyse
from core.render.imageio import read_exr
from core.render.metrics import relmse

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.render.mitsuba_env), and processes that never render must not pay for it.

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = REPO / "scenes" / "cbox.xml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--res", type=int, default=512, help="image side (scene parameter res)")
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for overhead.md")


def _timed(cmd: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO, capture_output=True)
    return time.perf_counter() - start


def run(args: argparse.Namespace) -> dict:

    defines = {"res": str(args.res), "spp": str(args.spp)}
    effects = analyse(SceneSpec(args.scene, defines))
    with tempfile.TemporaryDirectory() as tmp:
        plain_out, farm_out = Path(tmp) / "plain.exr", Path(tmp) / "quekaro.exr"
        plain_cmd = [sys.executable, "-m", "bench.plain", str(args.scene), "--spp", str(args.spp), "-t",
                     str(args.threads), "-o", str(plain_out), *(f"-D{k}={v}" for k, v in defines.items())]
        ours_cmd = [sys.executable, "-m", "quekaro", "render", str(args.scene), "--opt", "off", "--spp",
                    str(args.spp), "--threads", str(args.threads), "-o", str(farm_out)]
        ours_cmd += [arg for k, v in defines.items() for arg in ("-D", f"{k}={v}")]
        _timed(plain_cmd)  # warm the kernel cache for both (same kernels are not shared: warm each)
        _timed(ours_cmd)
        plain_s, ours_s = [], []
        for _ in range(args.repeats):
            plain_s.append(_timed(plain_cmd))
            ours_s.append(_timed(ours_cmd))
        a, b = read_exr(plain_out), read_exr(farm_out)
        report = json.loads(farm_out.with_suffix(".json").read_text())
    result = {
        "scene": str(args.scene), "res": args.res, "spp": args.spp, "threads": args.threads,
        "integrator": effects.integrator, "max_depth": effects.max_depth, "units": report["totals"]["units"],
        "plain_seconds": min(plain_s), "quekaro_seconds": min(ours_s), "ratio": min(ours_s) / min(plain_s),
        "plain_all": plain_s, "quekaro_all": ours_s,
        "mean_plain": float(a.mean()), "mean_quekaro": float(b.mean()), "relmse_between": relmse(b, a),
        "mean_rel_diff": float(abs(a.mean() - b.mean()) / max(a.mean(), 1e-12)),
    }
    text = format_report(result)
    write_report(args.out, "overhead", "Pipeline overhead against plain Mitsuba", text, "quekaro bench overhead")
    if not args.json:
        print(text)
    return result


def format_report(r: dict) -> str:
    def runs(key: str) -> str:
        return ", ".join(f"{s:.2f}" for s in r[key])

    return "\n".join([
        f"{Path(r['scene']).name} {r['res']}x{r['res']}, {r['spp']} spp, {r['threads']} threads, "
        f"{r['integrator']} max_depth {r['max_depth']}; fastest of the runs",
        f"plain Mitsuba     {r['plain_seconds']:7.2f} s   (runs {runs('plain_all')})",
        f"quekaro render    {r['quekaro_seconds']:7.2f} s   (runs {runs('quekaro_all')}), {r['units']} units",
        f"ratio             {r['ratio']:7.3f}   (target <= 1.05) {'PASS' if r['ratio'] <= 1.05 else 'MISS'}",
        f"image means       {r['mean_plain']:.5f} vs {r['mean_quekaro']:.5f} (rel. diff {r['mean_rel_diff']:.4f}); "
        f"relMSE between them {r['relmse_between']:.2e}",
    ])
