"""`quekaro bench denoise`'s cost and blend parts (bench/denoise.py) and the denoiser's quality setting
(core.image.denoise): the blend's weights and their ends, OIDN at each quality, and a real small run of
every part but the filters one, read back from its report."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.denoise import (
    AOV_SEED,
    CONTROL_SEED,
    add_arguments,
    blended,
    feathered,
    raw_weights,
    unit_scores,
)
from bench.denoise import _parsed as parsed
from core.errors import QuekaroError
from core.image.denoise import QUALITIES, denoise
from core.model.geometry import Rect
from core.model.units import WorkUnit

REPO = Path(__file__).resolve().parent.parent
CBOX = REPO / "scenes" / "cbox.xml"


def _unit(index: int, rect: Rect, c: float, nd: float) -> WorkUnit:
    return WorkUnit(index=index, rect=rect, C=c, S=rect.area, Nd=nd, cost=1.0)


UNITS = [_unit(0, Rect(0, 0, 32, 64), 0.1, 0.0), _unit(1, Rect(32, 0, 32, 64), 0.8, 0.5)]  # simple | complex


def test_unit_scores_are_the_mean_of_c_and_nd_over_their_largest() -> None:
    assert np.allclose(unit_scores(UNITS), [0.5 * 0.1 / 0.8, 1.0])
    flat = [_unit(0, Rect(0, 0, 8, 8), 0.0, 0.0), _unit(1, Rect(8, 0, 8, 8), 0.0, 0.0)]
    assert np.array_equal(unit_scores(flat), [0.0, 0.0])


def test_blend_strength_0_is_exactly_the_denoised_image_and_1_exactly_the_raw() -> None:
    rng = np.random.default_rng(1)
    raw, den = (rng.random((64, 64, 3), dtype=np.float32) * 10 for _ in range(2))
    scores = unit_scores(UNITS)
    for by in (scores, np.ones_like(scores)):
        assert np.array_equal(blended(den, raw, raw_weights(UNITS, by, 0.0, 64, 64)), den)
        assert np.array_equal(blended(den, raw, raw_weights(UNITS, by, 1.0, 64, 64)), raw)


def test_blend_keeps_more_raw_in_the_complex_unit_feathered_across_the_border() -> None:
    """Strength 0.5: the simple unit (score 0.0625) keeps 0.5^3.81 = 0.07 of the raw image, the complex
    one 0.5; within width / 32 = 2 px of their border the weight climbs between the two."""
    weights = raw_weights(UNITS, unit_scores(UNITS), 0.5, 64, 64)
    simple, complex_ = 0.5 ** (1 + 3 * (1 - 0.0625)), 0.5
    assert np.allclose(weights[:, :29], simple) and np.allclose(weights[:, 35:], complex_)
    row = weights[10, 28:36]
    assert np.all(np.diff(row) >= 0) and simple < row[3] < row[4] < complex_
    uniform = raw_weights(UNITS, np.ones(2), 0.5, 64, 64)
    assert np.array_equal(uniform, np.full((64, 64), 0.5, np.float32))


def test_feathering_keeps_a_constant_map_exact_and_the_mean() -> None:
    assert np.array_equal(feathered(np.ones((9, 7)), 3), np.ones((9, 7), np.float32))
    step = np.zeros((16, 16))
    step[:, 8:] = 1.0
    soft = feathered(step, 2)
    assert soft[0, 7] == pytest.approx(2 / 5) and soft[0, 8] == pytest.approx(3 / 5) and soft[0, 0] == 0.0


def test_each_oidn_quality_denoises_and_fast_is_another_network() -> None:
    """A flat grey under noise, at each quality: well below the noisy image's MSE (0.01); fast's image is not
    high's; an unknown quality is refused."""
    rng = np.random.default_rng(3)
    colour = 0.5 + rng.normal(0.0, 0.1, (64, 64, 3)).astype(np.float32)
    albedo, normal = np.full((64, 64, 3), 0.5, np.float32), np.zeros((64, 64, 3), np.float32)
    normal[..., 2] = 1.0
    out = {q: denoise(colour, albedo, normal, q) for q in QUALITIES}
    assert all(np.mean((o - 0.5) ** 2) < 0.1 * np.mean((colour - 0.5) ** 2) for o in out.values())
    assert not np.array_equal(out["fast"], out["high"])
    with pytest.raises(ValueError, match="denoiser quality 'best'"):
        denoise(colour, albedo, normal, "best")


def test_the_bench_refuses_an_unknown_part_quality_or_strength() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for bad, message in ((["--parts", "cost,speed"], "--parts cost,speed"), (["--qualities", "best"], "--qualities"),
                         (["--strengths", "0.5,2"], "--strengths 0.5,2")):
        with pytest.raises(QuekaroError, match=message):
            parsed(parser.parse_args(bad))


@pytest.mark.slow
def test_bench_denoise_prints_the_cost_line_the_settings_and_the_blend(tmp_path: Path) -> None:
    """A small real run of the cost, settings and blend parts on a 64 px cbox: real jobs, real OIDN; the
    product's setting (16 spp, high) among those timed, so that its estimated share is the jobs' own."""
    done = subprocess.run([sys.executable, "-m", "quekaro", "bench", "denoise", str(CBOX), "--parts",
                           "cost,settings,blend", "--res", "48", "--ref-spp", "256", "--cost-res", "64",
                           "--cost-spp", "4", "--cost-runs", "1", "--aov-spp", "16,1", "--qualities", "high,fast",
                           "--compare-spp", "4,16", "--strengths", "0.25,0.5", "--out", str(tmp_path),
                           "--cache-dir", str(tmp_path / "cache"), "--json"],
                          capture_output=True, text=True, cwd=REPO, timeout=600)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    report = Path(result["report"]).read_text()
    line = re.search(r"median of 1 scene\(s\): (\d+\.\d)%; target <= 5%: (met|missed)", report)
    assert line and (line.group(2) == "met") == (float(line.group(1)) <= 5.0), report
    run = result["cost"]["scenes"]["cbox"]["runs"][0]
    assert run["size"] == [64, 64] and 0 < run["aov_s"] + run["denoise_s"] < run["total_s"] < run["wall_s"]
    rows = result["settings"]["rows"]
    assert [(r["aov_spp"], r["quality"], r["seed"]) for r in rows] == [
        (16, "high", AOV_SEED), (16, "fast", AOV_SEED), (1, "high", AOV_SEED), (1, "fast", AOV_SEED),
        (16, "high", CONTROL_SEED)]
    assert rows[0]["flip"] == {"4": 1.0, "16": 1.0} and all(r["share"] > 0 for r in rows)
    assert rows[0]["share"] == pytest.approx(result["cost"]["share"])  # the product's setting: the jobs' own share
    assert "| 1 spp, fast |" in report and "| 16 spp, high (control: another seed) |" in report
    assert re.search(r"5% of a job from \d+\.\d s on", report)
    blend = result["blend"]
    assert [(m["spp"], m["mode"], m["strength"]) for m in blend["medians"]][:3] == [
        (4, "raw", 1.0), (4, "rules", 0.25), (4, "uniform", 0.25)]
    assert "| cbox | 4 |" in report and "| cbox | 16 |" in report and "**Blend verdict: the rules' blend" in report
