"""Effect analysis: each decision and its reason; the cheaper choice keeps the image, and is not taken
where it would change it (media, dielectrics, an envmap seen through glass)."""

from pathlib import Path

import numpy as np
import pytest

from core.errors import QuekaroError, SceneError
from core.model.job import SceneSpec
from core.render.process import render_full
from core.scene.effects import analyse, analyse_loaded

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "tests" / "data" / "scenes"
SMALL = {"width": "24", "height": "24"}


def _mean(spec, integrator, depth, spp=256, seed=0):
    return render_full(spec, "llvm_ad_rgb", integrator, depth, spp, seed=seed, threads=1).mean()


def test_the_analysis_hands_over_the_scene_it_loaded_in_the_chosen_variant():
    import mitsuba as mi

    spec = SceneSpec(DATA / "tiny.xml", SMALL)
    effects, scene = analyse_loaded(spec, {"variant": "llvm_ad_spectral"})
    assert effects == analyse(spec, {"variant": "llvm_ad_spectral"}) and effects.variant == "llvm_ad_spectral"
    assert mi.variant() == "llvm_ad_spectral" and isinstance(scene, mi.Scene)
    assert [int(v) for v in scene.sensors()[0].film().size()] == [24, 24]


def test_the_scenes_integrator_is_kept_even_where_direct_would_be_cheaper():
    # A single convex diffuse sphere: no light reaches the camera after two bounces, but the scene asks for
    # `path`, and the analysis never changes what the scene asks to compute.
    effects = analyse(SceneSpec(DATA / "tiny.xml", SMALL))
    assert effects.integrator == "path" and effects.override is None and effects.splittable
    assert any("the scene's own, kept as written" in r for r in effects.reasons)


def test_a_default_driven_integrator_type_follows_its_define(tmp_path):
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><default name="integrator" value="path"/>'
                     '<integrator type="$integrator"/><shape type="sphere"/></scene>')
    assert analyse(SceneSpec(scene)).integrator == "path"
    direct = analyse(SceneSpec(scene, {"integrator": "direct"}))
    assert direct.integrator == "direct" and any("takes none" in r for r in direct.reasons)


def test_nested_integrators_are_described_and_ptracer_is_not_split(tmp_path):
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><integrator type="moment"><integrator type="path">'
                     '<integer name="max_depth" value="3"/></integrator></integrator>'
                     '<shape type="sphere"/></scene>')
    effects = analyse(SceneSpec(scene))
    assert (effects.integrator, effects.max_depth, effects.splittable) == ("moment(path)", 3, True)
    scene.write_text('<scene version="3.0.0"><integrator type="ptracer"/><shape type="sphere"/></scene>')
    effects = analyse(SceneSpec(scene))
    assert not effects.splittable and any("splat anywhere" in r for r in effects.reasons)


def test_a_cut_or_depth_leaves_a_shallower_nested_integrator_as_written():
    """with_depth: the deepest nested integrators take the new depth; a shallower one keeps its own unless
    the new depth is less (an aov's depth-2 child was once rendered at its -1 sibling's new depth 20: 19 % brighter)."""
    from lxml import etree

    from core.model import integrators

    def depths(xml: str) -> dict[str, str]:
        tree = etree.fromstring(xml)
        return {e.get("name"): e.find("integer[@name='max_depth']").get("value") for e in tree.iter("integrator")
                if e.get("name")}

    tree = etree.fromstring('<integrator type="aov"><string name="aovs" value="dd.y:depth"/>'
                            '<integrator type="path" name="short"><integer name="max_depth" value="3"/></integrator>'
                            '<integrator type="path" name="full"><integer name="max_depth" value="-1"/></integrator>'
                            '</integrator>')
    assert depths(integrators.with_depth(tree, 20)) == {"short": "3", "full": "20"}
    assert depths(integrators.with_depth(tree, 2)) == {"short": "2", "full": "2"}
    assert depths(integrators.with_depth(tree, -1)) == {"short": "3", "full": "-1"}
    tree.find("integrator[@name='full']/integer").set("value", "12")
    assert depths(integrators.with_depth(tree, 6)) == {"short": "3", "full": "6"}
    assert depths(integrators.with_depth(tree, 16)) == {"short": "3", "full": "16"}  # the user's --depth 16
    # the pre-pass measures the first leaf as the units render it: short at 3, not at the tree's depth
    assert etree.fromstring(integrators.radiance_xml(tree, 16)).find("integer").get("value") == "3"
    assert etree.fromstring(integrators.radiance_xml(tree, 2)).find("integer").get("value") == "2"


@pytest.mark.parametrize("name", ["glass_envmap.xml", "fog_ball.xml", "baffled_tunnel.xml"])
def test_the_scenes_depth_is_kept_with_its_reason(name):
    effects = analyse(SceneSpec(DATA / name, SMALL))
    depth = 8 if name != "baffled_tunnel.xml" else -1
    assert effects.integrator == "path" and effects.max_depth == depth
    assert f"max_depth {depth}: the scene's own" in effects.reasons


@pytest.mark.slow
def test_a_reflectance_bound_on_the_depth_is_no_bound_on_a_pixels_light():
    """Why the analysis lowers no depth: a diffuse scene of albedo 0.3 bounds the light of paths deeper than
    6 at 0.5 % of its lamp's radiance, but where the camera sees light that came round a baffle, those
    paths carry more of the pixel. Paired seeds: the same paths up to depth 6, so the difference is the
    tail itself; at 2048 spp its share measured 0.87-1.02 % over five seeds against the bound's 0.5 %."""
    spec = SceneSpec(DATA / "baffled_tunnel.xml", {"refl": "0.3", "width": "32"})
    cut, full = _mean(spec, "path", 6, spp=2048), _mean(spec, "path", -1, spp=2048)
    assert full > cut and 1 - cut / full > 0.005, (cut, full)


def test_glass_corner_keeps_its_depth_and_its_gold_given_in_rgb_renders_in_rgb():
    effects = analyse(SceneSpec(REPO / "scenes" / "glass-corner.xml", {"res": "16"}))
    assert (effects.variant, effects.integrator, effects.max_depth) == ("llvm_ad_rgb", "path", 12)


@pytest.mark.parametrize(("bsdf", "variant"), [
    ('<bsdf type="conductor"><string name="material" value="Au"/></bsdf>', "llvm_ad_spectral"),
    ('<bsdf type="twosided"><bsdf type="roughconductor"><string name="material" value="$metal"/></bsdf></bsdf>',
     "llvm_ad_spectral"),
    ('<bsdf type="conductor"/>', "llvm_ad_rgb"),  # Mitsuba's default material: none, a perfect mirror
    ('<bsdf type="conductor"><string name="material" value="$plain"/></bsdf>', "llvm_ad_rgb"),
    ('<bsdf type="conductor"><string name="material" value="none"/></bsdf>', "llvm_ad_rgb"),
    ('<bsdf type="conductor"><rgb name="eta" value="0.2, 0.4, 1.4"/><rgb name="k" value="3.9, 2.4, 1.9"/></bsdf>',
     "llvm_ad_rgb"),
])
def test_a_conductor_of_a_measured_metal_needs_spectral(tmp_path, bsdf, variant):
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><default name="metal" value="Cr"/><default name="plain" value="none"/>'
                     f'<shape type="sphere">{bsdf}</shape></scene>')
    assert analyse(SceneSpec(scene)).variant == variant


def test_a_measured_metal_renders_another_colour_in_rgb():
    """Why: a gold ball under a white sky (noise-free: a mirror of a constant), rgb against spectral, off
    by more than the analysis's RGB_TOLERANCE of the brightest channel (measured: about 5 % per channel)."""
    import mitsuba as mi

    from core import mitsuba_env
    from core.scene.spectral_data import RGB_TOLERANCE

    colours = {}
    for variant in ("llvm_ad_rgb", "llvm_ad_spectral"):
        mitsuba_env.init(variant, threads=1)
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "path", "max_depth": 3},
            "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 8, "height": 8},
                       "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0])
                       @ mi.ScalarTransform4f().scale([0.3, 0.3, 1]),
                       "sampler": {"type": "independent", "sample_count": 4}},
            "sky": {"type": "constant"},
            "ball": {"type": "sphere", "bsdf": {"type": "conductor", "material": "Au"}}})
        colours[variant] = np.array(mi.render(scene)).reshape(-1, 3).mean(axis=0)
    rgb, spectral = colours["llvm_ad_rgb"], colours["llvm_ad_spectral"]
    assert np.max(np.abs(rgb - spectral)) / spectral.max() > RGB_TOLERANCE, (rgb, spectral)


def _spectrum_scene(tmp_path, spectrum: str) -> SceneSpec:
    scene = tmp_path / "s.xml"
    scene.write_text(f'<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse">{spectrum}</bsdf>'
                     '</shape></scene>')
    return SceneSpec(scene)


@pytest.mark.parametrize(("spectrum", "variant", "why"), [
    ('<spectrum name="reflectance" value="400:0.78, 500:0.78, 600:0.78, 700:0.78"/>', "llvm_ad_rgb",
     "no spectral data that rgb would render differently"),
    ('<spectrum name="reflectance" value="400:0.6, 550:0.62, 700:0.6"/>', "llvm_ad_rgb", "no spectral data"),
    ('<spectrum name="reflectance" value="400:0.02, 540:0.02, 550:0.9, 560:0.02, 700:0.02"/>',
     "llvm_ad_spectral", "rgb would render differently"),
    ('<spectrum name="reflectance" value="400:0.1, 700:0.9"/>', "llvm_ad_spectral", "rgb would render differently"),
    ('<spectrum name="reflectance" value="0.5"/>', "llvm_ad_rgb", "no spectral data"),
])
def test_spectral_variant_only_where_rgb_would_differ(tmp_path, spectrum, variant, why):
    effects = analyse(_spectrum_scene(tmp_path, spectrum))
    assert effects.variant == variant and why in effects.reasons[0]


def test_dispersion_and_blackbody_need_spectral(tmp_path):
    glass = ('<bsdf type="conductor"><spectrum name="eta" value="400:0.20, 700:0.25"/>'
             '<spectrum name="k" value="400:3.0, 700:3.0"/></bsdf>')
    scene = tmp_path / "g.xml"
    scene.write_text(f'<scene version="3.0.0"><shape type="sphere">{glass}</shape></scene>')
    assert "dispersion" in analyse(SceneSpec(scene)).reasons[0]
    scene.write_text('<scene version="3.0.0"><shape type="sphere"><emitter type="area">'
                     '<spectrum name="radiance" type="blackbody"><float name="temperature" value="3000"/>'
                     '</spectrum></emitter></shape></scene>')
    assert analyse(SceneSpec(scene)).variant == "llvm_ad_spectral"


def test_overrides_win_and_say_so():
    effects = analyse(SceneSpec(DATA / "tiny.xml", SMALL), {"integrator": "volpath", "max_depth": 5})
    assert (effects.integrator, effects.override, effects.max_depth) == ("volpath", "volpath", 5)
    assert sum("user override" in r for r in effects.reasons) == 2
    assert effects.to_dict()["reasons"] == effects.reasons
    with pytest.raises(SceneError, match="unknown effect override"):
        analyse(SceneSpec(DATA / "tiny.xml"), {"spp": 3})


def test_an_integrator_override_says_which_of_the_scenes_parameters_it_drops(tmp_path):
    """`--integrator` replaces the scene's integrator by a bare type: the reasons name what goes with it."""
    scene = tmp_path / "s.xml"
    path = ('<integrator type="path"><boolean name="hide_emitters" value="true"/><integer name="rr_depth" '
            'value="2"/><integer name="max_depth" value="5"/></integrator>')
    scene.write_text(f'<scene version="3.0.0"><integrator type="moment">{path}{path}</integrator>'
                     '<shape type="sphere"/></scene>')
    effects = analyse(SceneSpec(scene), {"integrator": "volpath"})
    assert "integrator volpath: user override, with its type's defaults (the scene's moment(path, path) and its " \
           "hide_emitters, rr_depth are not used)" in effects.reasons, effects.reasons
    assert effects.max_depth == 5  # the scene's depth goes on to the override
    scene.write_text('<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="3"/>'
                     '</integrator><shape type="sphere"/></scene>')
    assert "integrator volpath: user override, with its type's defaults" in \
        analyse(SceneSpec(scene), {"integrator": "volpath"}).reasons


def test_a_depth_for_an_integrator_that_takes_none_is_refused(tmp_path):
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><integrator type="direct"/><shape type="sphere"/></scene>')
    with pytest.raises(SceneError, match="--depth 5: the integrator direct takes no depth"):
        analyse(SceneSpec(scene), {"max_depth": 5})


def test_a_variant_that_cannot_load_here_is_refused_naming_it():
    """A cuda variant on a machine without a usable GPU (this one): a QuekaroError naming the variant and
    what Mitsuba said, not an ImportError from inside Dr.Jit."""
    import drjit as dr

    from core import mitsuba_env

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a CUDA backend: cuda_ad_rgb loads")
    with pytest.raises(QuekaroError, match=r"Mitsuba variant 'cuda_ad_rgb' cannot load here \(ImportError"):
        mitsuba_env.init("cuda_ad_rgb")
    assert mitsuba_env.init("llvm_ad_rgb") == "llvm_ad_rgb"  # and the process renders on
