"""Emulated agents (`quekaro agent --emulate COSTS.json`, agents/emulate.py): the real agent with its render
slept from a cost map. A 2-agent job runs through real processes (the embedded XMPP server, the master,
two `quekaro agent --emulate` processes, as `quekaro bench hosts` starts them): it completes, every tile is
its unit's window, no agent loaded Mitsuba or Dr.Jit, every line they log says EMULATED and so does the
job's report. A cost map that cannot be used is refused, naming its file."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agents.emulate import MARK, CostMap, Emulation
from agents.render_agent import build_parser, config_from_args
from bench.hosts import EmulatedFarm, StoreView, make_job, speeds_for
from core.errors import QuekaroError
from core.image.tiles import tile_source
from core.model.geometry import Rect
from core.model.job import SceneSpec
from core.render.process import RenderRequest

REPO = Path(__file__).resolve().parent.parent
W, H = 80, 48  # the test job's image: not square, so a swapped axis shows


def _costs(tmp_path: Path, per_sample: float = 1e-5, shape: tuple[int, int] = (12, 20)) -> Path:
    """A uniform cost map, coarser than the image (each cell stands for 4x4 pixels of the 80x48 job)."""
    return CostMap(np.full(shape, per_sample), fixed_s=0.01, width=W, height=H).write(tmp_path / "costs.json")


def test_cost_map_seconds_stretch_over_the_image(tmp_path):
    grid = np.zeros((3, 4))
    grid[2, 3] = 1e-3  # one costly cell, bottom right
    costs = CostMap.from_file(CostMap(grid, fixed_s=0.5).write(tmp_path / "c.json"))
    # In a 40x30 image each cell is 10x10 pixels, each pixel costing what its cell says.
    assert costs.seconds(Rect(30, 20, 10, 10), 2, 40, 30) == pytest.approx(0.5 + 2 * 100 * 1e-3)
    assert costs.seconds(Rect(35, 25, 5, 5), 1, 40, 30, speed=2.0) == pytest.approx((0.5 + 25e-3) / 2)
    assert costs.seconds(Rect(0, 0, 30, 30), 64, 40, 30) == pytest.approx(0.5)


def test_emulated_worker_returns_the_window_it_slept_for(tmp_path):
    emulation = Emulation.load(_costs(tmp_path, 1e-6), factor=2.0)
    unit = Rect(10, 0, 20, 16)
    request = RenderRequest(SceneSpec(tmp_path / "never-read.xml"), "emulated", None, 8, 64, 3, W, H, unit,
                            band=2, job_id="j", unit_index=4)
    tile = emulation.worker.render(request)
    assert tile.rect == Rect(8, 0, 24, 20) and tile.core == unit  # at the top edge: both bands below
    assert tile.pixels.shape == (20, 24, 3) and tile.meta["emulated"] is True
    assert tile.meta["seconds"] >= (0.01 + 64 * 24 * 20 * 1e-6) / 2 * 0.9  # each pixel costs its cell


@pytest.mark.parametrize("content, says", [
    (None, "cannot read the cost map"),
    ("{not json", "cannot read the cost map"),
    ('{"format": "something/else"}', "expected 'quekaro-costs/1'"),
    ('{"format": "quekaro-costs/1", "seconds_per_sample": [[1, -2]]}', "seconds >= 0"),
])
def test_a_bad_cost_map_is_refused_naming_the_file(tmp_path, content, says):
    path = tmp_path / "bad-costs.json"
    if content is not None:
        path.write_text(content)
    done = subprocess.run([sys.executable, "-m", "quekaro", "agent", "--jid", "agent-1@localhost",
                           "--password", "pw", "--master", "master@localhost", "--master-url", "http://127.0.0.1:1",
                           "--workdir", str(tmp_path / "w"),
                           "--emulate", str(path)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert str(path) in done.stderr and says in done.stderr, done.stderr
    assert all(line.startswith(MARK) for line in done.stderr.splitlines() if line.strip()), done.stderr


def test_speed_needs_emulate():
    args = build_parser().parse_args(["--jid", "a@localhost", "--password", "p", "--master", "m@localhost",
                                      "--master-url", "http://127.0.0.1:1", "--speed", "2"])
    with pytest.raises(QuekaroError, match="--speed"):
        config_from_args(args)


def _wait_for_done_logs(logs: Path, job_id: str, units: int, timeout: float = 30.0) -> None:
    """Wait until the agents have logged `units` units of the job done. The master counts a unit done once
    its tile is on disk, a moment before the agent hears its upload ended and logs it: a SIGTERM sent at
    once could stop the agent in between."""
    pattern = re.compile(rf"unit \d+ of job {re.escape(job_id)}: done in ")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if sum(len(pattern.findall(log.read_text())) for log in logs.glob("agent-*.log")) >= units:
            return
        time.sleep(0.1)
    told = [line for log in sorted(logs.glob("agent-*.log")) for line in log.read_text().splitlines()
            if job_id in line]
    raise AssertionError(f"the agents logged fewer than {units} units of job {job_id} done within {timeout} s; "
                         "what they logged of it:\n" + "\n".join(told[-40:]))


def test_two_emulated_agents_complete_a_job(tmp_path):
    costs = CostMap.from_file(_costs(tmp_path))
    job = make_job(costs, REPO / "scenes" / "caustic-corner.xml", spp=64, width=W, height=H, units=6)
    with EmulatedFarm(tmp_path / "farm", tmp_path / "costs.json", speeds_for(2)) as farm:
        client = farm.client(timeout=120)
        job_id = client.submit(job.bundle, job.defines, job.options)
        status = client.wait(job_id, 120, poll=0.2, while_waiting=farm.check_alive)
        assert status["status"] == "done", status
        client.result(job_id, tmp_path / "result.exr")
        _wait_for_done_logs(tmp_path / "farm" / "logs", job_id, 6)
        farm.stop_agents()
        store = StoreView.read(farm.home, job_id)
        workdirs = [farm.workdir(i) for i in range(2)]
    report = json.loads((tmp_path / "result.json").read_text())
    assert report["totals"]["emulated_units"] == len(report["units"]) == 6
    assert all(u["emulated"] and u["rules"].startswith(MARK) for u in report["units"])
    for result, window in zip(store.results, store.windows(W, H), strict=True):
        tile = tile_source(result["tile_path"])
        assert tile.rect == window and tile.channels == ("R", "G", "B") and tile.meta["emulated"] is True
    for folder in workdirs:
        summary = json.loads((folder / "emulation.json").read_text())
        assert summary["heavy_modules"] == [], summary["heavy_modules"]
        assert summary["counts"]["out register"] >= 1 and summary["counts"]["out heartbeat"] >= 1
        assert "out inform" not in summary["counts"]  # a unit is answered by its upload alone
    assert {a["agent"] for a in store.attempts} <= set(farm.jids)
    for log in (tmp_path / "farm" / "logs").glob("agent-*.log"):
        lines = [line for line in log.read_text().splitlines() if line.strip()]
        assert lines and all(line.startswith(MARK) for line in lines), log.read_text()[-2000:]
