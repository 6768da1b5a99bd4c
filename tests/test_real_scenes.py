"""The real Mitsuba scenes in ../shared render through our loader and unit renderer (skipped without them)."""

from pathlib import Path

import numpy as np
import pytest

from core.model.geometry import Rect
from core.model.job import SceneSpec
from core.render.process import RenderProcess, RenderRequest
from core.scene.scene import image_size, referenced_files

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared" / "scenes" / "mitsuba-data"
pytestmark = pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/scenes/mitsuba-data is absent")

CASES = [
    ("cbox/cbox.xml", {"res": "32", "spp": "4"}, "llvm_ad_spectral"),
    ("cbox/cbox-rgb.xml", {"res": "32", "spp": "4"}, "llvm_ad_rgb"),
    ("cbox/cbox-spectral.xml", {"res": "32", "spp": "4"}, "llvm_ad_spectral"),
    ("matpreview/matpreview.xml", {"width": "40", "height": "30", "spp": "4"}, "llvm_ad_rgb"),
]


@pytest.fixture(scope="module")
def worker():
    # Rendered in a child, as the farm does: Mitsuba in the test process itself can deadlock after
    # many variant and thread-count changes (seen loading matpreview there).
    with RenderProcess() as w:
        yield w


@pytest.mark.parametrize("name, defines, variant", CASES)
def test_real_scene_renders_as_units(worker, name, defines, variant):
    spec = SceneSpec(SHARED / name, defines)
    width, height = image_size(spec)
    assert all(path.is_file() for path in referenced_files(spec))
    unit = Rect(width // 4, height // 4, width // 2, height // 2)
    tile = worker.render(RenderRequest(spec, variant, "path", 4, 4, 1, width, height, unit, band=2, threads=1),
                         timeout=120)
    assert tile.pixels.shape == (unit.h + 4, unit.w + 4, 3)
    assert np.isfinite(tile.pixels).all() and tile.pixels.mean() > 0
