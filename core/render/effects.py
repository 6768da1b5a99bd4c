"""Effect analysis: what a render may save without changing the image, with a reason for every decision.

The scene says what to compute: its integrator (type, parameters, nested integrators), its sensor and
its film are kept as written. The analysis may only make the render cheaper where the image stays
statistically the same, and says why:
- variant: rgb unless the XML's spectral data would render differently in rgb (spectral_data.py's test:
  paths of up to three bounces off each spectrum, and between any two, keep their colour in rgb within
  RGB_TOLERANCE; a wavelength-dependent index of refraction always needs spectral; blackbody spectra are
  spectral-only in Mitsuba). A flat reflectance passes; narrow lines and structured spectra do not.
  Polarized spectral where the scene computes polarization: a `stokes` integrator (Mitsuba refuses it
  in any other variant) or a polarizing BSDF (POLARIZING_BSDFS: unpolarized variants render them
  without the effect they exist for, e.g. crossed polarizers let light through).
- depth cap: only for path tracers without delta, glossy or transmissive BSDFs and without media (no
  specular chains): a path of depth d carries at most a^(d-1) of the light, a = the largest diffuse
  albedo, so max_depth is lowered where the whole tail beyond it is below DEPTH_TAIL of the light.
- tiles: an integrator whose samples stay in their pixel can be split into units; one that splats
  light paths anywhere on the film (ptracer) is rendered whole, as one unit (core.model.integrators).
User overrides (variant, integrator, max_depth) always win, and the reasons say so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from core.errors import SceneError
from core.model import integrators
from core.model.job import Effects, SceneSpec
from core.render import scene as scene_mod
from core.render import spectral_data

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.render.mitsuba_env), and processes that never render must not pay for it.

DEPTH_TAIL = 5e-3
RGB_VARIANT, SPECTRAL_VARIANT, POLARIZED_VARIANT = "llvm_ad_rgb", "llvm_ad_spectral", "llvm_ad_spectral_polarized"
POLARIZING_BSDFS = ("polarizer", "retarder", "pplastic", "measured_polarized")
_CAPPABLE = {"path", "volpath", "volpathmis", "prb", "prb_basic", "prbvolpath"}
_OVERRIDABLE = ("variant", "integrator", "max_depth")


def _scene_depth(elem: Any, depth: int | None) -> int:
    """The scene's own depth (-1 when its integrator takes none), refused where it renders nothing."""
    if depth is not None and (depth == 0 or depth < -1):
        # Mitsuba renders nothing at max_depth 0 (1 shows only the emitters): refuse rather than
        # deliver a black image without a word.
        raise SceneError(f"{elem.get(scene_mod.SRC_ATTR)}: integrator max_depth {depth} renders nothing; "
                         "use 1 or more, or -1 for unbounded")
    return -1 if depth is None else depth


SPECTRAL_RANGE_NM = (360.0, 830.0)  # Mitsuba's MI_CIE_MIN, MI_CIE_MAX: the wavelengths it samples


def _albedo(bsdf: Any) -> float:
    """Largest reflectance a diffuse BSDF can have; 1.0 when it cannot be read (no cap then)."""
    import mitsuba as mi

    params = mi.traverse(bsdf)
    keys = [k for k in params.keys() if k in ("reflectance.value", "reflectance.data")]  # noqa: SIM118
    if not keys or "Diffuse" not in bsdf.class_name():
        return 1.0
    spectral = "spectral" in str(mi.variant())
    return max(largest_reflectance(np.array(params[k], dtype=np.float64), spectral) for k in keys)


def largest_reflectance(values: np.ndarray, spectral: bool) -> float:
    """The largest reflectance that a texture's stored values give. In a spectral variant a colour (three
    values per texel) is stored as the coefficients (c0, c1, c2) of Mitsuba's sRGB spectral model (Jakob
    and Hanika 2019): reflectance s(x) = 1/2 + x / (2 sqrt(1 + x^2)) of x = c0 l^2 + c1 l + c2 over the
    wavelengths l it samples; s grows with x, so its largest value is at an end of the range or at the
    parabola's vertex. Read as reflectances, the coefficients of a grey 0.5 say 0."""
    if not spectral or values.size % 3 or (values.ndim == 3 and values.shape[-1] != 3):
        return float(np.max(values))
    c = values.reshape(-1, 3) if values.ndim == 3 else values.reshape(3, -1).T
    lo, hi = SPECTRAL_RANGE_NM

    def x(wavelength: np.ndarray | float) -> np.ndarray:
        return (c[:, 0] * wavelength + c[:, 1]) * wavelength + c[:, 2]

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # c0 = 0 or tiny: no vertex inside
        vertex = -c[:, 1] / (2.0 * c[:, 0])
    inside = (c[:, 0] < 0) & (vertex > lo) & (vertex < hi)
    top = np.maximum(np.maximum(x(lo), x(hi)), np.where(inside, x(np.where(inside, vertex, lo)), -np.inf))
    return float(np.max(0.5 + 0.5 * top / np.sqrt(top * top + 1.0)))


def _surface_facts(loaded: Any) -> dict[str, Any]:
    import mitsuba as mi

    facts = {"delta": False, "glossy": False, "transmission": False, "albedo": 0.0}
    for shape in loaded.shapes():
        bsdf = shape.bsdf()
        flags = int(bsdf.flags())
        facts["delta"] |= bool(flags & int(mi.BSDFFlags.Delta))
        facts["glossy"] |= bool(flags & int(mi.BSDFFlags.Glossy))
        facts["transmission"] |= bool(flags & int(mi.BSDFFlags.Transmission) and
                                      not flags & int(mi.BSDFFlags.Null))
        if not shape.is_emitter():
            facts["albedo"] = max(facts["albedo"], _albedo(bsdf))
    return facts


def depth_cap(albedo: float, tail: float = DEPTH_TAIL) -> int | None:
    """Smallest depth d whose truncated tail, sum over k >= d of a^(k-1), is below `tail`; None if a >= 1."""
    if albedo >= 1.0:
        return None
    if albedo <= 0.0:
        return 2
    return max(2, math.ceil(1 + math.log(tail * (1 - albedo)) / math.log(albedo)))


def analyse(spec: SceneSpec, overrides: dict[str, Any] | None = None) -> Effects:
    """Decide variant, depth and tiling for the scene; `overrides` (variant/integrator/max_depth) win."""
    return analyse_loaded(spec, overrides)[0]


def analyse_loaded(spec: SceneSpec, overrides: dict[str, Any] | None = None) -> tuple[Effects, Any]:
    """`analyse`, and the scene as it loaded in the chosen variant, for a caller that renders it next
    (the pre-pass) and need not load it twice."""
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    unknown = set(overrides) - set(_OVERRIDABLE)
    if unknown:
        raise SceneError(f"unknown effect override(s): {sorted(unknown)} (allowed: {list(_OVERRIDABLE)})")
    root = scene_mod.expand(spec).root
    reasons: list[str] = []
    polarized = polarization_need(root, spec.path)
    need = polarized or spectral_data.spectral_need(root, spec.path)
    variant = POLARIZED_VARIANT if polarized else SPECTRAL_VARIANT if need else RGB_VARIANT
    reasons.append(f"variant {variant}: " + (need or "no spectral data that rgb would render differently"))
    variant = _override(overrides, "variant", variant, reasons)
    elem = integrators.scene_element(root)
    override = overrides.get("integrator")
    name = override or integrators.describe(elem)
    reasons.append(f"integrator {name}: " + ("user override" if override else "the scene's own, kept as written"))
    if override:
        entry = integrators.kind(override)
        split, why = entry.splittable, f"{override}: {entry.note}"
    else:
        split, why = integrators.splittable(elem)
    reasons.append(("tiles: " if split else "one unit, the whole film: ") + why)
    loaded = scene_mod.load(spec, variant)  # also checks that Mitsuba accepts the scene
    own_depth = integrators.depth_of(elem)
    takes_depth = integrators.kind(override).depth if override else own_depth is not None
    if "max_depth" in overrides and not takes_depth:
        raise SceneError(f"{spec.path}: --depth {overrides['max_depth']}: the integrator {name} takes no depth")
    depth = _scene_depth(elem, own_depth)
    if "max_depth" not in overrides and not override:
        media = root.find(".//medium") is not None
        depth = _choose_depth(_surface_facts(loaded), elem, depth, media, reasons)
    depth = int(_override(overrides, "max_depth", depth, reasons))
    return Effects(variant, name, depth, reasons, override, split), loaded


def polarization_need(root: Any, scene_path: Any) -> str | None:
    """Why the scene needs a polarized variant (its first element that computes polarization), or None."""
    for elem in root.iter("integrator", "bsdf"):
        kind = elem.get("type")
        if (elem.tag, kind) == ("integrator", "stokes") or (elem.tag == "bsdf" and kind in POLARIZING_BSDFS):
            where = elem.get(scene_mod.SRC_ATTR, str(scene_path))
            return f"{where}: <{elem.tag} type={kind!r}> computes polarization, which only polarized variants do"
    return None


def _override(overrides: dict[str, Any], key: str, chosen: Any, reasons: list[str]) -> Any:
    if key in overrides and overrides[key] != chosen:
        reasons.append(f"{key} {overrides[key]}: user override (analysis chose {chosen})")
        return overrides[key]
    return chosen


def _choose_depth(facts: dict[str, Any], elem: Any, scene_depth: int, media: bool, reasons: list[str]) -> int:
    depth_types = [t for t in integrators.types(elem) if integrators.kind(t).depth]
    if not depth_types:
        reasons.append("max_depth: the integrator takes none")
        return scene_depth
    if any(t not in _CAPPABLE for t in depth_types):
        reasons.append(f"max_depth {scene_depth}: the scene's own (no cap for {', '.join(depth_types)})")
        return scene_depth
    if facts["delta"] or facts["glossy"] or facts["transmission"] or media:
        reasons.append(f"max_depth {scene_depth}: the scene's own; no cap with specular/glossy chains or media")
        return scene_depth
    cap = depth_cap(facts["albedo"])
    if cap is None:
        reasons.append(f"max_depth {scene_depth}: the scene's own (albedo unknown or >= 1: no cap)")
        return scene_depth
    if scene_depth != -1 and scene_depth <= cap:
        reasons.append(f"max_depth {scene_depth}: the scene's own (within the diffuse cap {cap})")
        return scene_depth
    reasons.append(f"max_depth {cap}: diffuse only, largest albedo {facts['albedo']:.2f}, the light beyond "
                   f"depth {cap} is under {DEPTH_TAIL:.1%} (scene asked {scene_depth})")
    return cap
