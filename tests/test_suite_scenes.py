"""Every scene of the accuracy suite loads and renders in plain Mitsuba at a tiny size (a typo in one
would otherwise surface an hour into `quekaro bench accuracy --suite`)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.suite import SUITE
from core.model.job import SceneSpec
from core.scene.scene import load
from planning.accuracy import content_key


@pytest.mark.parametrize("scene", SUITE, ids=[s.name for s in SUITE])
def test_suite_scene_renders(scene) -> None:
    import mitsuba as mi  # after load() below has chosen the variant

    if not scene.path.exists():
        pytest.fail(f"{scene.name}: {scene.path} is missing (../shared/scenes must sit beside the repository)")
    spec = SceneSpec(scene.path, scene.with_size(16))
    assert content_key(spec)  # the project's own XML reading (lxml) is stricter than Mitsuba's
    loaded = load(spec, "llvm_ad_rgb", threads=1)
    image = np.asarray(mi.render(loaded, spp=2))
    assert image.shape[1] == 16 and np.isfinite(image).all() and image.mean() > 0
