"""A farm's folders are its user's alone (issue 62): `core.home.make_private` closes a home that others
could read and sets umask 077, and every file a real farm writes while it renders a job is 0600."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from core.errors import QuekaroError
from core.home import make_private
from farm.local import LocalFarm
from tests.test_farm import SCENE, bundle_of, wait_job


@pytest.fixture(autouse=True)
def _umask_022():
    """Files made as most users' umask makes them (a farm started in this process set 077), restored after."""
    before = os.umask(0o022)
    yield
    os.umask(before)


def _open_to_others(home: Path) -> list[str]:
    return [f"{p} {stat.filemode(p.lstat().st_mode)}" for p in [home, *home.rglob("*")]
            if not p.is_symlink() and p.lstat().st_mode & 0o077]


def test_a_home_others_could_read_is_closed_with_all_it_holds_and_new_files_are_private(tmp_path: Path) -> None:
    home = tmp_path / "home"
    (home / "jobs").mkdir(parents=True)
    home.chmod(0o755)
    (home / "jobs.sqlite").write_text("x")
    (home / "jobs.sqlite").chmod(0o644)
    (home / "jobs" / "tile.exr").write_text("x")
    (home / "jobs" / "tile.exr").chmod(0o664)
    outside = tmp_path / "outside.txt"
    outside.write_text("x")
    outside.chmod(0o644)
    (home / "link").symlink_to(outside)
    assert make_private(home) == 4  # the home, jobs/, and the two files; not the link's target
    assert _open_to_others(home) == [] and stat.S_IMODE(outside.stat().st_mode) == 0o644
    assert make_private(home) == 0
    (home / "new").write_text("x")
    assert stat.S_IMODE((home / "new").stat().st_mode) == 0o600


@pytest.mark.skipif(os.getuid() != 0, reason="needs root to give a folder to another user (CI runs as root)")
def test_a_home_of_another_user_is_refused(tmp_path: Path) -> None:
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    os.chown(theirs, 65534, 65534)
    with pytest.raises(QuekaroError, match=rf"--home {theirs}: the folder belongs to user id 65534, not to this user"):
        make_private(theirs)


@pytest.mark.slow
def test_every_file_a_farm_writes_while_it_renders_a_job_is_its_users_alone(tmp_path: Path) -> None:
    home = tmp_path / "farm"
    home.mkdir()
    home.chmod(0o755)
    defines = {"res": "32", "spp": "4"}
    with LocalFarm(home, agents=1, threads=1) as farm:
        farm.wait_for_agents()
        client = farm.client()
        job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "off"})
        assert wait_job(farm, job_id)["status"] == "done"
        client.result(job_id, tmp_path / "out.exr")
        written = {p.name for p in home.rglob("*")}
        assert {"jobs.sqlite", "admin.token", "master.log", "result.exr"} <= written, written
        assert _open_to_others(home) == []


@pytest.mark.slow
def test_a_farm_run_inside_a_program_gives_its_umask_back(tmp_path: Path) -> None:
    """A test or a benchmark that runs a LocalFarm in its own process keeps its umask once the farm stops."""
    with LocalFarm(tmp_path / "farm", agents=1, threads=1) as farm:
        farm.wait_for_agents()
        during = os.umask(0o077)
        os.umask(during)
    after = os.umask(0o022)
    assert (during, after) == (0o077, 0o022)
