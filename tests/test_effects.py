"""Effect analysis: each decision and its reason; the cheaper choice keeps the image, and is not taken
where it would change it (media, dielectrics, an envmap seen through glass)."""

from pathlib import Path

import pytest

from core.effects import analyse, depth_cap
from core.errors import SceneError
from core.render_unit import render_full
from core.scene import SceneSpec

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "tests" / "data" / "scenes"
SMALL = {"width": "24", "height": "24"}


def _mean(spec, integrator, depth, spp=256, seed=0):
    return render_full(spec, "llvm_ad_rgb", integrator, depth, spp, seed=seed, threads=1).mean()


def test_depth_cap_formula():
    assert depth_cap(0.0) == 2 and depth_cap(1.0) is None
    cap = depth_cap(0.73)
    assert 0.73 ** (cap - 1) / (1 - 0.73) <= 5e-3 < 0.73 ** (cap - 2) / (1 - 0.73)


def test_direct_for_a_single_convex_surface_keeps_the_image():
    spec = SceneSpec(DATA / "tiny.xml", SMALL)
    effects = analyse(spec)
    assert (effects.integrator, effects.max_depth) == ("direct", 2)
    assert any("convex Sphere" in r for r in effects.reasons)
    cheap, full = _mean(spec, "direct", None), _mean(spec, "path", 8, seed=1)
    assert abs(cheap / full - 1) < 0.02


def test_depth_cap_on_a_diffuse_scene_keeps_the_image():
    spec = SceneSpec(REPO / "scenes" / "cbox.xml", {"res": "24", "max_depth": "-1"})
    effects = analyse(spec)
    assert effects.integrator == "path" and 2 < effects.max_depth < 40
    assert any("diffuse only" in r for r in effects.reasons)
    capped, full = _mean(spec, "path", effects.max_depth), _mean(spec, "path", -1, seed=1)
    assert abs(capped / full - 1) < 0.03


@pytest.mark.parametrize("name, integrator", [("glass_envmap.xml", "path"), ("fog_ball.xml", "volpath")])
def test_no_shortcut_where_it_would_change_the_image(name, integrator):
    spec = SceneSpec(DATA / name, SMALL)
    effects = analyse(spec)
    assert effects.integrator == integrator and effects.max_depth == 8
    # the shortcut the analysis refused really changes the image
    shortcut = _mean(spec, "direct", None) if integrator == "path" else _mean(spec, "path", 8)
    assert abs(shortcut / _mean(spec, integrator, 8, seed=1) - 1) > 0.05


def test_glass_corner_keeps_its_depth():
    effects = analyse(SceneSpec(REPO / "scenes" / "glass-corner.xml", {"res": "16"}))
    assert (effects.variant, effects.integrator, effects.max_depth) == ("llvm_ad_rgb", "path", 12)


def test_spectral_input_picks_spectral(tmp_path):
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse">'
                     '<spectrum name="reflectance" value="400:0.1, 700:0.9"/></bsdf></shape></scene>')
    effects = analyse(SceneSpec(scene))
    assert effects.variant == "llvm_ad_spectral" and "per wavelength" in effects.reasons[0]


def test_overrides_win_and_say_so():
    effects = analyse(SceneSpec(DATA / "tiny.xml", SMALL), {"integrator": "path", "max_depth": 5})
    assert (effects.integrator, effects.max_depth) == ("path", 5)
    assert sum("user override" in r for r in effects.reasons) == 2
    assert effects.to_dict()["reasons"] == effects.reasons
    with pytest.raises(SceneError, match="unknown effect override"):
        analyse(SceneSpec(DATA / "tiny.xml"), {"spp": 3})
