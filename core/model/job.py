"""The job contract: what crosses the wire and the disk about a job, named once for the whole farm.

`SceneSpec` (a scene file, its -D parameters and search paths), `RenderOptions` (what the user asked for),
`JobSpec` (what a user submits beside a scene bundle: parameters and options), `Effects` (what the render
simulates, and why) and `JobPlan` (a planned job: size, effects, spp, depth, its work units). Each has
`to_dict` / `from_dict`, used by the CLI, the job API, the job store and the in-process pipeline alike.
The choices they validate against are each named once: the levels in `core.model.levels`, the defuzzifiers in
`fuzzy.engine`, Mitsuba's integrators in `core.model.integrators`, the variant pattern here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core.errors import QuekaroError, SceneError
from core.model.frames import FRAME_MAX, SEQUENCE_ID, FrameRange
from core.model.geometry import DEFAULT_FILTER_RADIUS, filter_reach
from core.model.integrators import CATALOGUE
from core.model.levels import LEVELS, OFF, RULE_LEVELS
from core.model.units import SPP_MAX, WorkUnit
from fuzzy.engine import DEFUZZIFIERS

VARIANT_PATTERN = re.compile(r"(scalar|llvm|cuda)(_ad)?_(rgb|spectral|mono)[a-z_]*")  # a Mitsuba variant name


@dataclass(frozen=True)
class SceneSpec:
    """A scene to render: its XML file, the `-D name=value` parameters it is loaded with, extra folders to
    look for its files in (Mitsuba's `-a`, searched after everything else), and a reconstruction filter
    that replaces its films' own (`rfilter`: a denoised job's box; None keeps the scene's)."""

    path: Path
    defines: dict[str, str] = field(default_factory=dict)
    search_paths: tuple[Path, ...] = ()
    rfilter: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "defines", {str(k): str(v) for k, v in dict(self.defines).items()})
        object.__setattr__(self, "search_paths", tuple(Path(p).absolute() for p in self.search_paths))

    def __hash__(self) -> int:
        return hash(self.key())

    def key(self) -> tuple[Any, ...]:
        """A hashable identity: the resolved path, the sorted parameters, the search paths, the filter."""
        return (str(self.path.resolve()), tuple(sorted(self.defines.items())), tuple(map(str, self.search_paths)),
                self.rfilter)

    def with_defines(self, **extra: Any) -> SceneSpec:
        """The same scene with some parameters added or replaced."""
        return SceneSpec(self.path, {**self.defines, **{k: str(v) for k, v in extra.items()}}, self.search_paths,
                         self.rfilter)

    def to_dict(self) -> dict[str, Any]:
        replaced = {"rfilter": self.rfilter} if self.rfilter else {}  # a spec without one reads as before
        return {"path": str(self.path), "defines": dict(self.defines),
                "search_paths": [str(p) for p in self.search_paths], **replaced}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SceneSpec:
        if not isinstance(data, dict) or "path" not in data:
            raise SceneError(f"scene spec must be an object with a 'path', got {data!r}")
        defines = data.get("defines") or {}
        if not isinstance(defines, dict):
            raise SceneError(f"scene spec field 'defines' must be an object, got {defines!r}")
        rfilter = data.get("rfilter")
        if rfilter is not None and rfilter not in RFILTERS:
            raise SceneError(f"scene spec field 'rfilter': {str(rfilter)[:40]!r} is not one of {', '.join(RFILTERS)}")
        return cls(Path(data["path"]), defines, tuple(data.get("search_paths") or ()), rfilter)


RFILTERS = ("box", "tent", "gaussian", "mitchell", "catmullrom", "lanczos")  # Mitsuba's reconstruction filters


# Integer options and their ranges (the message schema's limits, core.model.messages.JobInfo).
_INT_RANGES = {"spp": (1, SPP_MAX), "depth": (1, 1024), "threads": (1, 4096), "units": (1, 4096),
               "sensor": (0, 1024)}


@dataclass(frozen=True)
class RenderOptions:
    """What the user asked for: optimisation level, predefined spp/depth, rules and overrides."""

    level: str = "off"
    spp: int | None = None
    depth: int | None = None
    threads: int | None = None
    rules: Path | None = None
    defuzzifier: str | None = None  # None: centroid in one process, each agent's own on a farm
    variant: str | None = None
    integrator: str | None = None
    units: int | None = None  # target number of work units; None: chosen from the image size
    sensor: int = 0  # which of the scene's sensors renders (Mitsuba's -s)
    # Adaptive (planning.budgets): the rules set the level's samples, measured noise places them.
    adaptive: bool = False
    # Denoised (core.image.denoise): a box filter and the denoiser's AOVs; the raw image kept beside.
    denoise: bool = False
    # In passes (planning.progressive): until each unit's relative error is under `noise`, or for `time`
    # seconds of rendering (`spp` is then the cap), or `progressive`: each unit's own samples, in passes.
    noise: float | None = None
    time: float | None = None
    progressive: bool = False

    def __post_init__(self) -> None:
        if self.level not in LEVELS:
            raise QuekaroError(f"--opt {self.level!r}: expected one of {', '.join(LEVELS)}")
        for name in ("adaptive", "denoise", "progressive"):
            if type(getattr(self, name)) is not bool:
                raise QuekaroError(f"option {name}: {getattr(self, name)!r} is not true or false")
        if self.adaptive and self.level == OFF:
            raise QuekaroError("--adaptive: level off renders the user's spp everywhere; adaptive sampling "
                               f"places a rule level's samples (--opt {'/'.join(RULE_LEVELS)})")
        for name, (lo, hi) in _INT_RANGES.items():
            value = getattr(self, name)
            if value is None:
                continue
            if type(value) is not int:  # bool, float (1e400 is inf), str: refused, not coerced
                raise QuekaroError(f"option {name} (--{name} {value!r}): not an integer")
            if not lo <= value <= hi and not (name == "depth" and value == -1):
                raise QuekaroError(f"option {name} (--{name} {value}): outside {lo}..{hi}"
                                   + (" (or -1 for unbounded)" if name == "depth" else ""))
        self._check_goal()
        if self.defuzzifier is not None and self.defuzzifier not in DEFUZZIFIERS:
            raise QuekaroError(f"option defuzzifier: {self.defuzzifier!r} is not one of {', '.join(DEFUZZIFIERS)}")
        if self.integrator is not None and self.integrator not in CATALOGUE:
            raise QuekaroError(f"option integrator: {self.integrator!r} is not one of Mitsuba's integrators")
        if self.variant is not None and not (isinstance(self.variant, str) and VARIANT_PATTERN.fullmatch(self.variant)):
            raise QuekaroError(f"option variant: {str(self.variant)[:40]!r} is not a Mitsuba variant name")

    def _check_goal(self) -> None:
        for name in ("noise", "time"):
            value = getattr(self, name)
            if value is not None and (type(value) not in (int, float) or not 0 < value < math.inf):
                raise QuekaroError(f"option {name} (--{name} {value!r}): not a positive number")
        goals = [f"--{name}" for name in ("noise", "time", "progressive") if getattr(self, name) not in (None, False)]
        if len(goals) > 1:
            raise QuekaroError(f"{' and '.join(goals)}: give one goal (a relative error, seconds of rendering, or "
                               "the job's samples in passes)")
        if self.in_passes and self.adaptive:
            raise QuekaroError("--adaptive with --noise, --time or --progressive: a job in passes places its samples "
                           "by their own measured noise; leave --adaptive out")

    @property
    def in_passes(self) -> bool:
        """Whether the job renders in passes (planning.progressive): to a noise or time goal, or its samples."""
        return self.noise is not None or self.time is not None or self.progressive

    def check_used(self) -> None:
        """Refuse a new job's options that it would ignore: a rule file or defuzzifier at level off. Checked
        where a job is submitted (the CLI, the master), not on every read: a job stored before is kept."""
        ruled = [name for name, value in (("--rules", self.rules), ("--defuzzifier", self.defuzzifier))
                 if value is not None]
        if ruled and self.level == OFF:
            raise QuekaroError(f"{' and '.join(ruled)}: level off applies no rules (every unit renders the "
                               f"user's spp and depth); give a rule level (--opt {'/'.join(RULE_LEVELS)}) or "
                               f"leave {' and '.join(ruled)} out")
        if self.noise is not None and self.noise >= 1:
            raise QuekaroError(f"--noise {self.noise:g}: a relative error of {self.noise * 100:g} %, which any image "
                               "meets; give it as a fraction under 1 (0.02 for 2 %)")

    def overrides(self) -> dict[str, Any]:
        """The effect decisions the user forced (they win over the analysis)."""
        forced = {"variant": self.variant, "integrator": self.integrator, "max_depth": self.depth}
        return {k: v for k, v in forced.items() if v is not None}

    def to_dict(self) -> dict[str, Any]:
        return {"level": self.level, "spp": self.spp, "depth": self.depth, "threads": self.threads,
                "rules": str(self.rules) if self.rules else None, "defuzzifier": self.defuzzifier,
                "variant": self.variant, "integrator": self.integrator, "units": self.units,
                "sensor": self.sensor, "adaptive": self.adaptive,
                **({"denoise": True} if self.denoise else {}),  # a job without it reads (and seeds) as before
                **({name: getattr(self, name) for name in ("noise", "time") if getattr(self, name) is not None}),
                **({"progressive": True} if self.progressive else {})}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RenderOptions:
        """The options of a JSON object; unknown keys are refused, naming them (never silently dropped)."""
        if not isinstance(data, dict):
            raise QuekaroError(f"options must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise QuekaroError(f"option {unknown[0][:40]!r} is not known (known: "
                               f"{', '.join(f.name for f in dataclasses.fields(cls))})")
        rules = data.get("rules")
        if rules is not None and not isinstance(rules, str):
            raise QuekaroError(f"option rules: {rules!r} is not a path")
        return cls(level=data.get("level", "off"), spp=data.get("spp"), depth=data.get("depth"),
                   threads=data.get("threads"), rules=Path(rules) if rules else None,
                   defuzzifier=data.get("defuzzifier"), variant=data.get("variant"),
                   integrator=data.get("integrator"), units=data.get("units"), sensor=data.get("sensor", 0),
                   adaptive=data.get("adaptive", False), denoise=data.get("denoise", False),
                   noise=data.get("noise"), time=data.get("time"), progressive=data.get("progressive", False))


@dataclass
class Effects:
    """What the render simulates, and why.

    `integrator` names what renders (the scene's own tree, e.g. `moment(path)`, or the user's override);
    `override` is the user's integrator type (None: the scene's own); `max_depth` the path depth the units
    start from (-1: unbounded, or the integrator takes none); `splittable` whether units may be tiles.
    """

    variant: str
    integrator: str
    max_depth: int
    reasons: list[str] = field(default_factory=list)
    override: str | None = None
    splittable: bool = True

    def to_dict(self) -> dict[str, Any]:
        return {"variant": self.variant, "integrator": self.integrator, "max_depth": self.max_depth,
                "reasons": list(self.reasons), "override": self.override, "splittable": self.splittable}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Effects:
        return cls(str(data["variant"]), str(data["integrator"]), int(data["max_depth"]),
                   [str(r) for r in data.get("reasons", [])], data.get("override"),
                   bool(data.get("splittable", True)))


JOB_HEADER_MAX = 8000  # bytes of a submitted job's -D parameters and options (aiohttp reads headers to 8190)


@dataclass(frozen=True)
class JobSpec:
    """What a user submits beside a scene bundle: the scene's -D parameters, the options, a label (`name`), and
    for a frame sequence either the range the master expands (`frames`) or, on each of its jobs, the sequence
    it belongs to and its frame number (`sequence`, `frame`)."""

    defines: dict[str, str] = field(default_factory=dict)
    options: RenderOptions = field(default_factory=RenderOptions)
    name: str | None = None
    frames: FrameRange | None = None
    sequence: str | None = None
    frame: int | None = None

    def __post_init__(self) -> None:
        if self.name is not None and (not isinstance(self.name, str) or not _NAME.fullmatch(self.name)):
            raise QuekaroError(f"--name {str(self.name)[:40]!r}: 1 to {NAME_MAX} printable characters")
        if self.sequence is not None and (not isinstance(self.sequence, str)
                                          or not SEQUENCE_ID.fullmatch(self.sequence)):
            raise QuekaroError(f"job field sequence {str(self.sequence)[:40]!r}: expected seq- and 8-32 hex digits")
        if (self.sequence is None) != (self.frame is None):
            raise QuekaroError("job fields sequence and frame: a frame of a sequence gives both")
        if self.frame is not None and (type(self.frame) is not int or not 0 <= self.frame <= FRAME_MAX):
            raise QuekaroError(f"job field frame {self.frame!r}: not a whole number in 0..{FRAME_MAX}")
        if self.frames is not None and self.sequence is not None:
            raise QuekaroError("job fields frames and sequence: a range is expanded into frames, not one of them")
        if self.frames is not None and self.frames.define in self.defines:
            raise QuekaroError(f"-D {self.frames.define}: given both as a frame range and as a value")

    def to_dict(self) -> dict[str, Any]:
        extra = {"name": self.name, "frames": self.frames.to_dict() if self.frames else None,
                 "sequence": self.sequence, "frame": self.frame}
        return {"defines": dict(self.defines), "options": self.options.to_dict(),
                **{k: v for k, v in extra.items() if v is not None}}

    def header(self) -> str:
        """The job as its submission's header carries it (JSON); a QuekaroError naming -D where it is longer
        than an HTTP header may be."""
        text = json.dumps(self.to_dict(), separators=(",", ":"))
        size = len(text.encode())
        if size > JOB_HEADER_MAX:
            longest = max(self.defines, key=lambda k: len(k) + len(self.defines[k]), default="")
            raise QuekaroError(f"-D: the job's parameters and options take {size} bytes, over the {JOB_HEADER_MAX} "
                               f"a job carries (the longest: -D {longest[:40]}=..., "
                               f"{len(self.defines.get(longest, ''))} characters); put long values in the scene "
                               "file or a file it includes")
        return text

    def frame_job(self, sequence: str, frame: int) -> JobSpec:
        """One frame of this range's sequence: its parameter set to the frame's number."""
        assert self.frames is not None
        return JobSpec({**self.defines, self.frames.define: str(frame)}, self.options, self.name, None, sequence,
                       frame)

    @classmethod
    def from_dict(cls, data: Any) -> JobSpec:
        """Strict: unknown keys, and parameters that are not name -> text, are refused naming them."""
        if not isinstance(data, dict):
            raise QuekaroError(f"a job must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - set(_SPEC_FIELDS))
        if unknown:
            raise QuekaroError(f"job field {unknown[0][:40]!r} is not known (known: {', '.join(_SPEC_FIELDS)})")
        defines = data.get("defines", {})
        if not isinstance(defines, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                    for k, v in defines.items()):
            raise QuekaroError("job field defines: expected an object of name -> text (-D name=value)")
        frames = data.get("frames")
        return cls(dict(defines), RenderOptions.from_dict(data.get("options", {})), data.get("name"),
                   None if frames is None else FrameRange.from_dict(frames), data.get("sequence"),
                   data.get("frame"))


_SPEC_FIELDS = ("defines", "options", "name", "frames", "sequence", "frame")
NAME_MAX = 80
_NAME = re.compile(rf"[^\x00-\x1f\x7f]{{1,{NAME_MAX}}}")


RGB = ("R", "G", "B")
# Mitsuba's film pixel formats -> the colour channels they write (alpha, where the format has it, follows).
FILM_COLOURS = {"rgb": RGB, "rgba": RGB, "xyz": ("X", "Y", "Z"), "xyza": ("X", "Y", "Z"),
                "luminance": ("Y",), "luminance_alpha": ("Y",)}

# hdrfilm's file formats (the names Mitsuba accepts, any case) -> the suffix Mitsuba gives the file, and its
# component formats. PFM and RGBE store float32 only; Mitsuba overrides any other component format.
FILE_SUFFIXES = {"openexr": ".exr", "exr": ".exr", "pfm": ".pfm", "rgbe": ".rgbe"}
COMPONENT_FORMATS = ("float16", "float32", "uint32")
IMAGE_SUFFIXES = tuple(dict.fromkeys(FILE_SUFFIXES.values()))  # .exr, .pfm, .rgbe
RAW_SUFFIX = ".raw.exr"  # a denoised job's raw image, with the denoiser's AOVs, beside its image


@dataclass(frozen=True)
class ImageFile:
    """The file a job's image is written to, as the scene's film asks (hdrfilm's `file_format` and
    `component_format`, Mitsuba's defaults OpenEXR and float16)."""

    format: str = "openexr"
    component: str = "float16"

    def __post_init__(self) -> None:
        fmt = "openexr" if self.format == "exr" else self.format
        if fmt not in FILE_SUFFIXES:
            raise QuekaroError(f"image file format {self.format!r}: expected one of openexr, pfm, rgbe")
        if self.component not in COMPONENT_FORMATS:
            raise QuekaroError(f"image component format {self.component!r}: expected one of "
                               f"{', '.join(COMPONENT_FORMATS)}")
        object.__setattr__(self, "format", fmt)
        if fmt != "openexr":
            object.__setattr__(self, "component", "float32")

    @property
    def suffix(self) -> str:
        return FILE_SUFFIXES[self.format]

    def to_dict(self) -> dict[str, str]:
        return {"format": self.format, "component": self.component}

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> ImageFile:
        """`to_dict`'s output; a plan stored before the film's file was recorded wrote float32 OpenEXR."""
        if data is None:
            return cls("openexr", "float32")
        return cls(str(data.get("format", "openexr")), str(data.get("component", "float16")))


@dataclass
class JobPlan:
    """A planned job: image size, effects, the user's spp/depth, and the units to render. A farm job also
    records its bundle's and rule file's sha256 (what agents check what they download against)."""

    spec: SceneSpec
    options: RenderOptions
    width: int
    height: int
    effects: Effects
    spp: int
    depth: int
    units: list[WorkUnit]
    prepass_seconds: float = 0.0
    prepass_info: dict[str, Any] = field(default_factory=dict)
    bundle_sha256: str | None = None
    rules_sha256: str | None = None
    # The film's reconstruction filter radius (what composition must cut from each band); Mitsuba's default
    # for plans stored before it was recorded, all of which used that filter's band.
    filter_radius: float = DEFAULT_FILTER_RADIUS
    # Adaptive jobs: every unit's first pass in samples per pixel (each unit's mean is its WorkUnit.spp),
    # and how the level's samples were shared among the units (planning.budgets.Shares.to_dict).
    first_spp: int | None = None
    shares: dict[str, Any] = field(default_factory=dict)
    # The film's colour channels (its pixel format: R, G, B; X, Y, Z; or Y): tiles carry colour as R, G, B
    # (core.image.film), and the job's image is written in the film's own.
    colour: tuple[str, ...] = RGB
    # The file the job's image is written to, as the film asks.
    image_file: ImageFile = ImageFile()
    # The channels every tile carries (core.image.film.film_channels: R, G, B, the film's alpha, the AOVs
    # the integrator adds), which a master holds each uploaded tile to; None in plans stored before.
    channels: tuple[str, ...] | None = None
    # A progressive job at level off whose scene render_counts renders as Mitsuba does: each pass draws its
    # samples on its unit alone, its band holding their spill, and the units' tiles add up (no sample
    # drawn twice; core.render.per_pixel.render_core). Otherwise a band is rendered again by each unit.
    spill: bool = False

    @property
    def reach(self) -> int:
        """Band pixels that composition cuts (core.model.geometry.filter_reach): no unit's band may be less."""
        return filter_reach(self.filter_radius)

    def features(self) -> dict[str, list[float]]:
        """The fuzzy inputs of every unit, in unit order."""
        return {"C": [u.C for u in self.units], "S": [float(u.S) for u in self.units],
                "Nd": [u.Nd for u in self.units]}

    def ranges(self) -> dict[str, tuple[float, float]]:
        """The observed range of each dynamic input over the whole scene (the paper's dynamic sets)."""
        return {name: (min(values), max(values)) for name, values in self.features().items()}

    def to_dict(self) -> dict[str, Any]:
        """Everything but the scene's location and the units (the job store keeps those in their own
        columns and rows), the units' neighbours included, and a progressive job's pinned depth and samples
        per unit (its store rows hold its passes')."""
        return {"options": self.options.to_dict(), "width": self.width, "height": self.height,
                "effects": self.effects.to_dict(), "spp": self.spp, "depth": self.depth,
                "ranges": {k: list(v) for k, v in self.ranges().items()},
                "prepass_seconds": self.prepass_seconds, "prepass_info": dict(self.prepass_info),
                "neighbours": {str(u.index): list(u.neighbours) for u in self.units},
                "pinned": {str(u.index): [u.depth, u.spp] for u in self.units if u.depth is not None},
                "bundle_sha256": self.bundle_sha256, "rules_sha256": self.rules_sha256,
                "filter_radius": self.filter_radius, "first_spp": self.first_spp, "shares": dict(self.shares),
                "colour": list(self.colour), "image_file": self.image_file.to_dict(),
                "channels": None if self.channels is None else list(self.channels), "spill": self.spill,
                **({"rfilter": self.spec.rfilter} if self.spec.rfilter else {})}  # the store keeps the path apart

    @classmethod
    def from_dict(cls, data: dict[str, Any], spec: SceneSpec, units: list[WorkUnit]) -> JobPlan:
        """The plan `to_dict` wrote, for the scene at `spec` with these units (their neighbours, and pinned
        depth and samples, restored)."""
        try:
            near = {int(k): tuple(v) for k, v in data.get("neighbours", {}).items()}
            units = [dataclasses.replace(u, neighbours=near.get(u.index, u.neighbours)) for u in units]
            pinned = {int(k): (int(depth), int(spp)) for k, (depth, spp) in data.get("pinned", {}).items()}
            units = [dataclasses.replace(u, depth=pinned[u.index][0], spp=pinned[u.index][1])
                     if u.index in pinned else u for u in units]
            spec = SceneSpec.from_dict({**spec.to_dict(), "rfilter": data.get("rfilter")})
            return cls(spec, RenderOptions.from_dict(data["options"]), int(data["width"]), int(data["height"]),
                       Effects.from_dict(data["effects"]), int(data["spp"]), int(data["depth"]), units,
                       float(data.get("prepass_seconds", 0.0)), dict(data.get("prepass_info", {})),
                       data.get("bundle_sha256"), data.get("rules_sha256"),
                       float(data.get("filter_radius", DEFAULT_FILTER_RADIUS)),
                       None if data.get("first_spp") is None else int(data["first_spp"]),
                       dict(data.get("shares") or {}), tuple(str(c) for c in data.get("colour", RGB)),
                       ImageFile.from_dict(data.get("image_file")),
                       None if data.get("channels") is None else tuple(str(c) for c in data["channels"]),
                       bool(data.get("spill", False)))
        except (KeyError, TypeError, ValueError) as exc:
            raise QuekaroError(f"stored job plan is malformed: {type(exc).__name__}: {exc}") from exc
