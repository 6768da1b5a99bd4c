"""Effect analysis: what a render may save without changing the image, with a reason for every decision.

The scene's integrator, sensor and film are kept as written. The analysis picks the variant (rgb unless
the scene's spectral data or polarization need more), keeps the scene's own depth, and says whether the
integrator can be split into tiles. User overrides (variant, integrator, max_depth) always win, and the
reasons say so. Entry points: `analyse`, `analyse_loaded`, `polarization_need`.
"""

from __future__ import annotations

from typing import Any

from core.errors import SceneError
from core.model import integrators
from core.model.job import Effects, SceneSpec
from core.scene import scene as scene_mod
from core.scene import spectral_data

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.mitsuba_env), and processes that never render must not pay for it.

RGB_VARIANT, SPECTRAL_VARIANT, POLARIZED_VARIANT = "llvm_ad_rgb", "llvm_ad_spectral", "llvm_ad_spectral_polarized"
POLARIZING_BSDFS = ("polarizer", "retarder", "pplastic", "measured_polarized")
_OVERRIDABLE = ("variant", "integrator", "max_depth")


def _scene_depth(elem: Any, depth: int | None) -> int:
    """The scene's own depth (-1 when its integrator takes none), refused where it renders nothing."""
    if depth is not None and (depth == 0 or depth < -1):
        # Mitsuba renders nothing at max_depth 0 (1 shows only the emitters): refuse rather than
        # deliver a black image without a word.
        raise SceneError(f"{elem.get(scene_mod.SRC_ATTR)}: integrator max_depth {depth} renders nothing; "
                         "use 1 or more, or -1 for unbounded")
    return -1 if depth is None else depth


def analyse(spec: SceneSpec, overrides: dict[str, Any] | None = None) -> Effects:
    """Decide variant, depth and tiling for the scene; `overrides` (variant/integrator/max_depth) win.

    Variant: rgb unless rgb would render the scene's spectral data differently (spectral_data.spectral_need)
    or the scene computes polarization (`polarization_need`). Depth: the scene's own max_depth, never
    lowered a priori. A bound from the reflectances (a path of depth d carries at most a^(d-1) of the
    brightest emitter's radiance) does not bound a pixel's share: where light arrives over many bounces
    (a baffled room) the tail is a larger part of the pixel, and Russian roulette already ends the long
    paths such a cap would cut; a rule level's per-unit cut is measured instead (planning.depthcut).
    Tiles: an integrator that splats light paths anywhere on the film (ptracer) renders whole, as one
    unit (core.model.integrators)."""
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
    reasons.append(f"integrator {name}: " + (_replaced(elem) if override else "the scene's own, kept as written"))
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
        reasons.append(f"max_depth {depth}: the scene's own" if takes_depth else "max_depth: the integrator takes none")
    depth = int(_override(overrides, "max_depth", depth, reasons))
    return Effects(variant, name, depth, reasons, override, split), loaded


def polarization_need(root: Any, scene_path: Any) -> str | None:
    """Why the scene needs a polarized variant (its first element that computes polarization), or None.

    A `stokes` integrator (Mitsuba refuses it in any other variant) or a polarizing BSDF (an unpolarized
    variant renders it without the effect it exists for: crossed polarizers let light through)."""
    for elem in root.iter("integrator", "bsdf"):
        kind = elem.get("type")
        if (elem.tag, kind) == ("integrator", "stokes") or (elem.tag == "bsdf" and kind in POLARIZING_BSDFS):
            where = elem.get(scene_mod.SRC_ATTR, str(scene_path))
            return f"{where}: <{elem.tag} type={kind!r}> computes polarization, which only polarized variants do"
    return None


def _replaced(elem: Any) -> str:
    dropped = integrators.parameter_names(elem)
    return "user override, with its type's defaults" + (
        f" (the scene's {integrators.describe(elem)} and its {', '.join(dropped)} are not used)" if dropped else "")


def _override(overrides: dict[str, Any], key: str, chosen: Any, reasons: list[str]) -> Any:
    if key in overrides and overrides[key] != chosen:
        reasons.append(f"{key} {overrides[key]}: user override (analysis chose {chosen})")
        return overrides[key]
    return chosen
