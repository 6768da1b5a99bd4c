"""Metrics: zero on identical images, known values, no division by zero on black references."""

import argparse
import json

import numpy as np
import pytest

from core.image import imageio, metrics
from core.image.imageio import ImageError
from quekaro import cmd_diff


def _images():
    rng = np.random.default_rng(3)
    ref = rng.random((16, 16, 3), dtype=np.float32)
    return ref, np.clip(ref + rng.normal(0, 0.05, ref.shape).astype(np.float32), 0, None)


def test_identical_images_give_zero():
    ref, _ = _images()
    for image in (ref, np.zeros_like(ref)):
        assert metrics.all_metrics(image, image) == {
            "mean_pixel_diff_percent": 0.0, "rmse": 0.0, "relmse": 0.0, "flip": 0.0}


def test_known_values():
    ref = np.full((4, 4, 3), 0.25, np.float32)
    test = ref + 0.1
    assert metrics.rmse(test, ref) == pytest.approx(0.1, rel=1e-5)
    assert metrics.relmse(test, ref) == pytest.approx(0.01 / (0.0625 + 0.01), rel=1e-4)
    white, black = np.ones((2, 2, 3), np.float32), np.zeros((2, 2, 3), np.float32)
    assert metrics.mean_pixel_diff_percent(white, black) == pytest.approx(100.0)
    assert metrics.diff_image(white, black).shape == (2, 2)


def test_black_reference_has_no_division_by_zero():
    _, test = _images()
    black = np.zeros_like(test)
    values = metrics.all_metrics(test, black)
    assert all(np.isfinite(v) for v in values.values())
    assert values["relmse"] == pytest.approx(np.mean(test.astype(np.float64) ** 2) / 0.01, rel=1e-4)
    assert 0 < values["flip"] <= 1


def test_more_noise_is_worse_on_every_metric():
    ref, small = _images()
    big = np.clip(ref + (small - ref) * 4, 0, None)
    a, b = metrics.all_metrics(small, ref), metrics.all_metrics(big, ref)
    assert all(b[k] > a[k] for k in a)


def test_refuses_mismatch_and_nan():
    ref, test = _images()
    with pytest.raises(ImageError, match="differ in size"):
        metrics.rmse(test[:8], ref)
    test[0, 0, 0] = np.nan
    with pytest.raises(ImageError, match="non-finite"):
        metrics.flip(test, ref)


def test_cli_diff_json(tmp_path, capsys):
    ref, test = _images()
    imageio.write_exr(tmp_path / "a.exr", test)
    imageio.write_exr(tmp_path / "b.exr", ref)
    parser = argparse.ArgumentParser()
    cmd_diff.register(parser.add_subparsers())
    args = parser.parse_args(["diff", str(tmp_path / "a.exr"), str(tmp_path / "b.exr"), "-o",
                              str(tmp_path / "d.png"), "--json"])
    assert args.func(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {"mean_pixel_diff_percent", "rmse", "relmse", "flip"}
    assert out["rmse"] == pytest.approx(metrics.rmse(test, ref))
    grey = imageio.read_png(tmp_path / "d.png")[..., 0]
    assert np.allclose(grey, metrics.diff_image(test, ref), atol=1.5 / 255)
