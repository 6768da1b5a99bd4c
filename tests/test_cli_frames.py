"""Jobs and frame sequences from the command line, on a real local farm: `submit --wait -o` writes the image,
`result` names it after the scene (a frame's SCENE_0001.exr), several scenes say which id is which, `status`
shows a job's parameters and a sequence as one line, and `watch`, `status`, `cancel`, `result` take a
sequence id."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from core.image.imageio import read_image
from core.model.geometry import DEFAULT_FILTER_RADIUS, filter_reach
from farm.client import FarmClient
from farm.local import LocalFarm

REPO = Path(__file__).resolve().parent.parent
CBOX, GLASS = REPO / "scenes" / "cbox.xml", REPO / "scenes" / "glass-corner.xml"
SMALL = ["-D", "res=16", "--units", "1"]


@pytest.fixture(scope="module")
def home(tmp_path_factory: pytest.TempPathFactory):
    with LocalFarm(tmp_path_factory.mktemp("farm") / "home", agents=1, threads=1) as farm:
        farm.wait_for_agents()
        yield farm.home


def quekaro(home: Path, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, "-m", "quekaro", *args, "--home", str(home)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)
    assert "Traceback" not in done.stderr, done.stderr
    return done


def images(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.glob("*.exr"))


@pytest.mark.slow
def test_a_frame_range_is_one_sequence_written_frame_by_frame(home: Path, tmp_path: Path) -> None:
    sent = quekaro(home, "submit", str(CBOX), *SMALL, "-D", "spp=1:3", "--wait", "-o", str(tmp_path / "out"))
    assert sent.returncode == 0, sent.stderr
    first, *_ = sent.stdout.splitlines()
    sequence, scene, frames = first.split("  ")
    assert sequence.startswith("seq-") and (scene, frames) == ("cbox.xml", "3 frames"), first
    assert images(tmp_path / "out") == ["cbox_0001.exr", "cbox_0002.exr", "cbox_0003.exr"]

    status = quekaro(home, "status", sequence).stdout.splitlines()
    assert status[0].startswith(f"{sequence}  done      3/3 frames  3/3 units  cbox.xml"), status
    assert [line.split("  ")[0] for line in status[1:]] == ["frame 1", "frame 2", "frame 3"], status
    frame_jobs = [line.split("  ")[1] for line in status[1:]]
    listed = quekaro(home, "status").stdout.splitlines()
    assert any(line.startswith(f"{sequence}  done      3/3 frames") for line in listed), listed
    assert not [line for line in listed if line.split("  ")[0] in frame_jobs]  # grouped under the sequence

    fetched = quekaro(home, "result", sequence, cwd=tmp_path)
    assert fetched.returncode == 0 and images(tmp_path) == images(tmp_path / "out"), fetched.stderr
    watched = quekaro(home, "watch", sequence)
    assert watched.stdout.splitlines()[-1] == f"{sequence} done: 3/3 frames 3/3 units, agents busy 0", watched.stdout
    frame = quekaro(home, "result", frame_jobs[1], "-o", str(tmp_path / "one"))
    assert frame.returncode == 0 and images(tmp_path / "one") == ["cbox_0002.exr"], frame.stderr
    assert quekaro(home, "cancel", sequence).stdout == f"{sequence}: had already ended\n"


@pytest.mark.slow
def test_several_files_with_sequence_are_its_frames_in_order(home: Path, tmp_path: Path) -> None:
    sent = quekaro(home, "submit", str(CBOX), str(GLASS), *SMALL, "--spp", "1", "--sequence", "--wait",
                   "-o", str(tmp_path))
    assert sent.returncode == 0, sent.stderr
    lines = sent.stdout.splitlines()
    sequence = lines[2].split("  ")[0]
    assert lines[0].endswith("  cbox.xml  frame 1") and lines[1].endswith("  glass-corner.xml  frame 2"), lines
    assert lines[2] == f"{sequence}  2 frames" and sequence.startswith("seq-"), lines
    assert images(tmp_path) == ["cbox_0001.exr", "glass-corner_0002.exr"]


@pytest.mark.slow
def test_several_scenes_say_which_id_is_which_and_status_shows_the_parameters(home: Path, tmp_path: Path) -> None:
    sent = quekaro(home, "submit", str(CBOX), str(GLASS), *SMALL, "--spp", "2", "--name", "shot 1", "--wait")
    assert sent.returncode == 0, sent.stderr
    ids = [line.split("  ") for line in sent.stdout.splitlines() if line.endswith(".xml")]
    assert [scene for _id, scene in ids] == ["cbox.xml", "glass-corner.xml"], sent.stdout
    shown = quekaro(home, "status", ids[0][0]).stdout
    assert 'job: cbox.xml, level off, 2 spp, 16x16, -D res=16  "shot 1"' in shown, shown
    both = quekaro(home, "status", "shot 1")  # a name stands for the id where one job has it
    named = ", ".join(sorted(i for i, _ in ids))
    assert both.returncode == 2 and f"2 jobs are named 'shot 1'; give one's id: {named}" in both.stderr, both.stderr
    take = quekaro(home, "submit", str(CBOX), *SMALL, "--spp", "1", "--name", "take 7", "--wait")
    assert take.returncode == 0, take.stderr
    fetched = quekaro(home, "result", "take 7", cwd=tmp_path)
    assert fetched.returncode == 0 and (tmp_path / "cbox.exr").is_file(), fetched.stderr
    assert quekaro(home, "status", "take 7").stdout.startswith(take.stdout.splitlines()[0])


@pytest.mark.slow
def test_submit_wait_writes_the_image_and_result_names_it_after_the_scene(home: Path, tmp_path: Path) -> None:
    sent = quekaro(home, "submit", str(CBOX), *SMALL, "--spp", "1", "--wait", "-o", str(tmp_path / "mine.exr"))
    assert sent.returncode == 0 and (tmp_path / "mine.exr").is_file(), sent.stderr
    job_id = sent.stdout.splitlines()[0]
    fetched = quekaro(home, "result", job_id, cwd=tmp_path)
    assert fetched.returncode == 0 and fetched.stdout.startswith("cbox.exr  report: cbox.json"), fetched.stdout
    assert (tmp_path / "cbox.png").is_file() and (tmp_path / "cbox.json").is_file()


@pytest.mark.slow
def test_a_cancelled_sequence_ends_wait_with_its_reason(home: Path) -> None:
    waiting = subprocess.Popen([sys.executable, "-m", "quekaro", "submit", str(CBOX), "-D", "res=64", "-D",
                                "spp=4000:4002", "--units", "1", "--wait", "--home", str(home)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        sequence = waiting.stdout.readline().split("  ")[0]
        cancelled = quekaro(home, "cancel", sequence)
        assert cancelled.stdout == f"{sequence}: every frame still running cancelled\n", cancelled.stderr
        _out, err = waiting.communicate(timeout=300)
    finally:
        if waiting.poll() is None:
            waiting.kill()
            waiting.wait()
    assert waiting.returncode == 1 and f"job {sequence} cancelled" in err, err


@pytest.mark.slow
def test_ctrl_c_on_submit_wait_stops_the_watching_not_the_job(home: Path) -> None:
    waiting = subprocess.Popen([sys.executable, "-m", "quekaro", "submit", str(CBOX), "-D", "res=64", "--spp", "4000",
                                "--units", "1", "--wait", "--home", str(home)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        job_id = waiting.stdout.readline().strip()
        while not waiting.stdout.readline().startswith(f"{job_id} "):  # a progress line: it is watching
            pass
        waiting.send_signal(signal.SIGINT)
        _out, err = waiting.communicate(timeout=60)
    finally:
        if waiting.poll() is None:
            waiting.kill()
            waiting.wait()
    assert waiting.returncode == 130, err
    assert (f"stopped watching; {job_id} goes on on the farm: quekaro cancel {job_id} stops it, "
            f"quekaro result {job_id} fetches it") in err, err
    assert "Traceback" not in err, err
    status = quekaro(home, "status", job_id).stdout
    assert re.match(rf"{job_id}\s+(running|queued)", status), status  # the job goes on
    assert quekaro(home, "cancel", job_id).returncode == 0


def _cancelled_after(home: Path, args: list[str], ready) -> str:
    """A job submitted with `args`, cancelled once its status satisfies `ready`: its id."""
    sent = quekaro(home, "submit", str(CBOX), *args)
    assert sent.returncode == 0, sent.stderr
    job_id = sent.stdout.strip()
    client = FarmClient.from_home(home)
    deadline = time.monotonic() + 120
    while not ready(client.status(job_id)):
        assert time.monotonic() < deadline, client.status(job_id)
        time.sleep(0.05)
    assert client.cancel(job_id) is True
    return job_id


@pytest.mark.slow
def test_a_cancelled_job_gives_its_tiles_so_far_with_partial_black_where_no_unit_landed(home: Path,
                                                                                        tmp_path: Path) -> None:
    """`result` of a cancelled job refuses, saying --partial gives its tiles so far; with --partial it writes
    SCENE.partial.exr: the units that landed as rendered, the others black, and the report names them."""
    job_id = _cancelled_after(home, ["-D", "res=64", "--spp", "4000", "--units", "4"], lambda j: j["units_done"])
    refused = quekaro(home, "result", job_id, cwd=tmp_path)
    assert refused.returncode == 2, refused.stderr
    assert f"{job_id}: cancelled by the user; --partial writes its tiles so far" in refused.stderr
    fetched = quekaro(home, "result", job_id, "--partial", cwd=tmp_path)
    assert fetched.returncode == 0 and fetched.stdout.startswith("cbox.partial.exr  report: cbox.partial.json")
    report = json.loads((tmp_path / "cbox.partial.json").read_text())
    missing = report["partial"]["units_missing"]
    assert report["partial"]["status"] == "cancelled" and 1 <= len(missing) <= 3, report["partial"]
    assert f"partial: cancelled; {len(missing)} of 4 units have no tile (black)" in fetched.stdout
    image = read_image(tmp_path / "cbox.partial.exr")[..., :3]
    landed = np.zeros(image.shape[:2], bool)
    for unit in report["units"]:
        x, y, w, h = unit["rect"]
        landed[y:y + h, x:x + w] = True
    assert sorted(u["index"] for u in report["units"]) == sorted(set(range(4)) - set(missing))
    assert np.all(np.isfinite(image)) and (image[landed].max(axis=-1) > 0).mean() > 0.9  # cbox: lit everywhere
    reach = max(u["band"] for u in report["units"]) + filter_reach(DEFAULT_FILTER_RADIUS)  # past its unit
    far = ~binary_dilation(landed, iterations=reach)
    assert far.any() and np.all(image[far] == 0)


@pytest.mark.slow
def test_a_cancelled_job_in_passes_gives_every_unit_from_its_passes_so_far(home: Path, tmp_path: Path) -> None:
    """A budget job in passes, cancelled once each unit has a pass: its partial image has every unit."""
    job_id = _cancelled_after(home, ["-D", "res=64", "--spp", "4096", "--units", "4", "--progressive"],
                              lambda j: j["passes"]["done"] >= 4)
    fetched = quekaro(home, "result", job_id, "--partial", "-o", str(tmp_path / "shot.exr"))
    assert fetched.returncode == 0, fetched.stderr
    report = json.loads((tmp_path / "shot.json").read_text())
    assert report["partial"]["units_missing"] == [] and report["partial"]["tiles"] >= 4
    assert "partial: cancelled; every unit has a tile, from " in fetched.stdout, fetched.stdout
    image = read_image(tmp_path / "shot.exr")[..., :3]
    assert np.all(np.isfinite(image)) and (image.max(axis=-1) > 0).mean() > 0.9


@pytest.mark.slow
def test_a_running_job_gives_its_tiles_so_far_composed_again_as_passes_land(home: Path, tmp_path: Path) -> None:
    """`result` of a running job says --partial gives its tiles so far; --partial composes them then, and again
    once more passes have landed (its report counts them, and describes the image fetched); once the job is
    cancelled the image says so."""
    sent = quekaro(home, "submit", str(CBOX), "-D", "res=64", "--time", "60", "--spp", "65536", "--units", "4")
    assert sent.returncode == 0, sent.stderr
    job_id = sent.stdout.strip()
    client = FarmClient.from_home(home)

    def passes_done_over(n: int) -> int:
        deadline = time.monotonic() + 60
        while (done := client.status(job_id)["passes"]["done"]) <= n:
            assert time.monotonic() < deadline, client.status(job_id)
            time.sleep(0.05)
        return done

    passes_done_over(3)
    refused = quekaro(home, "result", job_id, cwd=tmp_path)
    assert refused.returncode == 2 and f"{job_id}: running; --partial writes its tiles so far" in refused.stderr

    def fetch(name: str) -> tuple[dict, np.ndarray]:
        fetched = quekaro(home, "result", job_id, "--partial", "-o", str(tmp_path / name))
        assert fetched.returncode == 0, fetched.stderr
        report = json.loads((tmp_path / name).with_suffix(".json").read_text())
        assert "partial" in report, fetched.stdout  # not the image of a job that ended meanwhile
        report = report["partial"]
        assert f"partial: {report['status']}; every unit has a tile, from " in fetched.stdout, fetched.stdout
        return report, read_image(tmp_path / name)[..., :3]

    first, first_image = fetch("first.exr")
    assert first["status"] == "running" and first["units_missing"] == [] and first["tiles"] >= 4
    passes_done_over(first["tiles"])
    later, later_image = fetch("later.exr")
    assert later["status"] == "running" and later["tiles"] > first["tiles"]
    assert np.all(np.isfinite(later_image)) and np.any(later_image != first_image)  # more samples, composed again
    assert client.cancel(job_id) is True
    ended, _ = fetch("ended.exr")
    assert ended["status"] == "cancelled" and ended["tiles"] >= later["tiles"]
