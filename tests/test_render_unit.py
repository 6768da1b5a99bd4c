"""Unit rendering: jobs, seeds, the shifted-camera window, and the crash-proof child process."""

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from lxml import etree

from core.errors import RenderError, SceneError
from core.model.geometry import Rect
from core.model.job import RenderOptions, SceneSpec
from core.model.seeds import plan_seed, unit_seed
from core.render import spawn
from core.render.process import (
    RenderProcess,
    RenderRequest,
    _local_cache,
    _SceneCache,
    render_full,
    render_job_here,
    set_window,
)
from core.rules.unit_params import Planner
from planning.jobplan import plan_job, plan_params
from planning.pipeline import plan_for_units_here, unit_job

REPO = Path(__file__).resolve().parent.parent
CBOX = SceneSpec(REPO / "scenes" / "cbox.xml", {"res": "48", "spp": "4"})
DATA = REPO / "tests" / "data" / "scenes"
VARIANT = "llvm_ad_rgb"


UNIT = Rect(8, 16, 16, 16)


def job(unit=UNIT, spp=16, seed=1, spec=CBOX, size=(48, 48), band=2, **kw):
    return RenderRequest(spec, VARIANT, "path", 4, spp, seed, size[0], size[1], unit, band=band, threads=1, **kw)


@pytest.fixture(scope="module")
def worker():
    with RenderProcess() as w:
        yield w


def test_plan_seeds_follow_the_scene_and_the_pre_pass_options_only():
    opts = {"level": "S", "spp": 64, "threads": 2}
    seed = plan_seed("ab" * 32, {"res": "64"}, opts)
    assert 0 <= seed < 2**31
    assert seed != plan_seed("cd" * 32, {"res": "64"}, opts)
    assert seed != plan_seed("ab" * 32, {"res": "65"}, opts)
    for shaping in ({"spp": 65}, {"depth": 3}, {"sensor": 1}, {"integrator": "direct"}, {"variant": "scalar_rgb"}):
        assert seed != plan_seed("ab" * 32, {"res": "64"}, {**opts, **shaping}), shaping
    # what only reads the pre-pass: every level of a scene reads one, so the levels keep the rules' order
    for reading in ({"threads": 1}, {"level": "N"}, {"rules": "x.xml"}, {"defuzzifier": "mom"}, {"units": 9},
                    {"adaptive": True}):
        assert seed == plan_seed("ab" * 32, {"res": "64"}, {**opts, **reading}), reading


def test_unit_seeds_are_distinct_and_stable():
    seeds = {unit_seed("job", u, p) for u in range(200) for p in range(3)}
    assert len(seeds) == 600 and all(0 <= s < 2**32 for s in seeds)
    assert unit_seed("job", 3, 1) == unit_seed("job", 3, 1) != unit_seed("job2", 3, 1)


def test_job_round_trip_and_refusals():
    j = job(job_id="abc", unit_index=5)
    assert RenderRequest.from_dict(j.to_dict()) == j
    assert j.window == Rect(6, 14, 20, 20)
    # at the image's edge the window is shifted inside, keeping its size: the band it lacks is on the far side
    assert job(unit=Rect(0, 0, 4, 4), band=10).window == Rect(0, 0, 24, 24)
    assert job(unit=Rect(40, 2, 8, 4), band=10).window == Rect(20, 0, 28, 24)
    assert job(unit=Rect(0, 0, 40, 4), band=10).window == Rect(0, 0, 48, 24)  # wider than the image: all of it
    with pytest.raises(RenderError, match="spp=0"):
        job(spp=0)
    with pytest.raises(RenderError, match="outside"):
        job(unit=Rect(40, 40, 16, 16))
    with pytest.raises(RenderError, match="malformed"):
        RenderRequest.from_dict({"scene": {"path": "x"}})


def test_shifted_camera_renders_the_same_pixels_as_a_crop():
    """Same seed, same window: the kernel-friendly shift and Mitsuba's crop give the same image."""
    import mitsuba as mi

    cache = _SceneCache()
    j = job(unit=Rect(20, 8, 16, 24), spp=8, size=(48, 48))
    shifted = render_job_here(j, cache)
    assert shifted.meta["window_method"] == "shift"
    scene, _ = cache.scene_for(j.scene, VARIANT, 1)
    params = mi.traverse(scene.sensors()[0])
    params["principal_point_offset_x"], params["principal_point_offset_y"] = cache.principal_point(0)
    params.update()
    set_window(scene, j.window, None)  # a real crop at the window's offset, camera as loaded
    cropped = np.array(mi.render(scene, integrator=cache.integrator("path", 4), spp=8, seed=j.seed))
    assert np.allclose(shifted.pixels, cropped[..., :3], rtol=1e-4, atol=1e-5)


def test_unit_matches_the_same_region_of_a_full_render():
    """With a band of the filter's reach (2 px, gaussian) the unit's core is the full render's region."""
    full = render_full(CBOX, VARIANT, "path", 4, 128, seed=11, threads=1)
    unit = Rect(8, 8, 24, 24)  # takes in the light's edge, where a band-less crop is visibly biased
    region = full[unit.slices()]
    core = render_job_here(job(unit=unit, spp=128, seed=12, band=2)).core_pixels()
    diff = (core - region).mean(axis=-1).ravel()
    stderr = diff.std() / np.sqrt(diff.size)
    assert abs(diff.mean()) < 4 * stderr
    assert abs(core.mean() / region.mean() - 1) < 0.03


def test_seeds_make_the_noise():
    a = render_job_here(job(seed=1)).pixels
    b = render_job_here(job(seed=1)).pixels
    c = render_job_here(job(seed=2)).pixels
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    assert np.corrcoef((a - c).ravel(), (b - c).ravel())[0, 1] > 0.99  # same noise, not merely close


def test_worker_renders_and_caches_the_scene(worker):
    first = worker.render(job(unit_index=0, job_id="j"), timeout=120)
    start = time.perf_counter()
    second = worker.render(job(seed=2), timeout=120)
    elapsed = time.perf_counter() - start
    assert first.rect == Rect(6, 14, 20, 20) and first.core == Rect(8, 16, 16, 16)
    assert first.meta["unit_index"] == 0 and first.meta["nonfinite"] == 0
    assert second.meta["load_seconds"] == 0.0 and second.meta["pid"] == first.meta["pid"] == worker.pid
    assert elapsed < 2.0
    assert np.isfinite(first.pixels).all() and first.pixels.mean() > 0


def test_broken_scene_is_a_scene_error_and_the_worker_survives(worker, tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text('<scene version="3.0.0"><shape type="nosuchplugin"/></scene>')
    pid = worker.pid
    with pytest.raises(SceneError, match=r"broken.xml"):
        worker.render(job(spec=SceneSpec(bad), size=(768, 576)), timeout=60)
    assert worker.pid == pid
    assert worker.render(job(), timeout=60).pixels.shape == (20, 20, 3)


def test_killed_child_is_a_render_error_and_the_worker_restarts():
    with RenderProcess() as w:
        w.render(job(), timeout=60)
        pid = w.pid
        killer = threading.Timer(0.3, os.kill, (pid, signal.SIGKILL))
        killer.start()
        with pytest.raises(RenderError, match="SIGKILL"):
            w.render(job(unit=Rect(0, 0, 48, 48), spp=20000, band=0), timeout=60)
        killer.join()
        tile = w.render(job(), timeout=60)
        assert tile.meta["pid"] != pid and w.starts == 2


def test_an_abort_ends_its_own_render_only_also_one_set_before_the_render_began():
    """A cancelled unit's render (the agent's AbortRender): set before the render began, the abort was lost
    and the render ran in full; `interrupt` with no render aborted, or another render's, kills nothing."""
    with RenderProcess() as w:
        w.render(job(), timeout=60)
        pid = w.pid
        w.interrupt()  # idle: the child and its compiled kernels stay
        assert w.pid == pid and w.alive()
        early = threading.Event()
        early.set()
        with pytest.raises(RenderError, match="interrupted"):
            w.render(job(), timeout=60, abort=early)
        assert w.render(job(), timeout=60, abort=threading.Event()).meta["pid"] == pid  # not this render's
        late = threading.Event()
        ender = threading.Timer(0.3, lambda: (late.set(), w.interrupt()))
        ender.start()
        started = time.monotonic()
        with pytest.raises(RenderError, match="SIGKILL"):
            w.render(job(unit=Rect(0, 0, 48, 48), spp=20000, band=0), timeout=60, abort=late)
        ender.join()
        assert time.monotonic() - started < 20  # ended, not rendered to its end
        assert w.render(job(), timeout=60).meta["pid"] != pid


def test_a_released_child_exits_and_the_next_render_starts_another():
    with RenderProcess() as w:
        first = w.render(job(), timeout=60)
        child = w._proc
        w.release()
        w.release()  # a second release sends nothing more
        assert child.wait(30) == 0 and not w.alive()  # it exits on its own, cleanly
        tile = w.render(job(), timeout=60)
        assert tile.meta["pid"] != first.meta["pid"] and w.starts == 2 and w.alive()


def test_a_released_child_skips_its_teardown_yet_leaves_its_compiled_kernels(tmp_path, monkeypatch):
    # It ends with os._exit: what it compiled must already be in Dr.Jit's cache ($HOME/.drjit), or every
    # job would compile its kernels again.
    monkeypatch.setenv("HOME", str(tmp_path))
    with RenderProcess() as w:
        w.render(job(), timeout=120)
        child = w._proc
        w.release()
        assert child.wait(30) == 0
    kernels = list((tmp_path / ".drjit").glob("*.llvm.*.bin"))
    assert kernels and all(k.stat().st_size > 0 for k in kernels)


def test_a_call_runs_in_the_child_and_what_it_raises_comes_back():
    with RenderProcess() as w:
        assert w.call(os.getpid) == w.pid != os.getpid()
        with pytest.raises(ValueError, match="invalid literal") as raised:
            w.call(int, "x")
        assert "in the render process" in str(raised.value.__notes__)
        with pytest.raises(RenderError, match="XMLSyntaxError"):  # it cannot cross the pipe: told as text
            w.call(etree.fromstring, "<a")
        missing = SceneSpec(DATA / "no-such-scene.xml")
        options = RenderOptions(level="S", spp=4, threads=1)
        with pytest.raises(SceneError, match=r"no-such-scene\.xml"):  # the planner's own error, as in process
            w.call(plan_job, missing, options, 0, doing="planning")
        assert w.starts == 1 and w.render(job(), timeout=60).meta["pid"] == w.pid  # the same child goes on


def test_a_child_dying_in_a_call_is_a_render_error_and_the_next_use_restarts():
    with RenderProcess() as w:
        pid = w.call(os.getpid)
        with pytest.raises(RenderError, match=r"planning: render process killed by SIGKILL"):
            w.call(os.kill, pid, signal.SIGKILL, doing="planning")
        assert w.call(os.getpid) != pid and w.starts == 2
        with pytest.raises(RenderError, match="sleeping: timed out"):
            w.call(time.sleep, 30, doing="sleeping", timeout=0.5)
        assert not w.alive() and w.render(job(), timeout=60).meta["pid"] not in (pid, None)


def test_a_child_started_early_is_the_next_workers_and_one_left_over_is_ended():
    spawn.start_early()
    early = spawn._early[0]
    with RenderProcess() as w:
        assert w.pid == early.pid and w.starts == 1 and w.call(os.getpid) == early.pid
    spawn.start_early()
    left = spawn._early[0]
    spawn.discard_early()
    assert left.wait(5) is not None and spawn._early is None
    spawn.start_early()
    dead = spawn._early[0]
    dead.kill()
    dead.wait()
    with RenderProcess() as w:  # a dead early child is replaced
        assert w.pid != dead.pid and w.render(job(), timeout=60).meta["pid"] == w.pid


def test_timeout_kills_and_recovers():
    with RenderProcess() as w:
        with pytest.raises(RenderError, match="timed out"):
            w.render(job(unit=Rect(0, 0, 48, 48), spp=50000, band=0), timeout=0.5)
        assert w.render(job(), timeout=60).pixels.shape == (20, 20, 3)


def test_infinite_radiance_gives_a_finite_tile_and_a_count():
    spec = SceneSpec(DATA / "inf_emitter.xml", {"width": "16", "height": "16"})
    tile = render_job_here(job(spec=spec, size=(16, 16), unit=Rect(0, 0, 16, 16), spp=4, band=0))
    assert np.isfinite(tile.pixels).all()
    assert tile.meta["nonfinite"] > 0


@pytest.mark.parametrize("size", [(1, 1), (1, 7), (9, 1)])
def test_degenerate_image_sizes(size):
    spec = SceneSpec(DATA / "tiny.xml", {"width": str(size[0]), "height": str(size[1])})
    tile = render_job_here(job(spec=spec, size=size, unit=Rect(0, 0, size[0], size[1]), spp=4, band=3))
    assert tile.pixels.shape == (size[1], size[0], 3) and tile.pixels.mean() > 0


def test_film_size_mismatch_is_refused():
    with pytest.raises(RenderError, match=r"image \(its crop window\) is 48x48, job says 64x64"):
        render_job_here(job(size=(64, 64)))


COMPAT = REPO / "tests" / "compat" / "scenes"


@pytest.mark.parametrize(("spec", "options"), [
    (CBOX, RenderOptions(level="S", spp=16, threads=1, adaptive=True, units=4)),  # after the pre-pass's renders
    (SceneSpec(COMPAT / "orthographic.xml"), RenderOptions(level="off", spp=4, threads=1, units=4)),
    (SceneSpec(COMPAT / "two_sensors.xml"),
     RenderOptions(level="N", spp=8, threads=1, sensor=1, adaptive=True, units=4)),
], ids=["cbox-S-adaptive", "orthographic-off", "second-sensor-N-adaptive"])
def test_the_units_render_the_scene_the_planning_loaded_as_a_fresh_load_would(spec, options):
    """The scene the analysis loaded (and the pre-pass rendered at another film size) is the one the
    units render, and their tiles equal those of a scene loaded afresh, seed for seed."""
    plan = plan_for_units_here(spec, options, seed=5)
    chosen = plan_params(plan, Planner(plan.options.rules, plan.options.defuzzifier))
    assert len(plan.units) > 1
    for unit, params in zip(plan.units, chosen, strict=True):
        order = unit_job(plan, unit, params, "adopted", 1)
        kept, fresh = render_job_here(order), render_job_here(order, _SceneCache())
        assert kept.meta["load_seconds"] == 0.0 < fresh.meta["load_seconds"]
        assert kept.meta["window_method"] == fresh.meta["window_method"]
        np.testing.assert_allclose(kept.pixels, fresh.pixels, rtol=1e-5, atol=1e-6)
    assert _local_cache.key[0] == spec.key()


def test_an_adaptive_unit_in_a_scalar_variant_is_refused_with_the_reason(worker):
    """An agent that fell back to scalar (no LLVM) cannot trace the per-pixel counts' wavefront: the unit
    fails with the reason (the master then awards it elsewhere), and a plain unit still renders there."""
    adaptive = RenderRequest(CBOX, "scalar_rgb", "path", 4, 8, 1, 48, 48, UNIT, band=2, threads=1, first=4)
    with pytest.raises(RenderError, match=r"adaptive sampling .* needs an llvm_\* or cuda_\* .* scalar_rgb"):
        worker.render(adaptive, timeout=120)
    plain = worker.render(RenderRequest(CBOX, "scalar_rgb", "path", 4, 8, 1, 48, 48, UNIT, band=2, threads=1),
                          timeout=120)
    assert plain.meta["variant"] == "scalar_rgb" and np.isfinite(plain.pixels).all() and plain.pixels.mean() > 0


def test_a_tile_says_the_spp_its_sampler_rendered(tmp_path):
    """Mitsuba rounds a stratified sampler's count to a square (11 -> 16): the tile's header says the 16 it
    rendered, not the 11 asked (the report's samples come from it); independent takes 11 as it is."""
    strat = tmp_path / "cbox.xml"
    strat.write_text((REPO / "scenes" / "cbox.xml").read_text().replace('sampler type="independent"',
                                                                       'sampler type="stratified"'))
    assert 'sampler type="stratified"' in strat.read_text()
    said = [render_job_here(job(spec=s, spp=11, band=0)).meta["spp"]
            for s in (CBOX, SceneSpec(strat, {"res": "48", "spp": "4"}))]
    assert said == [11, 16]
