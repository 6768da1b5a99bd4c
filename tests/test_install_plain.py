"""`pip install .` without extras renders and runs a farm: the runtime dependencies leave out the
benchmarks' (matplotlib, pyfuzzylite), the product runs with those two made unimportable, `quekaro bench`
says which extra to install, and the wheel carries the rules, the schema and the sample scenes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BENCH_ONLY = ("matplotlib", "fuzzylite")
BLOCKER = f'''
import importlib.abc, sys
class _NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in {BENCH_ONLY!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, _NotInstalled())
'''


def test_runtime_dependencies_leave_out_the_benchmarks_own() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    runtime = " ".join(project["dependencies"]).lower()
    assert not [name for name in ("matplotlib", "pyfuzzylite") if name in runtime]
    bench = " ".join(project["optional-dependencies"]["bench"]).lower()
    assert "matplotlib" in bench and "pyfuzzylite" in bench


@pytest.fixture
def without_bench_extras(tmp_path: Path) -> dict[str, str]:
    """An environment in which matplotlib and pyfuzzylite cannot be imported (as after `pip install .`)."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(BLOCKER)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
    probe = subprocess.run([sys.executable, "-c", "import matplotlib"], env=env, capture_output=True, text=True)
    assert probe.returncode != 0 and "matplotlib" in probe.stderr  # the blocker works
    return env


def quekaro(args: list[str], env: dict[str, str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quekaro", *args], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.slow
def test_renders_and_runs_a_farm_without_the_bench_extras(tmp_path: Path, without_bench_extras) -> None:
    env = without_bench_extras
    done = quekaro(["render", str(REPO / "scenes" / "cbox.xml"), "-o", "one.exr", "--spp", "4", "-D", "res=48"],
                   env, tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "one.exr").stat().st_size > 0
    done = quekaro(["demo", "--agents", "2", "--home", str(tmp_path / "farm"), "-o", "demo.exr"], env, tmp_path,
                   timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    report = json.loads((tmp_path / "demo.json").read_text())
    assert report["totals"]["units"] >= 2
    refused = quekaro(["bench", "fuzzy"], env, tmp_path)
    assert refused.returncode == 2 and "quekaro-farm[bench]" in refused.stderr


@pytest.mark.slow
def test_the_wheel_carries_rules_schema_and_scenes(tmp_path: Path) -> None:
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path), str(REPO)],
                   check=True, capture_output=True, timeout=600)
    (wheel,) = tmp_path.glob("quekaro_farm-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for needed in ("core/data/rules/pathtracing.xml", "core/data/scenes/cbox.xml", "fuzzy/quekaro-rules.xsd",
                   "bench/cli.py", "farm/local.py", "planning/pipeline.py"):
        assert needed in names, needed
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    assert "quekaro.commands" in zipfile.ZipFile(wheel).read(entry_points).decode()
