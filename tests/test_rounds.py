"""Two-round jobs (planning.rounds, `quekaro render --adaptive`): the whole job against plain Mitsuba
rendering the same file (the same means in every channel the film writes), the report of both rounds,
the round logic at its edges, the worker's counts and noise orders, and the refusals that say why."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from compat_cases import CASES, quekaro, reference
from render_check import FIREFLY_PIXELS, by_name, compare

from core.errors import QuekaroError, RenderError
from core.model.geometry import Rect
from core.model.job import RenderOptions, SceneSpec
from core.render.counts import NOISE_CHANNEL
from core.render.imageio import read_exr_channels
from core.render.worker import RenderRequest, render_job_here
from planning.rounds import Budget, SecondRound, combine, second_round, split_noise

BY_CASE = {c.name: c for c in CASES}
# Level S spends about a sixth of the user's spp on these scenes: 320 gives the jobs about the reference's
# 64, so that pixels lit by rare paths are seen by both sides (at 11 spp eight jobs saw none of a few).
USER_SPP = 320
RUNS = 8  # two-round images per case: their own variance enters the test on the means (with 4 its
# estimate from 3 degrees of freedom made a few pixels look significant that 8 runs did not)


def _render(case, out, units: int = 1) -> subprocess.CompletedProcess:
    args = [str(case.scene), "--opt", "S", "--adaptive", "--units", str(units), "--spp", str(USER_SPP),
            "-s", str(case.sensor), "-o", str(out), "--threads", "2", "--no-progress"]
    for key, value in case.defines.items():
        args += ["-D", f"{key}={value}"]
    return quekaro("render", *args)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["rgba", "aov", "spectral-spiky", "medium-homogeneous", "moment"])
def test_a_two_round_job_keeps_mitsubas_means(name, tmp_path):
    """RUNS jobs (each its own job id, so its own seeds) against 32 of plain Mitsuba's renders: no pixel
    channel's mean differs beyond the fireflies render_check tolerates; the channels are the film's.
    Four units, so that both rounds' bands meet at unit borders (composition cuts each band's filter
    reach: core.render.compose)."""
    case = BY_CASE[name]
    refs, ref_names = reference(case)
    images = []
    for k in range(RUNS):
        out = tmp_path / f"job{k}.exr"
        done = _render(case, out, units=4)
        assert done.returncode == 0, done.stderr[-2000:]
        image, names = read_exr_channels(out)
        assert sorted(names) == sorted(ref_names) and NOISE_CHANNEL not in names
        images.append(by_name(image, names, ref_names))
    verdict = compare(images, refs)
    assert verdict.failing <= FIREFLY_PIXELS, f"{name}: {verdict}"
    rounds = json.loads((tmp_path / "job0.json").read_text())["rounds"]
    assert rounds["first_spp"] == max(1, round(rounds["mean_spp"] * 0.5))
    assert rounds["second_mean_spp"] == pytest.approx(rounds["mean_spp"] - rounds["first_spp"], rel=0.05)


def test_a_two_round_job_renders_its_units_in_both_rounds(tmp_path):
    """--units are the render units of both rounds; every unit's report line counts both rounds."""
    out = tmp_path / "job.exr"
    done = _render(BY_CASE["aov"], out, units=4)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["options"]["adaptive"] is True and len(report["units"]) == 4
    first = report["rounds"]["first_spp"]
    assert all(u["spp"] >= first and u["seconds"] > 0 for u in report["units"])
    assert set(report["compose"]) == {"first_round", "second_round"}
    _, names = read_exr_channels(out)
    assert NOISE_CHANNEL not in names and len(names) == 11


def test_second_round_goes_where_the_noise_is_and_keeps_the_budget():
    spend = Budget(mean_spp=16, first=8)
    spot = np.full((32, 32), 0.01)
    spot[:8, :8] = 10.0
    second = second_round(spot, spend, seed=3, filter_radius=2.0)
    assert second.adapted and second.predicted < 0.95
    assert second.counts[:4, :4].min() > 8 > second.counts[24:, 24:].max()
    assert abs(second.counts.sum() - 8 * spot.size) < 0.02 * 8 * spot.size
    flat = second_round(np.full((32, 32), 0.2), spend, seed=3, filter_radius=2.0)
    assert not flat.adapted and (flat.counts == 8).all()  # nothing to gain: the rest uniformly
    spent = second_round(spot, Budget(mean_spp=1, first=1), seed=3, filter_radius=2.0)
    assert not spent.counts.any()  # round one took the whole budget


def test_window_combine_and_split_edges():
    counts = np.arange(20).reshape(4, 5)
    second = SecondRound(counts, 0.5, True)
    assert second.window(Rect(1, 2, 3, 2)).tolist() == [[11, 12, 13], [16, 17, 18]]
    a, b = np.ones((3, 4, 5), np.float32), np.full((3, 4, 5), 3.0, np.float32)
    both = combine(a, b, Budget(4, 2), SecondRound(np.full((4, 5), 2), 0.5, True))
    assert np.allclose(both, 2.0)  # equal counts: the plain average
    only_first = combine(a, b, Budget(4, 2), SecondRound(np.zeros((4, 5), int), 1.0, False))
    assert np.allclose(only_first, 1.0)  # no second-round samples: round one's value
    with pytest.raises(QuekaroError, match="differ in shape"):
        combine(a, b[:2], Budget(4, 2), second)
    image, names, noise = split_noise(np.zeros((4, 2, 2)), ("R", "G", "B", NOISE_CHANNEL))
    assert image.shape == (3, 2, 2) and names == ("R", "G", "B") and noise.shape == (2, 2)
    with pytest.raises(QuekaroError, match=NOISE_CHANNEL):
        split_noise(np.zeros((3, 2, 2)), ("R", "G", "B"))


def _request(**extra) -> RenderRequest:
    case = BY_CASE["rgba"]
    return RenderRequest(SceneSpec(case.scene), case.variant, None, None, 8, 5, 48, 40, Rect(16, 8, 24, 16),
                         band=2, threads=2, **extra)


def test_a_noise_order_returns_each_pixels_noise_as_its_last_channel():
    tile = render_job_here(_request(noise=True))
    assert tile.channels[-1] == NOISE_CHANNEL and tile.channels[:3] == ("R", "G", "B")
    assert tile.pixels.shape == (20, 28, len(tile.channels))  # the unit grown by its band
    noise = tile.pixels[..., -1]
    assert (noise >= 0).all() and noise.any()


def test_counts_must_fit_the_window():
    with pytest.raises(RenderError, match="do not match the window 20x28"):
        _request(counts=np.ones((16, 24), dtype=np.int64))  # the unit's shape, not its window's
    with pytest.raises(RenderError, match="non-negative integers"):
        _request(counts=np.full((20, 28), -1))


def test_adaptive_needs_a_rule_level_and_a_boolean():
    with pytest.raises(QuekaroError, match="adaptive sampling places a rule level"):
        RenderOptions(level="off", adaptive=True)
    with pytest.raises(QuekaroError, match="not true or false"):
        RenderOptions(level="S", adaptive="yes")
    assert RenderOptions.from_dict(RenderOptions(level="S", adaptive=True).to_dict()).adaptive is True
