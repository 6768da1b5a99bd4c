"""The seam measure: noise alone (equal or different per unit, skewed, independent or correlated between
neighbours as a pixel filter makes it) reads as no seam; a bias inside one unit or a band defect reads as
one and names the unit; degenerate layouts are handled."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from core.errors import QuekaroError
from core.image import imageio
from core.image.seams import seam_measure, unit_map
from core.model.geometry import Rect
from quekaro import cmd_diff

REPO = Path(__file__).resolve().parent.parent
SIDE = 128


def grid(n: int, side: int = SIDE) -> list[Rect]:
    step = side // n
    return [Rect(x * step, y * step, step, step) for y in range(n) for x in range(n)]


def noisy(rects: list[Rect], sigmas: list[float], seed: int, side: int = SIDE) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    reference = np.full((side, side, 3), 0.5, np.float32)
    test = reference.copy()
    for r, sigma in zip(rects, sigmas, strict=True):
        test[r.y:r.y + r.h, r.x:r.x + r.w] += rng.normal(0, sigma, (r.h, r.w, 1)).astype(np.float32)
    return test, reference


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.floats(1.0, 8.0))
def test_noise_alone_is_no_seam_whatever_each_units_noise(seed: int, spread: float) -> None:
    rects = grid(4)
    sigmas = list(np.random.default_rng(seed).uniform(0.01, 0.01 * spread, len(rects)))
    measure = seam_measure(*noisy(rects, sigmas, seed), rects)
    # Under noise alone the ratio is a chi-square with one degree of freedom per border piece, over their
    # count: 96 pieces here, deviation 0.14 and a long right tail (3,000 seeds at equal noise reached 1.60),
    # so its bounds are that distribution's one-in-a-million quantiles, not a fixed tolerance.
    n = measure.border_strips
    lo, hi = chi2.ppf(1e-6, n) / n, chi2.ppf(1 - 1e-6, n) / n
    assert not measure.seam and lo < measure.ratio < hi, measure
    assert abs(measure.correlation) < 0.05, measure


@pytest.mark.parametrize("seed", range(5))
def test_noise_correlated_between_neighbours_is_calibrated_away(seed: int) -> None:
    """A 3x3 box filter over white noise (as Mitsuba's gaussian pixel filter correlates neighbours)
    would inflate every strip's z^2 about 4 times; the measured correlation corrects it."""
    rects = grid(4)
    test, reference = noisy(rects, [0.05] * len(rects), seed)
    err = test - reference
    padded = np.pad(err, ((1, 1), (1, 1), (0, 0)), mode="edge")
    smooth = sum(padded[dy:dy + SIDE, dx:dx + SIDE] for dy in range(3) for dx in range(3)) / 9
    measure = seam_measure(reference + smooth, reference, rects)
    assert not measure.seam and measure.correlation > 0.5 and abs(measure.ratio - 1) < 0.35, measure


@pytest.mark.parametrize("width", [3, 4])
def test_a_bias_inside_one_unit_is_a_seam_and_names_it(width: int) -> None:
    rects = grid(4)
    test, reference = noisy(rects, [0.02] * len(rects), seed=1)
    r = rects[5]
    test[r.y:r.y + r.h, r.x:r.x + r.w] += 0.01  # half the noise's sigma: invisible pixel by pixel
    measure = seam_measure(test, reference, rects, width=width)
    assert measure.seam and measure.worst_unit == 5 and measure.unit_z > measure.unit_threshold, measure
    assert measure.ratio > 1.2, measure


def test_a_bias_over_the_whole_image_is_no_seam() -> None:
    """The measure reads steps across borders: a bias everywhere (a wrong exposure, a missing light) has
    none, and `quekaro diff`'s other metrics report it."""
    rects = grid(4)
    test, reference = noisy(rects, [0.02] * len(rects), seed=4)
    assert not seam_measure(test + 0.01, reference, rects).seam


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_skewed_noise_whose_mean_is_off_zero_in_a_region_is_no_seam(seed: int) -> None:
    """As a few samples per pixel of a glossy region render it: most pixels miss the rare bright paths and
    read low, a few read very high, so a strip's mean error is below 0 wherever a border crosses the
    region (the measure that tested each strip against 0 read seams in plain Mitsuba's own still-life)."""
    rng = np.random.default_rng(seed)
    rects = grid(4)
    reference = np.full((SIDE, SIDE, 3), 0.5, np.float32)
    # Lognormal per-pixel means of 16 samples, sigma 2: strongly right-skewed, expectation 0.5.
    sigma = 2.0
    samples = rng.lognormal(np.log(0.5) - sigma**2 / 2, sigma, (SIDE, SIDE, 16)).mean(axis=-1)
    test = np.repeat(samples[..., None], 3, axis=-1).astype(np.float32)
    measure = seam_measure(test, reference, rects)
    assert not measure.seam and abs(measure.ratio - 1) < 0.35, measure


def test_a_smeared_band_step_is_caught_with_a_band_wide_border() -> None:
    """A defect spread over a 4-pixel band (as blended bands would spread it) at every vertical border."""
    rects = grid(4)
    test, reference = noisy(rects, [0.02] * len(rects), seed=2)
    for x in range(SIDE // 4, SIDE, SIDE // 4):
        test[:, x - 2:x + 2] += np.linspace(0.0, 0.02, 4, dtype=np.float32)[None, :, None]
    assert seam_measure(test, reference, rects, width=3).seam


def test_one_unit_black_images_tiny_units_and_bad_input() -> None:
    test, reference = noisy([Rect(0, 0, SIDE, SIDE)], [0.02], seed=3)
    single = seam_measure(test, reference, [Rect(0, 0, SIDE, SIDE)])
    assert single.border_strips == 0 and not single.seam and single.worst_unit == -1
    black = np.zeros((SIDE, SIDE, 3), np.float32)
    assert seam_measure(black, black, grid(4)).border_strips == 0  # no variance: no information
    tiny = grid(32)  # 4-pixel units: strips of 12 pixels
    measure = seam_measure(*noisy(tiny, [0.02] * len(tiny), seed=5), tiny)
    assert not measure.seam and abs(measure.ratio - 1) < 0.2, measure
    with pytest.raises(QuekaroError, match="outside"):
        unit_map([Rect(100, 0, 40, 10)], SIDE, SIDE)
    with pytest.raises(QuekaroError, match="differ in size"):
        seam_measure(black, black[:10], grid(2))
    with pytest.raises(QuekaroError, match="width 0"):
        seam_measure(black, black, grid(2), width=0)
    assert (unit_map(grid(2), SIDE, SIDE)[SIDE // 2:, :SIDE // 2] == 2).all()


@pytest.mark.slow
def test_a_real_composed_render_has_no_seam_and_a_unit_scaled_by_20_percent_has_one(tmp_path) -> None:
    """cbox rendered as units at level off (`quekaro render`) against plain Mitsuba's long render: the
    compositor leaves no seam. The same image with one central unit's pixels scaled by 1.2 (at 16 spp, under a
    pixel's noise) has one, and `quekaro diff --units` names that unit."""
    from render_check import reference_renders  # imports Mitsuba: only this test pays for it

    scene = REPO / "scenes" / "cbox.xml"
    out = tmp_path / "job.exr"
    done = run_quekaro("render", str(scene), "-D", "res=128", "-D", "spp=16", "--opt", "off", "--units", "16",
                       "-o", str(out), "-t", "2")
    assert done.returncode == 0, done.stderr
    reference, _ = reference_renders(scene, "llvm_ad_rgb", 512, defines={"res": "128"}, renders=1)
    imageio.write_exr(tmp_path / "ref.exr", reference[0][..., :3])
    clean = diff_json(out, tmp_path / "ref.exr", out.with_suffix(".json"))
    assert not clean["seam"], clean
    units = json.loads(out.with_suffix(".json").read_text())["units"]
    # A unit inside the image: four borders to see its step across (the corner unit, with two, was missed
    # in one CI run: each job draws its own seeds).
    victim = min(units, key=lambda u: abs(u["rect"][0] + u["rect"][2] / 2 - 64)
                 + abs(u["rect"][1] + u["rect"][3] / 2 - 64))
    x, y, w, h = victim["rect"]
    image = imageio.read_image(out)
    image[y:y + h, x:x + w, :3] *= 1.2
    imageio.write_exr(tmp_path / "scaled.exr", image[..., :3])
    scaled = diff_json(tmp_path / "scaled.exr", tmp_path / "ref.exr", out.with_suffix(".json"))
    assert scaled["seam"] and scaled["worst_unit"] == units.index(victim), scaled


def run_quekaro(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quekaro", *args], capture_output=True, text=True, timeout=600)


def diff_json(test: Path, reference: Path, report: Path) -> dict:
    done = run_quekaro("diff", str(test), str(reference), "--units", str(report), "--json")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)["seams"]


def test_a_seam_width_without_units_is_refused(tmp_path) -> None:
    """--seam-width only sizes the seam measure, which needs the job's units (--units REPORT.json)."""
    image = np.full((8, 8, 3), 0.5, dtype=np.float32)
    imageio.write_exr(tmp_path / "a.exr", image)
    done = run_quekaro("diff", str(tmp_path / "a.exr"), str(tmp_path / "a.exr"), "--seam-width", "5")
    assert done.returncode != 0 and "--seam-width 5: seams are measured only at a job's unit borders" in done.stderr
    done = run_quekaro("diff", str(tmp_path / "a.exr"), str(tmp_path / "a.exr"), "--json")
    assert done.returncode == 0 and json.loads(done.stdout)["rmse"] == 0.0
    (tmp_path / "r.json").write_text(json.dumps({"units": [{"rect": [0, 0, 8, 8]}]}))
    done = run_quekaro("diff", str(tmp_path / "a.exr"), str(tmp_path / "a.exr"), "--units", str(tmp_path / "r.json"),
                       "--seam-width", "0")  # meant the default, 3
    assert done.returncode != 0 and "--seam-width 0: at least one pixel" in done.stderr


def test_the_difference_image_is_a_png_checked_before_measuring(tmp_path) -> None:
    """-o d.exr failed after the comparison and left an empty d.exr; a new folder is made, as render -o does."""
    imageio.write_exr(tmp_path / "a.exr", np.full((8, 8, 3), 0.5, dtype=np.float32))
    done = run_quekaro("diff", str(tmp_path / "a.exr"), str(tmp_path / "a.exr"), "-o", str(tmp_path / "d.exr"))
    assert done.returncode != 0 and "a name ending .png" in done.stderr and not (tmp_path / "d.exr").exists()
    done = run_quekaro("diff", str(tmp_path / "a.exr"), str(tmp_path / "a.exr"), "-o", str(tmp_path / "new" / "d.png"))
    assert done.returncode == 0 and (tmp_path / "new" / "d.png").stat().st_size > 0, done.stderr



def test_diff_names_the_files_of_an_image_it_cannot_measure(tmp_path) -> None:
    """A NaN in the test image or images of two sizes: the error names both files and which is at fault."""
    import OpenEXR

    good = np.full((8, 8, 3), 0.5, dtype=np.float32)
    bad = good.copy()
    bad[2, 3, 1] = np.nan
    imageio.write_exr(tmp_path / "good.exr", good)
    imageio.write_exr(tmp_path / "small.exr", good[:4])
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": bad}) as exr:  # write_exr refuses NaN
        exr.write(str(tmp_path / "nan.exr"))
    done = run_quekaro("diff", str(tmp_path / "nan.exr"), str(tmp_path / "good.exr"))
    assert done.returncode != 0
    assert f"{tmp_path / 'nan.exr'} against {tmp_path / 'good.exr'}: test image: 1 non-finite pixels" in done.stderr
    done = run_quekaro("diff", str(tmp_path / "good.exr"), str(tmp_path / "small.exr"))
    assert done.returncode != 0 and "small.exr: images differ in size: 8x8 vs 8x4" in done.stderr


def test_diff_refuses_images_of_other_colours_and_units_of_another_image(tmp_path) -> None:
    """An X, Y, Z image against an R, G, B one compares unlike channels (it read 5.9 % where the colours
    differ by 1 %), and a report of a 96 px job's units puts borders where a 128 px image has none."""
    image = np.full((8, 8, 3), 0.5, dtype=np.float32)
    imageio.write_exr(tmp_path / "rgb.exr", image)
    imageio.write_exr(tmp_path / "xyz.exr", image, channels=("X", "Y", "Z"))
    imageio.write_exr(tmp_path / "y.exr", image[..., :1], channels=("Y",))
    for other, words in (("xyz.exr", "X, Y, Z"), ("y.exr", "luminance (Y) only")):
        done = run_quekaro("diff", str(tmp_path / other), str(tmp_path / "rgb.exr"))
        assert done.returncode != 0 and f"{tmp_path / other} holds {words} and {tmp_path / 'rgb.exr'} R, G, B" \
            in done.stderr, done.stderr
    done = run_quekaro("diff", str(tmp_path / "xyz.exr"), str(tmp_path / "xyz.exr"), "--json")
    assert done.returncode == 0 and json.loads(done.stdout)["rmse"] == 0.0  # alike colours compare
    report = tmp_path / "r.json"
    report.write_text(json.dumps({"image": {"width": 6, "height": 8}, "units": [{"rect": [0, 0, 6, 8]}]}))
    done = run_quekaro("diff", str(tmp_path / "rgb.exr"), str(tmp_path / "rgb.exr"), "--units", str(report))
    assert done.returncode != 0 and f"--units {report}: its job's image is 6x8, the images compared are 8x8" \
        in done.stderr, done.stderr


def test_a_one_unit_job_has_no_border_to_measure_and_says_so() -> None:
    """It read "worst unit -1 z 0.0 of 4.0", a unit index that is none."""
    image = np.full((8, 8, 3), 0.5, dtype=np.float32)
    line = cmd_diff.seam_line(seam_measure(image, image, [Rect(0, 0, 8, 8)]).to_dict())
    assert line == "no seam (no border between units)"
