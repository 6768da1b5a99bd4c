"""A progressive job on a real two-agent farm: its passes are auctioned as units, merged on the master as
they land, and the job ends when every unit's estimated error is under the threshold; its image is the
one-process job's up to noise, and its estimate honest against plain Mitsuba's converged image."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from render_check import by_name, compare, reference_renders
from test_progressive_render import RES, SCENE, _reference, true_errors

from core.image.imageio import read_image
from core.image.metrics import relmse
from core.image.tiles import tile_source
from farm.local import LocalFarm
from master.store import JobStore
from tests.test_farm import bundle_of, wait_job

TAU = 0.05
DEFINES = {"res": str(RES), "spp": "1024"}
EVERY_PASS = 1  # the master's --pass-samples: these small units still render their five passes


@pytest.mark.slow
def test_a_noise_job_on_a_farm_meets_its_threshold_honestly_and_matches_one_process(tmp_path: Path) -> None:
    with LocalFarm(tmp_path / "farm", agents=2, threads=1) as farm:
        farm.wait_for_agents()
        client = farm.client()
        job_id = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "noise": TAU, "units": 9})
        job = wait_job(farm, job_id)
        assert job["status"] == "done", job
        out = client.result(job_id, tmp_path / "farm.exr")
    report = json.loads(out.with_suffix(".json").read_text())
    progressive = report["render_calls"]["progressive"]
    units = report["units"]
    assert progressive["goal"] == "noise" and progressive["reason"].startswith(f"{len(units)} of {len(units)} units")
    assert len(units) == 9 and {u["verdict"] for u in units} == {"met"}
    assert all(u["relative_error_estimate"] <= TAU and u["passes"] >= 4 for u in units)
    assert len({a for u in units for a in u["agent"].split(", ")}) == 2  # the passes of the job on both agents
    image = read_image(out)[..., :3]
    true = true_errors(image, _reference(), units, TAU)
    assert max(true) < 1.3 and np.median(true) < 1.1, true
    # the same job in one process: each image carries relative error ~TAU, so their relMSE is ~2 TAU^2
    local = tmp_path / "local.exr"
    from test_cli import quekaro

    done = quekaro("render", str(SCENE), "-D", f"res={RES}", "-D", "spp=1024", "--noise", str(TAU), "--units",
                   "9", "-o", str(local), "--no-progress", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert relmse(image, read_image(local)[..., :3]) < 3 * TAU ** 2


@pytest.mark.slow
def test_a_budget_job_on_a_farm_renders_each_units_samples_in_halving_passes(tmp_path: Path) -> None:
    """--progressive: every unit gets its 64 spp in passes of 32, 16, 8, 4 and 4 (an idle agent's extra
    pass stands in for a slow one and never adds to it), the job ends when all have them, every pass it
    keeps is done, and the image is the plain job's up to noise."""
    defines = {"res": str(RES), "spp": "64"}
    with LocalFarm(tmp_path / "farm", agents=2, threads=1, pass_samples=EVERY_PASS) as farm:
        farm.wait_for_agents()
        client = farm.client()
        passes = client.submit(bundle_of(SCENE, defines), defines, {"level": "off", "progressive": True, "units": 9})
        whole = client.submit(bundle_of(SCENE, defines), defines, {"level": "off", "units": 9})
        ended = {job_id: wait_job(farm, job_id) for job_id in (passes, whole)}
        assert all(job["status"] == "done" for job in ended.values()), ended
        assert ended[passes]["units_done"] == ended[passes]["units_total"], ended[passes]  # none withdrawn left
        out = client.result(passes, tmp_path / "passes.exr")
        plain = client.result(whole, tmp_path / "whole.exr")
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["render_calls"]["progressive"]["goal"] == "budget"
    assert report["render_calls"]["progressive"]["reason"].startswith("every unit has its samples")
    units = report["units"]
    assert len(units) == 9 and all(u["verdict"] == "budget" and u["passes"] >= 5 and u["spp"] == 64 for u in units)
    a, b = read_image(out)[..., :3], read_image(plain)[..., :3]
    assert relmse(a, b) < 0.05 and abs(a.mean() / b.mean() - 1) < 0.03  # 64 spp each: noise alone
    # Its passes drew their samples on their own units, their bands taking the spill: the tiles, added up
    # on the master, are plain Mitsuba's image at 64 spp pixel by pixel, seams included.
    assert any(r.startswith("bands: each unit's samples are drawn on its own pixels")
               for r in report["effects"]["reasons"]), report["effects"]["reasons"]
    ref, names = reference_renders(SCENE, report["effects"]["variant"], 64, defines={"res": str(RES)})
    verdict = compare(by_name(read_image(out), tuple(report["image"]["channels"]), names), ref)
    assert verdict.passed, verdict


@pytest.mark.slow
def test_a_budget_job_at_a_rule_level_renders_as_in_one_process_each_unit_at_one_depth(tmp_path: Path) -> None:
    """--progressive --opt VS: the master's plan pins each unit's depth and samples (the rules'), as
    `quekaro render` does: the two reports agree unit by unit, every pass tile of a unit says its depth,
    and the images agree up to noise."""
    defines = {"res": str(RES), "spp": "64"}
    options = {"level": "VS", "progressive": True, "units": 9}
    with LocalFarm(tmp_path / "farm", agents=2, threads=1, pass_samples=EVERY_PASS) as farm:
        farm.wait_for_agents()
        job_id = farm.client().submit(bundle_of(SCENE, defines), defines, options)
        assert wait_job(farm, job_id)["status"] == "done"
        out = farm.client().result(job_id, tmp_path / "farm.exr")
        with JobStore(farm.home / "jobs.sqlite", readonly=True) as store:
            pinned = {u.index: u.depth for u in store.units(job_id)}
            depths = {r.index: tile_source(r.tile_path).meta["depth"] for r in store.results(job_id)}
    n = 9
    assert all(depths[i] == pinned[i % n] == pinned[i] for i in depths) and len(depths) >= 5 * n
    from test_cli import quekaro

    local = tmp_path / "local.exr"
    done = quekaro("render", str(SCENE), "-D", f"res={RES}", "-D", "spp=64", "--opt", "VS", "--progressive",
                   "--units", "9", "-o", str(local), "--no-progress", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    lines = [json.loads(p.with_suffix(".json").read_text())["units"] for p in (out, local)]
    chosen = [[(u["rect"], u["depth"], u["spp"], u["rules"]) for u in units] for units in lines]
    assert chosen[0] == chosen[1] and len({spp for _, _, spp, _ in chosen[0]}) > 1, chosen
    a, b = read_image(out)[..., :3], read_image(local)[..., :3]
    assert relmse(a, b) < 0.05 and abs(a.mean() / b.mean() - 1) < 0.03
