"""A denoised job on a real two-agent farm: the agents render with the box filter, the master renders the
denoiser's AOV pass and denoises what it composed, and the client fetches the raw image beside the result;
the same job in one process (`quekaro render --denoise`) gives the same image up to noise."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from core.image.denoise import DENOISER_CHANNELS, denoise_planar
from core.image.metrics import relmse
from farm.local import LocalFarm
from tests.test_farm import SCENE, bundle_of, wait_job

REPO = Path(__file__).resolve().parent.parent
DEFINES = {"res": "64", "spp": "16"}


def _exr(path: Path) -> dict[str, np.ndarray]:
    with OpenEXR.File(str(path)) as f:
        return {name: np.array(c.pixels, dtype=np.float32) for name, c in f.channels().items()}


def _aov_planes(raw: dict[str, np.ndarray]) -> np.ndarray:
    """The denoiser's six planes as the raw image keeps them (albedo RGB as one channel, normal X, Y, Z)."""
    albedo = np.moveaxis(raw["denoise_albedo"], -1, 0)
    return np.concatenate([albedo, np.stack([raw[name] for name in DENOISER_CHANNELS[3:]])])


def _local(tmp_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The same job denoised by `quekaro render`: (denoised RGB, raw RGB)."""
    out = tmp_path / "local.exr"
    cmd = [sys.executable, "-m", "quekaro", "render", str(SCENE), "--denoise", "-o", str(out), "-t", "2",
           "--no-progress", *(a for k, v in DEFINES.items() for a in ("-D", f"{k}={v}"))]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert done.returncode == 0, done.stderr
    return _exr(out)["RGB"], _exr(out.with_suffix("").with_suffix(".raw.exr"))["RGB"]


@pytest.mark.slow
def test_a_denoised_farm_job_denoises_what_it_composed_and_matches_one_process(tmp_path: Path) -> None:
    """Tolerances: the result is half floats (2^-11 relative), so its denoising is redone from the raw image
    to relMSE 1e-4; two denoised renders of other seeds differ by their residual noise, measured at about a
    tenth of the raw noise here, so under half of it passes and a raw or wrongly filtered image fails."""
    with LocalFarm(tmp_path / "farm", agents=2, threads=1) as farm:
        farm.wait_for_agents()
        client = farm.client()
        job_id = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "denoise": True})
        job = wait_job(farm, job_id)
        assert job["status"] == "done", job
        out = client.result(job_id, tmp_path / "farm.exr")
        kept = (farm.home / "jobs" / job_id / "aov-pass.npy").is_file()
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["denoise"]["raw"] == str(tmp_path / "farm.raw.exr") and report["denoise"]["filter"] == "box"
    assert kept and len({u["agent"] for u in report["units"]}) == 2
    image, raw = _exr(out), _exr(tmp_path / "farm.raw.exr")
    assert set(image) == {"RGB"} and set(raw) >= {"RGB", "denoise_albedo", "denoise_normal.Z"}
    again = denoise_planar(np.moveaxis(raw["RGB"], -1, 0), ("R", "G", "B"), _aov_planes(raw))
    assert relmse(image["RGB"], np.moveaxis(again, 0, -1)) < 1e-4
    local, local_raw = _local(tmp_path)
    assert relmse(image["RGB"], local) < 0.5 * relmse(raw["RGB"], local), (relmse(image["RGB"], local),
                                                                           relmse(raw["RGB"], local))
    assert abs(raw["RGB"].mean() - local_raw.mean()) / local_raw.mean() < 0.06  # as tests/test_farm.py states
