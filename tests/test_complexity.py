"""planning.complexity: the pre-pass's budget, its maps (cost from rays per sample, noise from moments)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from core.model.job import SceneSpec
from planning.complexity import ComplexityError, ComplexityMap, _upsample, choose_downscale, prepass

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes" / "mitsuba-data"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason="../shared scenes absent")


@pytest.fixture(scope="module")
def mi():
    from core import mitsuba_env

    mitsuba_env.init("llvm_ad_rgb", 1)
    import mitsuba

    return mitsuba


@pytest.mark.parametrize(("w", "h", "spp"), [(256, 256, 64), (683, 512, 256), (1, 1, 1), (1, 5000, 64),
                                              (97, 89, 16)])
def test_downscale_keeps_samples_within_budget(w: int, h: int, spp: int) -> None:
    for share in (0.8, 0.2):
        k = choose_downscale(w, h, spp, 4, 0.05, share)
        low = -(-w // k) * -(-h // k)
        assert 4 * low <= share * 0.05 / 4 * spp * w * h or (k >= w and k >= h)
        assert k == 1 or 4 * -(-w // (k - 1)) * -(-h // (k - 1)) > share * 0.05 / 4 * spp * w * h  # smallest k


def test_relative_noise_divides_by_brightness_like_relmse() -> None:
    noise = np.array([[4.0, 4.0, 0.0]])
    cmap = ComplexityMap(np.ones((1, 3)), noise, mean=np.array([[10.0, 1.0, 0.0]]))
    assert cmap.relative_noise()[0] == pytest.approx([4.0 / 100.01, 4.0 / 1.01, 0.0])
    assert np.array_equal(ComplexityMap(np.ones((1, 3)), noise).relative_noise(), noise)  # no mean: absolute


def test_map_validation_names_the_field() -> None:
    with pytest.raises(ComplexityError, match="'noise'"):
        ComplexityMap(np.ones((2, 2)), np.full((2, 2), np.nan))
    with pytest.raises(ComplexityError, match="'mean'"):
        ComplexityMap(np.ones((2, 2)), np.ones((2, 2)), mean=-np.ones((2, 2)))
    with pytest.raises(ComplexityError, match="mean"):
        ComplexityMap(np.ones((2, 2)), np.ones((2, 2)), mean=np.ones((3, 2)))
    with pytest.raises(ComplexityError, match="'cost'"):
        ComplexityMap(-np.ones((2, 2)), np.ones((2, 2)))
    with pytest.raises(ComplexityError, match="shapes"):
        ComplexityMap(np.ones((2, 2)), np.ones((2, 3)))
    with pytest.raises(ComplexityError, match="depth_rays"):
        ComplexityMap(np.ones((2, 2)), np.ones((2, 2)), depth_rays=np.ones((2, 2)))
    with pytest.raises(ComplexityError, match="'depth_rays'"):
        ComplexityMap(np.ones((2, 2)), np.ones((2, 2)), depth_rays=np.full((3, 2, 2), np.inf))


def test_upsample_covers_any_size() -> None:
    low = np.arange(12.0).reshape(3, 4)
    for w, h in [(4, 3), (13, 7), (1, 1), (400, 2)]:
        up = _upsample(low, w, h)
        assert up.shape == (h, w)
        assert up[0, 0] == 0
        assert set(np.unique(up)) <= set(low.ravel())


def sphere_scene(mi, size: int = 32):
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}},
        "sphere": {"type": "sphere", "radius": 0.6, "bsdf": {"type": "diffuse"}},
        "light": {"type": "point", "position": [2, 2, 3], "intensity": {"type": "rgb", "value": 20}},
    })


def test_pixels_that_hit_nothing_are_nearly_free(mi) -> None:
    scene = sphere_scene(mi)
    cmap = prepass(scene, max_depth=8, full_spp=1024, spp=4)  # k = 1: the low-res grid is the image
    assert cmap.info["downscale"] == 1 and cmap.cost.shape == (32, 32)
    corner, centre = cmap.cost[0, 0], cmap.cost[16, 16]
    assert corner == 1.0  # the camera ray, nothing else
    assert centre >= 2.0  # camera ray and a shadow ray at least
    assert cmap.noise[0, 0] == 0.0
    assert cmap.mean is not None and cmap.mean[0, 0] == 0.0 and cmap.mean[16, 16] > 0.0  # lit sphere
    assert tuple(scene.sensors()[0].film().size()) == (32, 32)


def test_noise_pass_gets_its_share_of_the_samples_at_a_finer_grid(mi) -> None:
    from planning.complexity import NOISE_SHARE

    scene = sphere_scene(mi, size=64)
    cmap = prepass(scene, max_depth=8, full_spp=128)
    info = cmap.info
    allowed = 0.05 / 4 * 128 * 64 * 64  # the pre-pass's samples: budget / 4 of the render's
    noise_samples = info["spp"] * info["low_size"][0] * info["low_size"][1]
    cost_samples = info["cost_spp"] * info["cost_low_size"][0] * info["cost_low_size"][1]
    assert noise_samples <= NOISE_SHARE * allowed and cost_samples <= (1 - NOISE_SHARE) * allowed
    assert info["downscale"] < info["cost_downscale"]  # the noise map is the finer one
    assert cmap.cost.shape == cmap.noise.shape == (64, 64)
    assert tuple(scene.sensors()[0].film().size()) == (64, 64)  # both passes restore the film


@needs_shared
def test_one_ray_count_gives_the_rays_of_every_cut_depth(mi) -> None:
    """A cut changes no path before it, so the count at depth 8 holds each shallower depth's: layer d - 1
    equals a count traced to depth d with the same seed. Rays only add up with depth; in a closed box most
    paths go on (more rays at 8 than at 4), and the map's cost is the user's depth's layer."""
    from planning.complexity import _ray_count_pass

    scene = mi.load_file(str(SHARED / "cbox" / "cbox.xml"), res=32)
    rays = _ray_count_pass(scene, 16, 16, 8, 4, seed=5)
    assert rays.shape == (8, 16, 16)
    for depth in (1, 3, 4, 8):
        assert np.array_equal(rays[depth - 1], _ray_count_pass(scene, 16, 16, depth, 4, seed=5)[-1])
    assert np.all(np.diff(rays, axis=0) >= 0)
    assert rays[7].mean() > 1.1 * rays[3].mean()
    cmap = prepass(scene, max_depth=8, full_spp=1024)
    assert cmap.depth_rays is not None and len(cmap.depth_rays) == 8
    assert np.array_equal(cmap.cost, _upsample(cmap.depth_rays[-1], 32, 32))


def test_nothing_visible_gives_a_flat_cheap_map(mi) -> None:
    scene = mi.load_dict({"type": "scene", "sensor": {"type": "perspective",
                          "film": {"type": "hdrfilm", "width": 16, "height": 8}}})
    cmap = prepass(scene, max_depth=4)
    assert np.all(cmap.cost == 1.0) and np.all(cmap.noise == 0.0)


@needs_shared
@pytest.mark.slow
def test_prepass_is_far_cheaper_than_the_render(mi, capsys) -> None:
    spec = SceneSpec(SHARED / "cbox" / "cbox.xml", {"res": "128"})
    from core.scene.scene import load

    scene = load(spec)
    integrator = mi.load_dict({"type": "path", "max_depth": 6})

    def full() -> float:
        start = time.perf_counter()
        np.array(mi.render(scene, integrator=integrator, spp=64, seed=1))
        return time.perf_counter() - start

    cold_pre, cold_full = prepass(scene, max_depth=6, full_spp=64).seconds, full()
    pre = min(prepass(scene, max_depth=6, full_spp=64, seed=s).seconds for s in range(3))
    render = min(full() for _ in range(2))
    with capsys.disabled():
        print(f"\ncbox 128x128: prepass {pre * 1000:.1f} ms vs 64 spp render {render * 1000:.0f} ms "
              f"(ratio {pre / render:.3f}); first call in this process {cold_pre * 1000:.0f} ms vs "
              f"{cold_full * 1000:.0f} ms")
    assert pre < 0.25 * render
    assert tuple(scene.sensors()[0].film().size()) == (128, 128)  # the film is restored


@needs_shared
@pytest.mark.slow
def test_noise_map_predicts_where_the_error_is(mi) -> None:
    """Block-mean pre-pass noise against the real squared error of an 8 spp render (rank correlation)."""
    from core.scene.scene import load

    scene = load(SceneSpec(SHARED / "cbox" / "cbox.xml", {"res": "64"}))
    integrator = mi.load_dict({"type": "path", "max_depth": 6})
    cmap = prepass(scene, max_depth=6, full_spp=64, spp=8)
    ref = np.array(mi.render(scene, integrator=integrator, spp=1024, seed=3))[..., :3]
    low = np.array(mi.render(scene, integrator=integrator, spp=8, seed=4))[..., :3]
    err = ((low - ref) ** 2).mean(axis=2)
    blocks = lambda a: a.reshape(8, 8, 8, 8).mean(axis=(1, 3)).ravel()  # noqa: E731
    rank = lambda a: np.argsort(np.argsort(a))  # noqa: E731
    rho = np.corrcoef(rank(blocks(cmap.noise)), rank(blocks(err)))[0, 1]
    print(f"rank correlation of pre-pass noise with the 8 spp error over 8x8 blocks: {rho:.2f}")
    assert rho > 0.6


def test_a_cropped_film_is_scaled_whole_so_the_low_res_image_covers_its_crop_window(mi) -> None:
    """film_size on a film that crops itself renders the crop window's view, not the whole film's: at
    half size, the cropped scene's low-resolution image equals (within its noise) the uncropped film's
    at half size sliced at the halved crop offset, and differs from the slice one pixel over. The film is
    put back as loaded."""
    from core.image.film import film_channels
    from core.scene.scene import load
    from planning.complexity import film_size

    crop = Path(__file__).resolve().parent / "compat" / "scenes" / "crop.xml"  # 40x32 at (18, 10) of 64x56
    scene = load(SceneSpec(crop), "llvm_ad_rgb", threads=1)
    whole = load(SceneSpec(crop), "llvm_ad_rgb", threads=1)
    params = mi.traverse(whole.sensors()[0])
    params["film.crop_size"], params["film.crop_offset"] = [64, 56], [0, 0]
    params.update()

    def half(s, w, h):
        with film_size(s, w, h):
            mi.render(s, spp=1024, seed=3)
            return film_channels(s.sensors()[0].film())[0][..., :3]

    low = half(scene, 20, 16)
    full = half(whole, 32, 28)
    here, shifted = full[5:21, 9:29], full[5:21, 10:30]
    assert np.abs(low - here).mean() < 0.25 * np.abs(low - shifted).mean()
    film = scene.sensors()[0].film()
    assert (tuple(film.size()), tuple(film.crop_size()), tuple(film.crop_offset())) == ((64, 56), (40, 32), (18, 10))
