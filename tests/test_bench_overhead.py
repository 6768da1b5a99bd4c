"""`quekaro bench overhead`: a tiny real run of both sides (the whole `quekaro render` process and the
`mitsuba` command), its breakdown of the job's time, and its refusals."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench import overhead

REPO = Path(__file__).resolve().parent.parent


def bench(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quekaro", "bench", "overhead", "--json", "--res", "32",
                           "--spp", "8", "--repeats", "1", "--out", str(tmp_path), *extra],
                          cwd=REPO, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_a_tiny_real_run_times_both_sides_and_splits_the_jobs_time(tmp_path: Path) -> None:
    done = bench(tmp_path, "--levels", "off,S", "--adaptive", "-D", "spp=8")
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert result["defines"] == {"res": "32", "spp": "8"} and result["adaptive"] is True
    off, s = result["levels"]
    assert (off["level"], s["level"]) == ("off", "S")
    assert off["spp"] == 8 and 1 <= s["spp"] <= 8  # the command renders the job's own mean spp
    for row in (off, s):
        assert row["plain_seconds"] > 0 and row["quekaro_seconds"] > 0
        assert row["ratio"] == pytest.approx(row["quekaro_seconds"] / row["plain_seconds"])
        assert row["outside_job_seconds"] > 0 and row["render_seconds"] > 0 and row["rest_seconds"] > 0
        parts = row["outside_job_seconds"] + row["prepass_seconds"] + row["render_seconds"] + row["rest_seconds"]
        assert parts == pytest.approx(row["quekaro_seconds"])
        assert len(row["plain_runs"]) == len(row["quekaro_runs"]) == 1
        assert row["mean_rel_diff"] < 0.5  # the same scene, up to noise at a few spp
    assert off["prepass_seconds"] == 0 and s["prepass_seconds"] > 0  # level off runs no pre-pass
    written = (tmp_path / "overhead.md").read_text()
    assert overhead.format_report(result) in written and "--adaptive" in written
    assert "target: level off quekaro render / the mitsuba command <= 1.03:" in written


@pytest.mark.slow
def test_a_users_scene_keeps_its_own_size_and_its_film_file(tmp_path: Path) -> None:
    """A scene without a `res` parameter, whose film writes PFM: no -D res is forced on it (Mitsuba
    refused the unused parameter) and the job's mean is read from the .pfm it wrote. Mitsuba warns that
    PFM is float32 only: on stderr, so that --json's stdout holds the JSON alone."""
    scene = REPO / "tests" / "compat" / "scenes" / "film_pfm.xml"
    done = subprocess.run([sys.executable, "-m", "quekaro", "bench", "overhead", "--json", "--scene", str(scene),
                           "--spp", "4", "--repeats", "1", "--out", str(tmp_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert 'The PFM format only supports component_format="float32"' in done.stderr
    result = json.loads(done.stdout)
    [off] = result["levels"]
    assert result["defines"] == {} and off["mean_rel_diff"] < 0.5
    assert f"--scene {scene}" in (tmp_path / "overhead.md").read_text()


@pytest.mark.parametrize(("extra", "message"), [
    (("--levels", "XS"), "unknown level 'XS'"),
    (("--repeats", "0"), "--repeats 0"),
    (("-D", "res"), "expected NAME=VALUE"),
    (("--threads", str(os.cpu_count() + 1)), "the mitsuba command renders on all"),
    (("--scene", str(REPO / "tests" / "compat" / "scenes" / "_room.xml")), "has no $spp"),
])
def test_bad_arguments_are_refused_with_the_reason(tmp_path: Path, extra: tuple[str, ...], message: str) -> None:
    done = bench(tmp_path, *extra)
    assert done.returncode != 0 and message in done.stderr
    assert not (tmp_path / "overhead.md").exists()
