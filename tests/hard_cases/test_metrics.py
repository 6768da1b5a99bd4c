"""Hard cases of the image metrics (core.image.metrics): identical images, black and near-black references,
single pixels, non-finite input. Every metric is finite and silent (no numpy warning) or refuses clearly."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from core.image import metrics
from core.image.imageio import ImageError

METRICS = {
    "mean_pixel_diff_percent": metrics.mean_pixel_diff_percent,
    "rmse": metrics.rmse,
    "relmse": metrics.relmse,
    "flip": metrics.flip,
}


def _quiet(fn, *args):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a division by zero or an overflow warns: make it fail
        return fn(*args)


def _noisy(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).gamma(1.0, 0.5, (h, w, 3)).astype(np.float32)


@pytest.mark.parametrize("name", sorted(METRICS))
@pytest.mark.parametrize("image", [
    np.zeros((16, 16, 3), np.float32), _noisy(16, 16), np.full((1, 1, 3), 7.0, np.float32),
    np.full((2, 64, 3), 1e30, np.float32), _noisy(40, 1),
], ids=["black", "noisy", "one-pixel", "huge", "one-column"])
def test_identical_images_give_zero(name, image):
    assert _quiet(METRICS[name], image, image.copy()) == 0.0


@pytest.mark.parametrize("name", sorted(METRICS))
@pytest.mark.parametrize("peak", [0.0, 1e-12, 1e-7, 1e-5])
def test_black_and_near_black_reference_give_finite_errors(name, peak):
    reference = np.zeros((16, 16, 3), np.float32)
    reference[4, 4] = peak
    test = _noisy(16, 16, seed=1)
    value = _quiet(METRICS[name], test, reference)
    assert np.isfinite(value) and value > 0


def test_relmse_on_a_black_reference_is_the_documented_bound():
    test = np.full((4, 4, 3), 0.5, np.float32)
    reference = np.zeros((4, 4, 3), np.float32)
    assert metrics.relmse(test, reference) == pytest.approx(0.25 / metrics.RELMSE_EPSILON)
    assert metrics.mean_pixel_diff_percent(test, reference) == pytest.approx(
        100 * float(metrics.linear_to_srgb(test)[0, 0, 0]), rel=1e-6)


@pytest.mark.parametrize("name", sorted(METRICS))
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("which", ["test image", "reference image"])
def test_non_finite_input_is_refused_naming_the_image(name, bad, which):
    good = _noisy(8, 8)
    broken = good.copy()
    broken[3, 3, 1] = bad
    args = (broken, good) if which == "test image" else (good, broken)
    with pytest.raises(ImageError, match=f"{which}: 1 non-finite pixels"):
        METRICS[name](*args)


def test_all_metrics_on_black_pair_are_all_zero():
    black = np.zeros((3, 5, 3), np.float32)
    assert _quiet(metrics.all_metrics, black, black) == dict.fromkeys(METRICS, 0.0)
