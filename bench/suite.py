"""The accuracy benchmark's scene suite: six scenes of different character, none used to tune the rules
but for the floors of level S's and VS's simple units, chosen on all six (the rule file's header says so).

Two are Mitsuba's own (../shared/scenes/mitsuba-data: cbox, matpreview), four are written for the suite
(bench/scenes/: a diffuse interior lit through a small window, a glossy textured still life, a
volumetric block under a spot light, an outdoor scene under an environment map). Each entry says its
role: `tune` scenes are the ones any constant of the allocation may be chosen on, `report` scenes are
held out and only reported; a scene file from outside the suite is `user` (neither half).
`python -m bench.suite --write-sky` writes bench/scenes/sky.exr.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.errors import QuekaroError
from core.image.imageio import write_exr

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "scenes" / "mitsuba-data"


@dataclass(frozen=True)
class SuiteScene:
    name: str
    path: Path
    defines: dict[str, str] = field(default_factory=dict)
    role: str = "user"  # tune | report, or user: a file from outside the suite
    about: str = ""

    def with_size(self, res: int) -> dict[str, str]:
        """The -D parameters that give this scene a res-wide image (its own aspect kept)."""
        if "width" in self.defines:
            aspect = int(self.defines["height"]) / int(self.defines["width"])
            return {**self.defines, "width": str(res), "height": str(max(1, round(res * aspect)))}
        return {**self.defines, "res": str(res)}


SUITE = (
    SuiteScene("cbox", SHARED / "cbox" / "cbox.xml", {"res": "512"}, "tune",
               "Mitsuba's Cornell box (meshes): diffuse, one area light"),
    SuiteScene("interior", HERE / "scenes" / "interior-window.xml", {"res": "512"}, "tune",
               "large diffuse room lit through a small bright window"),
    SuiteScene("still-life", HERE / "scenes" / "still-life.xml", {"res": "512"}, "tune",
               "glossy and glass spheres on a checkered cloth, two small lamps"),
    SuiteScene("matpreview", SHARED / "matpreview" / "matpreview.xml", {"width": "683", "height": "512"},
               "report", "Mitsuba's material preview: envmap, serialized meshes"),
    SuiteScene("volume", HERE / "scenes" / "volume.xml", {"res": "512"}, "report",
               "scattering block (homogeneous medium, volpath) under a spot light"),
    SuiteScene("outdoor", HERE / "scenes" / "outdoor.xml", {"res": "512"}, "report",
               "buildings and a glossy sphere under a sky environment map with a sun"),
)
BY_NAME = {s.name: s for s in SUITE}


def scene_from_argument(text: str) -> SuiteScene:
    """A suite name, or the path of any Mitsuba scene file (role `user`, no -D of its own)."""
    if text in BY_NAME:
        scene = BY_NAME[text]
        if not scene.path.exists():
            raise QuekaroError(f"suite scene {text}: {scene.path} does not exist")
        return scene
    path = Path(text)
    if not path.is_file():
        raise QuekaroError(f"scene {text!r}: neither a suite scene ({', '.join(BY_NAME)}) nor a file")
    return SuiteScene(path.stem, path.resolve())


def sky(width: int = 512, height: int = 256) -> np.ndarray:
    """A latitude-longitude sky: blue above, brightening to the horizon, a dark ground, and a sun of
    half a degree's radius at 35 degrees elevation carrying most of the light."""
    v = (np.arange(height) + 0.5) / height  # 0 at the zenith, 1 at the nadir
    u = (np.arange(width) + 0.5) / width
    theta, phi = np.meshgrid(v * np.pi, u * 2 * np.pi, indexing="ij")
    elevation = np.pi / 2 - theta
    up = np.clip(np.sin(elevation), 0, 1)[..., None]
    image = np.where(elevation[..., None] >= 0,
                     np.array([0.9, 1.0, 1.1]) * (1 - up) + np.array([0.25, 0.45, 0.9]) * up,
                     np.array([0.08, 0.07, 0.06]))
    sun = np.array([np.cos(np.radians(35)) * np.cos(1.0), np.sin(np.radians(35)), np.cos(np.radians(35)) * np.sin(1.0)])
    dirs = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], axis=-1)
    disk = dirs @ sun > np.cos(np.radians(1.5))  # a few texels wide at this resolution
    image[disk] = np.array([30000.0, 28000.0, 24000.0]) / max(int(disk.sum()), 1) * 3
    return image.astype(np.float32)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.suite", description=__doc__)
    parser.add_argument("--write-sky", action="store_true", help="write bench/scenes/sky.exr")
    args = parser.parse_args(argv)
    if args.write_sky:
        write_exr(HERE / "scenes" / "sky.exr", sky())
        print(HERE / "scenes" / "sky.exr")
    else:
        for s in SUITE:
            print(f"{s.name:12s} {s.role:7s} {s.path}  {s.about}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
