"""Assembly memory: composing a 4096 x 4096 image from 64 tile files stays under twice the output image
(it peaked at about 10x when every tile was read up front and the sums were float64 images), and the
page's preview of it, shrunk, under half of that (it composed the image at full size)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
SCRIPT = r"""
import json, sys
from pathlib import Path
import numpy as np
from core.image.compose import compose_planar, compose_shrunk
from core.model.geometry import Rect
from core.image.imageio import write_exr, write_png_planar
from core.image.tiles import Tile, tile_source, write_tile

size, side, band, out, shrunk = 4096, 512, 2, Path(sys.argv[1]), sys.argv[2] == "shrunk"
paths = []
for y in range(0, size, side):
    for x in range(0, size, side):
        core = Rect(x, y, side, side)
        rect = core.window(band, size, size)
        pixels = np.full((rect.h, rect.w, 3), 0.25, np.float32) + np.float32((x + y) / (4 * size))
        paths.append(write_tile(out / f"{x}-{y}.exr", Tile(pixels, rect, core, {}), durable=False))
        del pixels

def rss(key):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key):
            return int(line.split()[1]) * 1024

Path("/proc/self/clear_refs").write_text("5")  # the peak starts again from here
base = rss("VmRSS:")
if shrunk:
    image = compose_shrunk([tile_source(p) for p in paths], size, size, 2)
else:
    image, report = compose_planar([tile_source(p) for p in paths], size, size)
    write_exr(out / "result.exr", image, channels=("R", "G", "B"), planar=True)
write_png_planar(out / "result.png", image)
full = 3 * size * size * 4
print(json.dumps({"grown": rss("VmHWM:") - base, "image": full, "mean": float(image.mean()), "shape": image.shape}))
"""


def composed(tmp_path: Path, mode: str) -> dict:
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), mode], capture_output=True, text=True,
                          cwd=REPO, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    found = json.loads(done.stdout.strip().splitlines()[-1])
    assert 0.25 < found["mean"] < 0.75  # every tile arrived
    return found


def test_composing_a_4096_image_stays_under_twice_the_image(tmp_path):
    found = composed(tmp_path, "full")
    assert found["grown"] < 2 * found["image"], f"peak grew {found['grown'] / 2**20:.0f} MiB for a " \
                                                  f"{found['image'] / 2**20:.0f} MiB image"
    print(f"assembly of 4096^2 x 3: peak grew {found['grown'] / 2**20:.0f} MiB, image {found['image'] / 2**20:.0f} MiB")


def test_a_4096_images_preview_shrunk_twice_grows_under_half_what_its_full_composition_grows(tmp_path):
    (tmp_path / "full").mkdir(), (tmp_path / "shrunk").mkdir()
    full, found = composed(tmp_path / "full", "full"), composed(tmp_path / "shrunk", "shrunk")
    assert found["shape"] == [3, 2048, 2048]
    assert found["grown"] < full["grown"] / 2, f"the preview grew {found['grown'] / 2**20:.0f} MiB, the full " \
                                                f"composition {full['grown'] / 2**20:.0f} MiB"
    print(f"4096^2 x 3: the preview at 2048^2 grew {found['grown'] / 2**20:.0f} MiB, the full composition "
          f"{full['grown'] / 2**20:.0f} MiB")
