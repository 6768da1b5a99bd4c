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
