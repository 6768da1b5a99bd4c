"""Rendering one work unit: the job description (`RenderRequest`), the render itself (`render_job_here`),
and the persistent child process (`RenderProcess`) that runs it, so that an LLVM abort or a hang costs
one unit, never the job.

A unit renders its window (its rectangle grown by its band) with the scene's own integrator, or that
integrator at the rules' `max_depth` (core.model.integrators), at the unit's spp and seed, through the
job's sensor. Its tile keeps every channel the film writes (the colour named R, G, B: core.image.film).
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, NoReturn

import numpy as np

from core import logs, mitsuba_env
from core.errors import QuekaroError, RenderError, SceneError
from core.image.film import film_channels, film_weight, sanitize
from core.image.passes import WEIGHT
from core.image.tiles import Tile
from core.model import integrators
from core.model.geometry import Rect
from core.model.job import SceneSpec
from core.render import spawn as child
from core.render.adaptive import render_adaptive
from core.render.per_pixel import render_core
from core.scene import scene
from core.scene.scene import sensor_of

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.mitsuba_env), and processes that never render must not pay for it.

STARTUP_TIMEOUT_S = 120.0
# What a unit's two-pass render (RenderRequest.first) adds to its tile's header.
ADAPTIVE_META = ("first_spp", "adapted", "predicted_relmse_ratio", "pass_seconds")
_PP_KEYS = ("principal_point_offset_x", "principal_point_offset_y")


@dataclass(frozen=True)
class RenderRequest:
    """Everything a process needs to render one unit; to_dict/from_dict give plain values for the render
    process's pipe.

    `integrator=None` renders with the scene's own integrator; a plugin name is the user's override.
    `max_depth=None` keeps the depth the scene wrote; a number replaces it on every depth-bearing
    integrator of the tree. `sensor` indexes the scene's sensors (Mitsuba's `-s`). `first` (adaptive
    jobs) renders the window in two passes, `first` samples per pixel and then the rest of a mean of `spp`
    where the first pass's noise is (core.render.adaptive.render_adaptive, statistically Mitsuba's image).
    `aovs` renders those AOVs alone (Mitsuba's aov integrator, no colour): a denoised job's pass for its
    denoiser (core.image.denoise.AOVS). `spill` (a pass only) draws the samples on the unit alone, its band
    holding their filter's spill (core.render.per_pixel.render_core): overlapping tiles then add up.
    """

    scene: SceneSpec
    variant: str
    integrator: str | None
    max_depth: int | None
    spp: int
    seed: int
    width: int
    height: int
    unit: Rect
    band: int = 0
    threads: int | None = None
    job_id: str = ""
    unit_index: int = -1
    extra: dict[str, Any] = field(default_factory=dict)
    sensor: int = 0
    first: int | None = None
    aovs: str | None = None
    pass_index: int | None = None
    spill: bool = False

    def __post_init__(self) -> None:
        _check_job(self)

    @property
    def window(self) -> Rect:
        """The rectangle actually rendered (core.model.geometry.Rect.window)."""
        return self.unit.window(self.band, self.width, self.height)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scene": self.scene.to_dict(), "variant": self.variant, "integrator": self.integrator,
            "max_depth": self.max_depth, "spp": self.spp, "seed": self.seed, "width": self.width,
            "height": self.height, "unit": self.unit.as_list(), "band": self.band,
            "threads": self.threads, "job_id": self.job_id, "unit_index": self.unit_index,
            "extra": dict(self.extra), "sensor": self.sensor, "first": self.first, "aovs": self.aovs,
            "pass_index": self.pass_index, "spill": self.spill,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RenderRequest:
        try:
            return cls(
                scene=SceneSpec.from_dict(data["scene"]), variant=str(data["variant"]),
                integrator=data.get("integrator"), max_depth=_opt_int(data.get("max_depth")),
                spp=int(data["spp"]), seed=int(data["seed"]), width=int(data["width"]),
                height=int(data["height"]), unit=Rect.from_list(data["unit"]),
                band=int(data.get("band", 0)), threads=_opt_int(data.get("threads")),
                job_id=str(data.get("job_id", "")), unit_index=int(data.get("unit_index", -1)),
                extra=dict(data.get("extra") or {}), sensor=int(data.get("sensor", 0)),
                first=_opt_int(data.get("first")), aovs=data.get("aovs"),
                pass_index=_opt_int(data.get("pass_index")), spill=bool(data.get("spill", False)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise RenderError(f"malformed unit job ({type(exc).__name__}: {exc})") from exc


def _opt_int(value: Any) -> int | None:
    return None if value is None else int(value)


def _check_job(job: RenderRequest) -> None:
    problems = []
    if job.spp < 1:
        problems.append(f"spp={job.spp} (must be >= 1; Mitsuba reads 0 as 'sampler default')")
    if job.first is not None and not 1 <= job.first <= job.spp:
        problems.append(f"first={job.first} (the first pass's spp: must be in 1..spp={job.spp})")
    if job.pass_index is not None and (job.pass_index < 0 or job.first is not None or job.aovs is not None):
        problems.append(f"pass_index={job.pass_index} (a pass is >= 0, and neither two-pass nor an AOV pass)")
    if job.spill and job.pass_index is None:
        problems.append("spill without pass_index (only a pass's tile is merged by its weights)")
    if job.max_depth is not None and job.max_depth < -1:
        problems.append(f"max_depth={job.max_depth} (must be >= -1)")
    if job.sensor < 0:
        problems.append(f"sensor={job.sensor} (must be >= 0)")
    if not 0 <= job.seed < 2**32:
        problems.append(f"seed={job.seed} (must fit 32 bits)")
    if job.width < 1 or job.height < 1:
        problems.append(f"image {job.width}x{job.height} (must be at least 1x1)")
    if job.band < 0:
        problems.append(f"band={job.band} (must be >= 0)")
    if job.threads is not None and job.threads < 1:
        problems.append(f"threads={job.threads} (must be >= 1)")
    image = Rect(0, 0, job.width, job.height)
    if job.unit.area == 0 or image.intersect(job.unit) != job.unit:
        problems.append(f"unit {job.unit.as_list()} is empty or outside the {job.width}x{job.height} image")
    if problems:
        raise RenderError("bad unit job: " + "; ".join(problems))


# ---- rendering, in whichever process calls it ------------------------------------------------------


class _SceneCache:
    """The last loaded scene and the integrators built for it, so consecutive units reuse them."""

    def __init__(self) -> None:
        self.key: tuple[Any, ...] | None = None
        self.scene: Any = None
        self.integrator_xml: Any = None
        self.own_depth: int | None = None
        self.base_pp: dict[int, tuple[float, float] | None] = {}
        self.images: dict[int, Rect] = {}
        self.integrators: dict[tuple[str | None, int | None], Any] = {}

    def scene_for(self, spec: SceneSpec, variant: str, threads: int | None) -> tuple[Any, float]:
        """(scene, seconds spent loading it now: 0 when cached)."""
        used = mitsuba_env.init(variant, threads)
        key = (spec.key(), used)
        if key == self.key:
            return self.scene, 0.0
        start = time.perf_counter()
        self.scene, self.key = None, None  # free the old scene before loading the next
        self._hold(spec, key, scene.load(spec))
        return self.scene, time.perf_counter() - start

    def adopt(self, spec: SceneSpec, variant: str, loaded: Any) -> None:
        """Hold `loaded`, a scene loaded from `spec` in `variant` in this process and left as loaded, as
        if `scene_for` had loaded it."""
        self._hold(spec, (spec.key(), mitsuba_env.init(variant)), loaded)

    def _hold(self, spec: SceneSpec, key: tuple[Any, ...], loaded: Any) -> None:
        self.scene = loaded
        self.integrator_xml = integrators.scene_element(scene.expand(spec).root)
        self.own_depth = integrators.depth_of(self.integrator_xml)
        self.key, self.integrators, self.base_pp, self.images = key, {}, {}, {}

    def principal_point(self, sensor: int) -> tuple[float, float] | None:
        if sensor not in self.base_pp:
            self.base_pp[sensor] = principal_point(self.scene, sensor)
        return self.base_pp[sensor]

    def image(self, sensor: int) -> Rect:
        """The sensor's image as loaded: its film's crop window, in film pixels."""
        if sensor not in self.images:
            film = sensor_of(self.scene, sensor).film()
            (x, y), (w, h) = ((int(v) for v in pair) for pair in (film.crop_offset(), film.crop_size()))
            self.images[sensor] = Rect(x, y, w, h)
        return self.images[sensor]

    def integrator(self, override: str | None, depth: int | None, aovs: str | None = None) -> Any:
        """None (the scene's own) unless the user overrode the type or a depth must change; `aovs` alone."""
        key = (override, depth, aovs)
        if key not in self.integrators:
            self.integrators[key] = integrator_for(override, depth, self.integrator_xml, self.own_depth) \
                if aovs is None else aovs_alone(aovs)
        return self.integrators[key]


def integrator_for(override: str | None, depth: int | None, scene_xml: Any, own_depth: int | None) -> Any:
    """What `mi.render` is given to render with: None (the scene's own integrator, as loaded) unless the
    user overrode its type or `depth` differs from the scene's `own_depth`, else `build_integrator`'s."""
    if override is None and (depth is None or own_depth in (None, depth)):
        return None
    return build_integrator(override, depth, scene_xml)


def aovs_alone(aovs: str) -> Any:
    """Mitsuba's aov integrator rendering `aovs` and no colour."""
    import mitsuba as mi

    try:
        return mi.load_dict({"type": "aov", "aovs": aovs})
    except RuntimeError as exc:
        raise RenderError(f"cannot render the AOVs {aovs}: {exc}") from exc


def build_integrator(override: str | None, depth: int | None, scene_xml: Any) -> Any:
    """The integrator a unit renders with: the user's override type (with `depth` where it takes one),
    else the scene's own integrator element `scene_xml` at `depth`."""
    import mitsuba as mi

    try:
        if override is None:
            return mi.load_string(integrators.with_depth(scene_xml, int(depth)))
        props: dict[str, Any] = {"type": override}
        if depth is not None and integrators.kind(override).depth:
            props["max_depth"] = depth
        return mi.load_dict(props)
    except RuntimeError as exc:
        what = override or integrators.describe(scene_xml)
        at = "" if depth is None else f" at depth {depth}"
        raise RenderError(f"cannot build integrator {what}{at}: {exc}") from exc


_local_cache = _SceneCache()  # this process's: the render process's units, or a caller rendering in process


def local_cache() -> _SceneCache:
    """This process's scene cache: what `adopt_scene` adopted and the units rendered here find."""
    return _local_cache


def adopt_scene(spec: SceneSpec, variant: str, loaded: Any) -> None:
    """Let this process's next units render `loaded` instead of loading `spec` again: a scene loaded
    from `spec` in `variant` and left as loaded (a render that changed its film's size put it back).
    The render process's planning hands over the scene its analysis loaded, which a large scene's
    second load would otherwise cost."""
    _local_cache.adopt(spec, variant, loaded)


def principal_point(scene: Any, sensor: int = 0) -> tuple[float, float] | None:
    """The sensor's own principal-point offset, or None when it has none (not perspective)."""
    import mitsuba as mi

    params = mi.traverse(sensor_of(scene, sensor))
    if not all(k in params for k in _PP_KEYS):
        return None
    # An llvm variant holds each as a one-element array, a scalar variant as a float.
    return tuple(float(np.ravel(params[key])[0]) for key in _PP_KEYS[:2])


def set_window(scene: Any, window: Rect, base: tuple[float, float] | None, sensor: int = 0) -> str:
    """Make the scene's sensor render `window` of its film (film pixels); return the method ("shift" or
    "crop").

    `base` is the sensor's principal point as loaded (from `principal_point`), None for a crop. A shift
    (perspective and thin-lens sensors) crops at (0, 0) with the window's size and moves the principal
    point by (x / W, y / H): the same rays (tested to float precision), but Dr.Jit compiles one kernel per
    window size, not per position (a crop offset is baked into the kernel and costs ~0.45 s to compile;
    docs/design.md section 3). Other sensors use a crop.
    """
    import mitsuba as mi

    params = mi.traverse(sensor_of(scene, sensor))
    width, height = (int(v) for v in params["film.size"])
    if base is not None:
        params[_PP_KEYS[0]] = base[0] + window.x / width
        params[_PP_KEYS[1]] = base[1] + window.y / height
        params["film.crop_offset"] = [0, 0]
        method = "shift"
    else:
        params["film.crop_offset"] = [window.x, window.y]
        method = "crop"
    params["film.crop_size"] = [window.w, window.h]
    params.update()
    return method


def render_job_here(job: RenderRequest, cache: _SceneCache | None = None) -> Tile:
    """Render the unit in this process (the child calls this; so can a test or a benchmark).

    Non-finite values (an emitter with infinite or NaN radiance) are set to 0, so they never propagate,
    and the number of pixels that had any is the tile's `meta["nonfinite"]`."""
    cache = cache or _local_cache
    window = job.window
    scene, load_s, method = aim(job, window, cache)
    sensor = sensor_of(scene, job.sensor, str(job.scene.path))
    film = sensor.film()
    integrator = cache.integrator(job.integrator, job.max_depth, job.aovs)
    start = time.perf_counter()
    raw, channels, passes = _render_window(scene, film, job, integrator)
    pixels, nonfinite = sanitize(raw)
    nonfinite = max(nonfinite, passes.pop("nonfinite", 0))
    if job.pass_index is not None:  # a pass of a progressive unit: its weights merge it (core.image.passes)
        pixels = np.concatenate([pixels, film_weight(film)[..., None]], axis=-1)
        channels = (*channels, WEIGHT)
    seconds = time.perf_counter() - start
    spp = job.spp if job.first is not None else rendered_spp(sensor, job.spp)
    meta = unit_meta(job, sensor, seconds, load_s, nonfinite, spp, method) | passes
    return Tile(pixels, window, job.unit, meta, channels)


def unit_meta(job: RenderRequest, sensor: Any, seconds: float, load_s: float, nonfinite: int, spp: int,
              method: str) -> dict[str, Any]:
    """A rendered unit's tile header: what rendered it, how, and what it cost."""
    import drjit as dr
    import mitsuba as mi

    return {
        "job_id": job.job_id, "unit_index": job.unit_index, "seconds": seconds, "load_seconds": load_s,
        "threads": dr.thread_count(),
        "nonfinite": nonfinite, "spp": spp, "depth": job.max_depth, "integrator": job.integrator,
        "variant": mi.variant(), "seed": job.seed, "band": job.band, "window_method": method,
        "pid": os.getpid(), "sensor": job.sensor, "filter_radius": float(sensor.film().rfilter().radius()),
        **({} if job.pass_index is None else {"pass": job.pass_index}), **({"spill": True} if job.spill else {}),
    }


def aim(job: RenderRequest, window: Rect, cache: _SceneCache) -> tuple[Any, float, str]:
    """(scene, seconds spent loading it, window method): the job's scene loaded (or cached) with its sensor
    aimed at `window`, in the image's pixels. A film the scene crops itself renders its crop window, so a
    window lies at the crop's offset in the film."""
    scene, load_s = cache.scene_for(job.scene, job.variant, job.threads)
    image = cache.image(job.sensor)
    if (image.w, image.h) != (job.width, job.height):
        raise RenderError(f"{job.scene.path}: the film's image (its crop window) is {image.w}x{image.h}, "
                          f"job says {job.width}x{job.height}")
    in_film = Rect(window.x + image.x, window.y + image.y, window.w, window.h)
    return scene, load_s, set_window(scene, in_film, cache.principal_point(job.sensor), job.sensor)


def rendered_spp(sensor: Any, spp: int) -> int:
    """The samples per pixel Mitsuba's render takes when asked for `spp` through this sensor's sampler:
    stratified, low-discrepancy, orthogonal and multi-jitter samplers round it to counts of their own
    (a square, a power of four, a prime's square), 11 to 16 with ldsampler; independent takes it as is."""
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    return int(sampler.sample_count())


def _render_window(scene: Any, film: Any, job: RenderRequest,
                   integrator: Any) -> tuple[np.ndarray, tuple[str, ...], dict[str, Any]]:
    """The window's pixels, channel names and what its passes did: Mitsuba's render, or with `first` the
    two-pass adaptive render (its pixels come sanitised: their non-finite count is in the dict)."""
    import mitsuba as mi

    if job.spill:
        window = job.window
        core = (job.unit.x - window.x, job.unit.y - window.y, job.unit.w, job.unit.h)
        pixels, channels = render_core(scene, core, job.spp, job.seed, job.sensor, integrator)
        return pixels, channels, {}
    if job.first is None:
        mi.render(scene, sensor=job.sensor, integrator=integrator, spp=job.spp, seed=job.seed)
        return (*film_channels(film), {})
    made = render_adaptive(scene, job.spp, job.seed, job.sensor, integrator, first=job.first)
    said = dict(zip(ADAPTIVE_META, (job.first, made.adapted, made.predicted, list(made.seconds)), strict=True))
    return made.pixels, made.channels, {"nonfinite": made.nonfinite, **said}


def render_full(spec: SceneSpec, variant: str, integrator: str | None, depth: int | None, spp: int,
                seed: int = 0, threads: int | None = None, sensor: int = 0) -> np.ndarray:
    """A plain render of the whole image in this process (the reference benchmarks compare against)."""
    width, height = scene.image_size(spec, sensor)
    job = RenderRequest(spec, variant, integrator, depth, spp, seed, width, height, Rect(0, 0, width, height),
                  threads=threads, sensor=sensor)
    return render_job_here(job).pixels


# ---- the child process ------------------------------------------------------------------------------


def mitsuba_log_level(name: str) -> Any:
    """Mitsuba's log level for a Python level's name: DEBUG and INFO as such, anything else warnings
    (Mitsuba's default)."""
    import mitsuba as mi

    return {"DEBUG": mi.LogLevel.Debug, "INFO": mi.LogLevel.Info}.get(name, mi.LogLevel.Warn)


def _child_entry(fd: int) -> NoReturn:
    """Entry point of the render process: fd is its end of the socket pair to the parent."""
    _child_main(Connection(fd))


def _child_main(conn: Any) -> NoReturn:
    """Loop of the render process: receive a job dict, answer ("ok", pixels, rect, meta) or ("error", ...);
    released (None) or left by the parent, it ends (`_exit_now`)."""
    start = time.perf_counter()
    import mitsuba  # imported once here, so each unit pays nothing for it

    conn.send(("ready", {"import_seconds": time.perf_counter() - start, "pid": os.getpid()}))
    cache = _local_cache  # what a call made here adopted (adopt_scene), the units find
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            _exit_now()  # the parent went away
        if message is None:
            _exit_now()
        if isinstance(message, tuple) and message[0] == "call":
            conn.send(_called(*message[1:]))
            continue
        if isinstance(message, tuple) and message[0] == "log":  # no answer
            mitsuba.set_log_level(mitsuba_log_level(message[1]))
            continue
        try:
            tile = render_job_here(RenderRequest.from_dict(message), cache)
            conn.send(("ok", tile.pixels, tile.rect.as_list(), tile.meta, tile.channels))
        except Exception as exc:
            kind = type(exc).__name__ if isinstance(exc, QuekaroError) else "RenderError"
            conn.send(("error", kind, f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=3)))


def _exit_now() -> NoReturn:
    """End the render process without the interpreter's teardown. It has answered everything and writes
    no file (Dr.Jit stores each kernel on disk as it compiles it), and tearing Mitsuba and Dr.Jit down took
    0.1-0.2 s that a job waited for at its end (`RenderProcess.stop`)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a parent gone away may have closed the pipe
            stream.flush()
    os._exit(0)


def _called(fn: Callable[..., Any], args: tuple[Any, ...]) -> tuple[Any, ...]:
    """`fn(*args)` in the render process, as an answer: ("result", value) or ("raised", exception, trace)."""
    try:
        return ("result", fn(*args))
    except Exception as exc:
        trace = traceback.format_exc(limit=5)
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:  # an exception that does not survive the pipe is told as a RenderError
            exc = RenderError(f"{type(exc).__name__}: {exc}")
        return ("raised", exc, trace)


def _death_reason(exitcode: int | None) -> str:
    if exitcode is None:
        return "render process stopped answering"
    if exitcode < 0:
        try:
            return f"render process killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"render process killed by signal {-exitcode}"
    return f"render process exited with status {exitcode}"


class RenderProcess:
    """A persistent child process rendering units one at a time, restarted after a crash or timeout.

    It keeps Mitsuba imported and the last scene loaded, so a unit costs little more than its render.
    """

    def __init__(self, startup_timeout: float = STARTUP_TIMEOUT_S) -> None:
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Connection | None = None
        self.startup_timeout = startup_timeout
        self.starts = 0
        self._ready = False
        self._released = False
        self.import_seconds: float | None = None
        self._abort: threading.Event | None = None  # the render in flight's (see `interrupt`)

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def alive(self) -> bool:
        """A child is running and has not been released."""
        return self._proc is not None and not self._released and self._proc.poll() is None

    def start(self) -> None:
        """Start the child (if not running) and wait until Mitsuba is imported in it."""
        if not self.alive():
            self.launch()
        if not self._ready:
            self._wait_ready()

    def launch(self) -> None:
        """Start the child without waiting for it: it imports Mitsuba while the caller does other work; the
        first `render` or `call` waits for it. A child started early (core.render.spawn) is taken."""
        if self.alive():
            return
        self._kill()  # a released child still shutting down, or a dead one: reaped
        self._proc, self._conn = child.take()
        self._ready = False
        self._released = False
        self.starts += 1

    def _wait_ready(self) -> None:
        if not self._conn.poll(self.startup_timeout):
            self._kill()
            raise RenderError(f"render process did not start within {self.startup_timeout:.0f} s")
        try:
            _, info = self._conn.recv()
        except (EOFError, OSError):
            raise RenderError(f"render process failed to start ({_death_reason(self._reap())})") from None
        self.import_seconds = float(info["import_seconds"])
        self._ready = True
        # Mitsuba's own log there: the level of this process's "mitsuba" logger, where one is set (the CLI's
        # `-v`: INFO, `-vv`: DEBUG); else warnings, as Mitsuba's default.
        self._conn.send(("log", logging.getLevelName(logging.getLogger(logs.MITSUBA_LOGGER).level)))

    def call(self, fn: Callable[..., Any], *args: Any, doing: str = "its work", timeout: float | None = None,
             abort: threading.Event | None = None) -> Any:
        """`fn(*args)` run in the child, which keeps what it imported and loaded for the units that follow
        (`quekaro render` plans there, so that its own process never imports Mitsuba); `fn` must be a
        module-level function and its arguments and result picklable. What `fn` raises is raised here
        (the child's traceback as a note); a crash is a RenderError naming `doing`, and the child restarts
        on next use; past `timeout` seconds it is killed, and `abort` ends it as in `render`."""
        answer = self._abortable(("call", fn, args), timeout, doing, abort)
        if answer[0] == "result":
            return answer[1]
        _, exc, trace = answer
        exc.add_note(f"in the render process:\n{trace}")
        raise exc

    def release(self) -> None:
        """Ask the child to exit without waiting for it (it ends at once, `_exit_now`, while the caller goes
        on); `stop` waits. A later `render` starts a new child."""
        if self._proc is not None and not self._released:
            with contextlib.suppress(OSError):
                self._conn.send(None)
            self._released = True

    def stop(self) -> None:
        """Ask the child to exit; kill it if it does not within a few seconds."""
        if self._proc is None:
            return
        self.release()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._proc.wait(5)
        self._kill()

    def kill(self) -> None:
        """End the child at once (Ctrl-C: a child rendering would read `release` only once its render ends)."""
        self._kill()

    def interrupt(self) -> None:
        """From any thread: kill the child if the render in flight was given an `abort` event that is set
        (the render then ends in a RenderError; the next call starts a new child, without the compiled
        kernels of this one). An idle child, or one rendering another unit, is left alone."""
        abort, proc = self._abort, self._proc
        if abort is not None and abort.is_set() and proc is not None and proc.poll() is None:
            proc.kill()

    def __enter__(self) -> RenderProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def render(self, job: RenderRequest, timeout: float | None = None, abort: threading.Event | None = None) -> Tile:
        """Render one unit in the child; a crash or timeout is a RenderError, and the next call restarts.
        `abort` set (and `interrupt` called) ends it, also before it has begun (as a RenderError)."""
        where = f"unit {job.unit_index} {job.unit.as_list()}"
        answer = self._abortable(job.to_dict(), timeout, where, abort)
        return self._tile_from_answer(answer, job, where)

    def _abortable(self, message: Any, timeout: float | None, where: str, abort: threading.Event | None) -> Any:
        """`_exchange`, which `interrupt` ends while `abort` is set, as it does before it begins."""
        self._abort = abort
        try:
            if abort is not None and abort.is_set():
                raise RenderError(f"{where}: interrupted before it began")
            return self._exchange(message, timeout, where, abort)
        finally:
            self._abort = None

    def _exchange(self, message: Any, timeout: float | None, where: str,
                  abort: threading.Event | None = None) -> Any:
        """Send the child one message and return its answer; RenderError (`where`: why) if it dies or
        does not answer within `timeout` (then it is killed), or `abort` was set while it started."""
        self.start()
        try:
            self._conn.send(message)
        except OSError:
            raise RenderError(f"{where}: {_death_reason(self._reap())}") from None
        if abort is not None and abort.is_set():  # set while the child started: `interrupt` found none
            self._kill()
            raise RenderError(f"{where}: interrupted")
        if not self._conn.poll(timeout):
            self._kill()
            raise RenderError(f"{where}: timed out after {timeout:.1f} s (render process killed)")
        try:
            return self._conn.recv()
        except (EOFError, OSError):
            raise RenderError(f"{where}: {_death_reason(self._reap())}") from None

    @staticmethod
    def _tile_from_answer(answer: tuple[Any, ...], job: RenderRequest, where: str) -> Tile:
        if answer[0] == "ok":
            _, pixels, rect, meta, channels = answer
            return Tile(pixels, Rect.from_list(rect), job.unit, meta, channels)
        _, kind, message, _trace = answer
        if kind == "SceneError":
            raise SceneError(message)
        raise RenderError(f"{where}: {message}")

    def _reap(self) -> int | None:
        """Wait for a dead child and forget it; its exit code."""
        proc = self._proc
        if proc is None:
            return None
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(5)
        code = proc.poll()
        self._kill()
        return code

    def _kill(self) -> None:
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._discard()

    def _discard(self) -> None:
        if self._conn is not None:
            self._conn.close()
        self._proc, self._conn = None, None


_default_worker: RenderProcess | None = None


def render_unit(job: RenderRequest, timeout: float | None = None) -> Tile:
    """Render a unit in this process's shared RenderProcess (started on first use)."""
    global _default_worker
    if _default_worker is None:
        _default_worker = RenderProcess()
    return _default_worker.render(job, timeout)
