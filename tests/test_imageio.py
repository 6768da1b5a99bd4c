"""Whole-image EXR/PNG files: exact EXR round trip, sRGB tonemapping, no silent NaN."""

import numpy as np
import pytest

from core.render.imageio import ImageError, linear_to_srgb, read_exr, read_png, write_exr, write_png


def test_exr_round_trip(tmp_path):
    image = np.random.default_rng(0).random((5, 7, 3), dtype=np.float32) * 100
    assert np.array_equal(read_exr(write_exr(tmp_path / "a.exr", image)), image)


def test_nan_is_never_silent(tmp_path):
    image = np.zeros((2, 2, 3), np.float32)
    image[1, 1, 0] = np.nan
    with pytest.raises(ImageError, match="1 non-finite"):
        write_exr(tmp_path / "a.exr", image)
    with pytest.raises(ImageError, match="non-finite"):
        write_png(tmp_path / "a.png", image)
    write_exr(tmp_path / "b.exr", image, allow_nonfinite=True)
    assert np.isnan(read_exr(tmp_path / "b.exr")[1, 1, 0])


def test_png_is_clamped_srgb(tmp_path):
    image = np.array([[[0.0, 0.5, 2.0], [0.0031308, 0.2, -1.0]]], np.float32)
    png = read_png(write_png(tmp_path / "a.png", image))
    expected = np.array([[[0, 0.7354, 1], [0.04, 0.4845, 0]]], np.float32)
    assert np.allclose(png, expected, atol=1 / 255)
    assert np.allclose(linear_to_srgb(np.float32([1.0])), 1.0)


def test_bad_inputs(tmp_path):
    (tmp_path / "x.exr").write_text("hello")
    with pytest.raises(ImageError, match="not an EXR"):
        read_exr(tmp_path / "x.exr")
    with pytest.raises(ImageError, match="shape"):
        write_exr(tmp_path / "y.exr", np.zeros((2, 2, 2)))


def test_an_xyz_films_preview_is_converted_as_mitsuba_converts_xyz_to_srgb():
    """core.render.film.display_rgb: an X, Y, Z film's colour planes become linear sRGB by the matrix of
    Mitsuba's own mi.xyz_to_srgb; other films' first three planes pass as they are."""
    import mitsuba as mi

    from core.render import mitsuba_env
    from core.render.film import display_rgb

    mitsuba_env.init("llvm_ad_rgb", 1)
    planar = np.random.default_rng(4).uniform(0.0, 2.0, size=(4, 3, 5)).astype(np.float32)
    ours = display_rgb(planar, ("X", "Y", "Z"))
    xyz = planar[:3].reshape(3, -1)
    theirs = np.array(mi.xyz_to_srgb(mi.Color3f(xyz[0], xyz[1], xyz[2]))).reshape(3, 3, 5)
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5)
    assert display_rgb(planar, ("R", "G", "B")) is not None and np.array_equal(display_rgb(planar, ("Y",)), planar[:3])
