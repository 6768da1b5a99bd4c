"""The compatibility suite's scenes (tests/compat/scenes): one per kind of input users bring, each with the
variant the effect analysis must choose and how it is rendered (spp, sensor, -D parameters, -a paths)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from render_check import (
    Verdict,
    by_name,
    compare,
    file_kind,
    file_quantum,
    mitsuba_file_kind,
    reference_renders,
)

from core.image.imageio import read_image_channels
from farm.client import FarmClient

SCENES = Path(__file__).resolve().parent / "compat" / "scenes"
RGB, SPECTRAL, POLARIZED = "llvm_ad_rgb", "llvm_ad_spectral", "llvm_ad_spectral_polarized"


@dataclass(frozen=True)
class Case:
    name: str
    file: str
    variant: str = RGB
    spp: int = 64
    sensor: int = 0
    defines: dict[str, str] = field(default_factory=dict)
    units: int = 6  # enough to have bands between tiles in both directions
    search: tuple[str, ...] = ()  # -a folders, relative to SCENES
    whole: bool = False  # rendered as one unit whatever --units asks (its samples or crops cannot be tiled)
    rendered_spp: int | None = None  # what Mitsuba's sampler takes for `spp`, where it rounds it

    @property
    def unit_spp(self) -> int:
        """The spp each unit's report entry must give: what was rendered."""
        return self.rendered_spp or self.spp

    @property
    def scene(self) -> Path:
        return SCENES / self.file


CASES = (
    Case("moment", "moment.xml"),
    Case("aov", "aov.xml"),
    Case("search-path", "searchpath/scene/scene.xml"),
    Case("search-path-a", "searchpath/scene/needs_a.xml", search=("searchpath/common",)),
    Case("file-names", "file names/scène d'été.xml"),  # spaces and accents in the scene's and its include's names
    Case("default-integrator", "default_integrator.xml", defines={"integrator": "direct"}),
    Case("sampler-default", "sampler_default.xml", spp=4),  # no sample_count: the sampler's default
    Case("sampler-stratified", "sampler_stratified.xml", spp=50, rendered_spp=64),  # rounded to a square
    Case("thinlens", "thinlens.xml"),  # depth of field
    Case("film-sample-border", "sample_border.xml"),  # samples beyond the tiles' and the image's edges
    Case("direct", "direct.xml"),
    Case("spectral-flat", "spectral_flat.xml"),
    Case("spectral-spiky", "spectral_spiky.xml", variant=SPECTRAL),
    Case("spectral-file", "spectral_file.xml", variant=SPECTRAL),  # a .spd file read before any variant is set
    Case("spectral-grey-box", "spectral_grey_box.xml", variant=SPECTRAL),  # colours stored as coefficients
    Case("nested-depths", "nested_depths.xml"),  # nested integrators of different depths
    Case("instancing", "instancing.xml"),
    Case("medium-homogeneous", "medium_homogeneous.xml"),
    Case("medium-grid", "medium_grid.xml"),
    Case("emitters-textured", "emitters_textured.xml"),
    Case("orthographic", "orthographic.xml"),
    Case("second-sensor", "two_sensors.xml", sensor=1),
    Case("rgba", "rgba.xml"),
    Case("lanczos", "lanczos.xml"),
    Case("film-crop", "crop.xml"),
    Case("film-xyza", "film_xyza.xml"),
    Case("film-luminance-alpha", "film_luminance_alpha.xml"),
    Case("film-pfm", "film_pfm.xml"),
    Case("film-rgbe", "film_rgbe.xml"),
    Case("film-uint32", "film_uint32.xml"),
    Case("radiancemeter", "radiancemeter.xml", whole=True),
    Case("irradiancemeter", "irradiancemeter.xml", spp=256, whole=True),  # a sensor carried by a shape
    Case("polarized-stokes", "stokes.xml", variant=POLARIZED),
    Case("batch-sensor", "batch.xml", whole=True),  # its crops are not its image's parts
    Case("ptracer", "ptracer.xml", whole=True),  # its light paths land anywhere on the film
)


# ---- running a case, shared by tests/test_compat.py and tests/compat_report.py ---------------------------

REPO = SCENES.parent.parent.parent
_refs: dict[str, tuple] = {}


def job_args(case: Case) -> list[str]:
    """The `quekaro render` / `quekaro submit` arguments of a case (level off: no rules)."""
    args = [str(case.scene), "--opt", "off", "--units", str(case.units), "-s", str(case.sensor)]
    for key, value in case.defines.items():
        args += ["-D", f"{key}={value}"]
    for folder in case.search:
        args += ["-a", str(SCENES / folder)]
    return args


# Level S spends about a sixth of the user's spp on these scenes: 320 gives adaptive jobs about the
# reference's 64, so that pixels lit by rare paths are seen by both sides (at 11 spp eight jobs saw none of a few).
ADAPTIVE_SPP = 320


def adaptive_args(case: Case, units: int) -> list[str]:
    """The case as an adaptive job (`--adaptive`) at level S in `units` units, for render and submit alike."""
    args = job_args(case)
    args[args.index("--opt") + 1], args[args.index("--units") + 1] = "S", str(units)
    return [*args, "--adaptive", "--spp", str(ADAPTIVE_SPP)]


def check_adaptive_report(report: dict, units: int) -> None:
    """An adaptive job's report: the plan's shares, each unit rendered in two passes at its share, and the
    shares spending the level's samples."""
    shared = report["adaptive"]
    assert report["options"]["adaptive"] is True and len(report["units"]) == units
    assert shared["first_spp"] == max(1, round(shared["mean_spp"] * 0.5)) and shared["rule_units"] >= 1
    assert [u["spp"] for u in report["units"]] == shared["unit_spp"]
    assert all(u["first_spp"] == shared["first_spp"] <= u["spp"] and u["seconds"] > 0 for u in report["units"])
    areas = [u["rect"][2] * u["rect"][3] for u in report["units"]]
    spent = sum(a * s for a, s in zip(areas, shared["unit_spp"], strict=True)) / sum(areas)
    assert abs(spent - shared["mean_spp"]) <= max(1.0, 0.05 * shared["mean_spp"]), (spent, shared)


def quekaro(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run the real command line."""
    return subprocess.run([sys.executable, "-m", "quekaro", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def reference(case: Case) -> tuple:
    """Plain Mitsuba's renders of the case as its film's file holds them (cached for the process)."""
    if case.name not in _refs:
        _refs[case.name] = reference_renders(case.scene, case.variant, case.spp, case.sensor, case.defines,
                                             search_paths=tuple(SCENES / f for f in case.search), as_file=True)
    return _refs[case.name]


def mitsuba_kind(case: Case) -> tuple[str, str]:
    """The suffix and component format of the file plain Mitsuba writes for the case (cached)."""
    key = f"{case.name}:kind"
    if key not in _refs:
        _refs[key] = mitsuba_file_kind(case.scene, case.variant, case.sensor, case.defines,
                                       search_paths=tuple(SCENES / f for f in case.search))
    return _refs[key]


def compare_files(case: Case, images: np.ndarray | list[np.ndarray]) -> Verdict:
    """render_check.compare of images read from the case's job files (channels in the reference's order)
    against plain Mitsuba's files of the case, at the files' precision."""
    refs, _ = reference(case)
    return compare(images, refs, quantum=file_quantum(mitsuba_kind(case), refs.mean(axis=0)))


def problems(case: Case, out: Path) -> list[str]:
    """What differs between the job's image (beside OUT's report, with the suffix the report names) and
    plain Mitsuba's: the file's suffix and component format, its channels, their values, and the spp the
    report gives its units; empty when nothing does."""
    report = json.loads(out.with_suffix(".json").read_text())
    written = out.with_suffix(Path(report["image"]["file"]).suffix)
    kind = file_kind(written)
    if kind != mitsuba_kind(case):
        return [f"file {kind} != Mitsuba's {mitsuba_kind(case)}"]
    image, names = read_image_channels(written)
    ref_names = reference(case)[1]
    if sorted(names) != sorted(ref_names):
        return [f"channels {list(names)} != Mitsuba's {list(ref_names)}"]
    found = []
    verdict = compare_files(case, by_name(image, names, ref_names))
    if not verdict.passed:
        found.append(str(verdict))
    if report["effects"]["variant"] != case.variant:
        found.append(f"variant {report['effects']['variant']} != {case.variant}")
    units = 1 if case.whole else case.units
    if len(report["units"]) != units:
        found.append(f"{len(report['units'])} units, expected {units}")
    said = sorted({u["spp"] for u in report["units"]})
    if said != [case.unit_spp]:
        found.append(f"the report's unit spp {said}, rendered {case.unit_spp}")
    return found


def wait_done(client: FarmClient, job_id: str, timeout: float = 600.0) -> dict:
    """The job's status once it is no longer running."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.status(job_id)
        if job["status"] != "running":
            return job
        time.sleep(0.5)
    raise AssertionError(f"job {job_id} still running: {client.status(job_id)}")
