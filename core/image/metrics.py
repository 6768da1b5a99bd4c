"""Image error metrics: the paper's mean per-pixel colour difference, RMSE, relative MSE and FLIP.

All take two float32 (H, W, 3) linear RGB images of equal shape: `test` first, then `reference`
(for the symmetric metrics the order does not matter). Identical images give 0 for every metric.
Non-finite input is an error, never a silent NaN result.
"""

from __future__ import annotations

import flip_evaluator
import numpy as np

from core.image.imageio import ImageError, as_rgb, linear_to_srgb

RELMSE_EPSILON = 1e-2
# HDR-FLIP derives its exposure range from the reference's peak luminance; below about 1e-7 the range
# is empty and the C++ library aborts the whole process. Under this peak, FLIP runs in LDR mode.
FLIP_HDR_MIN_PEAK = 1e-5
_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def _pair(test: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = as_rgb(test, "test image"), as_rgb(reference, "reference image")
    if a.shape != b.shape:
        raise ImageError(f"images differ in size: {a.shape[1]}x{a.shape[0]} vs {b.shape[1]}x{b.shape[0]}")
    for name, image in (("test image", a), ("reference image", b)):
        bad = int((~np.isfinite(image)).any(axis=-1).sum())
        if bad:
            raise ImageError(f"{name}: {bad} non-finite pixels")
    return a, b


def diff_image(test: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Grey (H, W) image of the per-pixel colour difference used by `mean_pixel_diff_percent`.

    Each pixel: the mean over R, G, B of |sRGB(test) - sRGB(reference)|, where sRGB() clamps the linear
    value to [0, 1] and applies the sRGB transfer curve; so values lie in [0, 1].
    """
    a, b = _pair(test, reference)
    return np.abs(linear_to_srgb(a) - linear_to_srgb(b)).mean(axis=-1)


def mean_pixel_diff_percent(test: np.ndarray, reference: np.ndarray) -> float:
    """The paper's metric: the mean over all pixels of `diff_image`, in percent (0 to 100).

    It compares what a viewer sees (display values, as the paper compared 8-bit images): the images
    are clamped to [0, 1] and sRGB encoded, the absolute differences of the three channels are averaged
    per pixel, and those are averaged over the image and multiplied by 100.
    """
    return float(diff_image(test, reference).mean() * 100.0)


def rmse(test: np.ndarray, reference: np.ndarray) -> float:
    """Root mean squared error over all pixels and channels, on linear values."""
    a, b = _pair(test, reference)
    return float(np.sqrt(np.mean((a.astype(np.float64) - b) ** 2)))


def relmse(test: np.ndarray, reference: np.ndarray, epsilon: float = RELMSE_EPSILON) -> float:
    """Relative MSE: mean over pixels and channels of (test - ref)^2 / (ref^2 + epsilon), linear values.

    epsilon = 0.01 by default keeps an all-black (or partly black) reference from dividing by zero;
    there the metric degrades to 100 x the squared error.
    """
    a, b = _pair(test, reference)
    ref = b.astype(np.float64)
    return float(np.mean((a - ref) ** 2 / (ref**2 + epsilon)))


def flip(test: np.ndarray, reference: np.ndarray, hdr: bool = True) -> float:
    """Mean FLIP error (NVIDIA's perceptual metric, package flip-evaluator), in [0, 1].

    `hdr=True` (default): inputs are linear RGB radiance, negative values clamped to 0; HDR-FLIP picks
    its own exposure range. `hdr=False`: LDR-FLIP on the display values (clamped, sRGB encoded).
    A (near-)black reference, peak luminance under FLIP_HDR_MIN_PEAK, is always compared in LDR mode.
    """
    a, b = _pair(test, reference)
    if np.array_equal(a, b):
        return 0.0  # FLIP's HDR exposure search is undefined on an all-black pair; identical is 0
    if hdr and float((np.maximum(b, 0.0) @ _LUMA).max()) >= FLIP_HDR_MIN_PEAK:
        ref, tst, mode = np.maximum(b, 0.0), np.maximum(a, 0.0), "HDR"
    else:
        ref, tst, mode = linear_to_srgb(b), linear_to_srgb(a), "LDR"
    _, mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(ref), np.ascontiguousarray(tst), mode)
    return float(mean)


def all_metrics(test: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Every metric at once, under the names `quekaro diff --json` prints."""
    return {
        "mean_pixel_diff_percent": mean_pixel_diff_percent(test, reference),
        "rmse": rmse(test, reference),
        "relmse": relmse(test, reference),
        "flip": flip(test, reference),
    }
