"""`quekaro bench threshold`: the progressive job to a noise goal against uniform spp reaching it in every
unit, end to end on a small suite scene, and its arithmetic."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.threshold import (
    HONEST_FACTOR,
    claims,
    format_report,
    needed_spp,
    next_spp,
    reference_corrected,
    summary,
    unit_relmse,
)
from core.image.metrics import RELMSE_EPSILON
from core.model.geometry import Rect

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_bench_threshold_measures_the_job_and_uniform_spp_at_the_same_goal(tmp_path):
    # TAU 0.03 at 64 px: the job renders past its first passes (at 0.1 they already meet it), and the
    # reference has ~4x the samples of the most any unit gets.
    tau = 0.03
    cmd = [sys.executable, "-m", "quekaro", "bench", "threshold", "cbox", "--res", "64", "--ref-spp", "1024",
           "--noise", str(tau), "--spp", "1024", "--units", "4", "--json", "--out", str(tmp_path / "out"),
           "--cache-dir", str(tmp_path / "cache")]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert result["noise"] == tau and result["spp_cap"] == 1024 and set(result["scenes"]) == {"cbox"}
    scene = result["scenes"]["cbox"]
    p, u = scene["progressive"], scene["uniform"]
    assert scene["size"] == [64, 64] and p["units"] == len(p["rects"]) == len(p["spp"]) == len(p["true_over_tau"])
    assert sum(w * h for _, _, w, h in p["rects"]) == 64 * 64  # the units tile the image
    assert p["wall_s"] > p["render_s"] > 0 and p["units_render_s"] > 0
    # each side timed twice in turn (the default --repeats), the fastest kept
    assert len(p["runs_s"]) == len(u["runs_s"]) == 2 and result["repeats"] == 2
    assert p["render_s"] == min(p["runs_s"]) and u["seconds"] == min(u["runs_s"]) > 0
    assert p["passes"] >= 4 * p["units"] and p["rounds"] >= 2
    assert set(p["verdicts"]) <= {"met", "cap"} and 0 <= p["honest"] <= p["units"]
    assert all(0 < t <= r for t, r in zip(p["true_over_tau"], p["raw_over_tau"], strict=True))
    assert p["spp_spread"]["min"] <= p["spp_spread"]["median"] <= p["spp_spread"]["max"] <= 1024
    assert u["probe_spp"] == 64 and 1 <= u["spp"] <= 1024 and u["seconds"] > 0 and not u["capped"]
    assert 1 <= len(u["renders"]) <= 2 and u["renders"][-1]["spp"] == u["spp"]
    assert 1 / 1.5 < u["worst_over_tau"] < 1.5, u  # the probe's prediction brought the worst unit to TAU
    assert math.isfinite(scene["time_ratio"]) and scene["time_ratio"] > 0
    assert scene["time_ratio"] == pytest.approx(p["render_s"] / u["seconds"])
    assert result["median_time_ratio"] == pytest.approx(scene["time_ratio"])
    assert result["honest_share"] == pytest.approx(p["honest"] / p["units"])
    assert len(list((tmp_path / "cache" / "references").glob("cbox-*.exr"))) == 1
    text = (tmp_path / "out" / "threshold.md").read_text()
    assert text.startswith("# Rendering to a noise threshold against uniform spp (`quekaro bench threshold cbox")
    assert "| cbox | tune | 0.03 |" in text and "load average (1 min)" in text and "the fastest of 2" in text
    assert "target: units whose true error is within 1.2 x their claim:" in text
    assert "target: median render time, progressive / uniform:" in text and ("PASS" in text or "MISS" in text)


@pytest.mark.slow
def test_bench_threshold_measures_each_scene_in_a_process_of_its_own_under_a_name_of_its_own(tmp_path):
    # The suite's cbox and the project's scenes/cbox.xml: one stem, told apart by their folders.
    cmd = [sys.executable, "-m", "quekaro", "bench", "threshold", "cbox", str(REPO / "scenes" / "cbox.xml"),
           "--res", "32", "--ref-spp", "256", "--noise", "0.05", "--spp", "256", "--units", "4", "--repeats", "1",
           "--json", "--out", str(tmp_path / "out"), "--cache-dir", str(tmp_path / "cache")]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert {n: s["role"] for n, s in result["scenes"].items()} == {"cbox-cbox": "tune", "scenes-cbox": "user"}
    assert result["all_units"] == sum(s["progressive"]["units"] for s in result["scenes"].values())
    assert all(len(s["progressive"]["runs_s"]) == len(s["uniform"]["runs_s"]) == 1  # --repeats reached each child
               for s in result["scenes"].values())
    ratios = sorted(s["time_ratio"] for s in result["scenes"].values())
    assert result["median_time_ratio"] == pytest.approx(sum(ratios) / 2)
    text = (tmp_path / "out" / "threshold.md").read_text()
    assert "| cbox-cbox | tune |" in text and "| scenes-cbox | user |" in text


@pytest.mark.parametrize(("option", "says"), [("--units", "--units 0: at least 1"),
                                              ("--probe-spp", "--probe-spp 0: at least 1"),
                                              ("--noise", "--noise 0.0: a positive relative error"),
                                              ("--repeats", "--repeats 0: at least 1")])
def test_a_goal_or_count_it_cannot_run_with_is_refused_before_anything_renders(tmp_path, option, says):
    cmd = [sys.executable, "-m", "quekaro", "bench", "threshold", "cbox", option, "0", "--out", str(tmp_path / "out")]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=120)
    assert done.returncode == 2 and says in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "out").exists()


def test_the_spp_needed_scales_the_probe_by_its_relmse_over_tau_squared():
    assert needed_spp(64, 4 * 0.05**2, 0.05) == 256
    assert needed_spp(64, 0.05**2, 0.05) == 64  # the probe is just enough: no rounding up past it
    assert needed_spp(64, 0.05**2 / 4, 0.05) == 16  # more than enough: fewer samples than the probe
    assert needed_spp(64, 1.001 * 0.05**2, 0.05) == 65  # any shortfall rounds up
    assert needed_spp(64, 1e-12, 0.05) == 1 and needed_spp(64, 0.0, 0.05) == 1  # no noise: one sample
    with pytest.raises(ValueError):
        needed_spp(64, 0.01, 0.0)


def test_a_uniform_render_is_predicted_again_only_where_it_missed_tau_by_over_a_tenth():
    tau = 0.05
    assert next_spp(1000, (1.05 * tau) ** 2, tau, 4096) is None  # near enough
    assert next_spp(1000, (0.95 * tau) ** 2, tau, 4096) is None
    assert next_spp(1000, (1.5 * tau) ** 2, tau, 4096) == 2250  # short: the spp it predicts
    assert next_spp(1000, (0.5 * tau) ** 2, tau, 4096) == 250  # over-sampled: fewer
    assert next_spp(1000, (3 * tau) ** 2, tau, 4096) == 4096  # never past the cap
    assert next_spp(4096, (1.5 * tau) ** 2, tau, 4096) is None  # at the cap and short: nothing more to try
    assert next_spp(1, 0.0, tau, 4096) is None  # one sample of a noiseless scene is the least there is


def test_the_references_share_of_the_measured_relmse_is_taken_out():
    # Against a reference of R samples an image of n measures v/n + v/R; its own share is v/n.
    v, n, ref = 0.3, 256, 1024
    assert reference_corrected(v / n + v / ref, n, ref) == pytest.approx(v / n)
    assert reference_corrected([0.2, 0.2], [1024, 0], 1024) == pytest.approx([0.1, 0.2])
    assert reference_corrected(0.0, 64, 1024) == 0.0


def test_each_units_relmse_is_over_its_own_rectangle():
    ref = np.ones((4, 6, 3))
    image = ref.copy()
    image[:, 3:] = 1.5  # the right half off by 0.5 in every channel
    rects = [Rect(0, 0, 3, 4), Rect(3, 0, 3, 4), Rect(0, 0, 6, 4)]
    assert unit_relmse(image, ref, rects) == pytest.approx([0.0, 0.25 / (1 + RELMSE_EPSILON),
                                                            0.125 / (1 + RELMSE_EPSILON)])


def test_a_unit_claims_tau_where_it_met_it_and_its_estimate_at_the_cap():
    units = [{"verdict": "met", "relative_error_estimate": 0.04}, {"verdict": "cap", "relative_error_estimate": 0.09},
             {"verdict": "met", "relative_error_estimate": None}]
    assert claims(units, 0.05) == pytest.approx([0.05, 0.09, 0.05])


def _scene(honest: int, units: int, ratio: float) -> dict:
    spread = {"min": 0.8, "median": 1.0, "max": 1.1}
    return {"role": "tune", "time_ratio": ratio,
            "progressive": {"units": units, "honest": honest, "render_s": 2.0, "wall_s": 3.0, "at_cap": 1,
                            "runs_s": [2.5, 2.0],
                            "spp_spread": {"min": 16, "median": 64, "max": 1024}, "true_over_tau_spread": spread,
                            "raw_over_tau_spread": spread},
            "uniform": {"spp": 1024, "predicted_spp": 1500, "says_spp": 2000, "capped": True, "seconds": 4.0,
                        "runs_s": [4.0, 4.25],
                        "worst_over_tau": 1.3, "worst_raw_over_tau": 1.4, "probe_predicted_spp": 700,
                        "renders": [{"worst_over_tau": 1.6}, {"worst_over_tau": 1.3}]}}


def test_the_targets_pool_the_units_and_take_the_median_ratio():
    scenes = {"a": _scene(19, 20, 0.5), "b": _scene(19, 20, 0.7), "c": _scene(20, 20, 0.6)}
    found = summary(scenes)
    assert found["honest_share"] == pytest.approx(58 / 60) and found["median_time_ratio"] == pytest.approx(0.6)
    assert [t["pass"] for t in found["targets"]] == [True, True]
    missed = summary({"a": _scene(18, 20, 0.61)})
    assert [t["pass"] for t in missed["targets"]] == [False, False]
    text = format_report({"noise": 0.05, "spp_cap": 1024, "res": 64, "units": 16, "ref_spp": 4096, "probe_spp": 64,
                          "threads": 2, "repeats": 2, "seconds": 12.0, "load": [1.0, 2.0],
                          "scenes": {"a": _scene(19, 20, 0.5)},
                          **summary({"a": _scene(19, 20, 0.5)})})
    assert "| a | tune | 0.05 | 2.00 (3.00) | 16 / 64 / 1024 | 1024 (needs 2000, capped); the probe's 700 gave " \
           "1.60 TAU | 4.00 | 1.30 (1.40) | 0.50 | 2.50, 2.00 / 4.00, 4.25 | 19 of 20, 1 at the cap |" in text
    assert f"target: units whose true error is within {HONEST_FACTOR:g} x their claim: 95.0% (19 of 20) " \
           "(target >= 95%): PASS" in text
    assert "target: median render time, progressive / uniform: 0.50 (target <= 0.6): PASS" in text
    assert "load average (1 min) 1.0 at the start, 2.0 at the end" in text
