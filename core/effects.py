"""Effect analysis: decide what a render must simulate (variant, integrator, depth cap), with a reason
for every decision, from the scene's XML (before a variant exists) and the loaded scene's flags.

Rules, each conservative (when unsure, keep the costlier choice):
- variant: spectral when the XML uses spectral-only input (wavelength:value spectra, spectrum files,
  blackbody/regular/irregular spectra); otherwise rgb.
- integrator: `volpath` when the XML declares a participating medium; `direct` when no light can
  reach the camera through two or more bounces (no delta/glossy/transmissive BSDF, and either every
  non-emitting surface is black or there is a single convex one, which cannot light itself);
  otherwise `path`.
- depth cap: only without delta, glossy or transmissive BSDFs and without media (no specular chains):
  a path of depth d carries at most a^(d-1) of the light, a = the largest diffuse albedo, so depth is
  capped where the whole tail beyond it is below DEPTH_TAIL of the image's light.
User overrides (variant, integrator, max_depth) always win, and the reasons say so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core import scene as scene_mod
from core.errors import SceneError

DEPTH_TAIL = 5e-3
RGB_VARIANT, SPECTRAL_VARIANT = "llvm_ad_rgb", "llvm_ad_spectral"
_SPECTRAL_TYPES = {"blackbody", "regular", "irregular"}
_PATH_TRACERS = {"path", "volpath", "volpathmis", "direct", "prb", "prbvolpath"}
_CONVEX = {"Sphere", "Rectangle", "Disk"}
_OVERRIDABLE = ("variant", "integrator", "max_depth")


@dataclass
class Effects:
    """What the render simulates, and why."""

    variant: str
    integrator: str
    max_depth: int
    reasons: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"variant": self.variant, "integrator": self.integrator, "max_depth": self.max_depth,
                "reasons": list(self.reasons)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Effects:
        return cls(str(data["variant"]), str(data["integrator"]), int(data["max_depth"]),
                   [str(r) for r in data.get("reasons", [])])


def _spectral_need(root: Any) -> str | None:
    for elem in root.iter("spectrum"):
        src = elem.get(scene_mod.SRC_ATTR, "?")
        if elem.get("type") in _SPECTRAL_TYPES:
            return f"{src}: <spectrum type={elem.get('type')!r}> is spectral-only"
        if elem.get("filename"):
            return f"{src}: spectrum read from file {elem.get('filename')!r}"
        if ":" in elem.get("value", ""):
            return f"{src}: <spectrum name={elem.get('name')!r}> is given per wavelength"
    return None


def _scene_integrator(root: Any) -> tuple[str, int]:
    elem = root.find("integrator")
    if elem is None:
        return "path", -1
    depth = -1
    for child in elem:
        if child.tag == "integer" and child.get("name") == "max_depth":
            try:
                depth = int(child.get("value", "-1"))
            except ValueError as exc:
                raise SceneError(f"{elem.get(scene_mod.SRC_ATTR)}: max_depth {child.get('value')!r}") from exc
    if depth == 0 or depth < -1:
        # Mitsuba renders nothing at max_depth 0 (1 shows only the emitters): refuse rather than
        # deliver a black image without a word.
        raise SceneError(f"{elem.get(scene_mod.SRC_ATTR)}: integrator max_depth {depth} renders nothing; "
                         "use 1 or more, or -1 for unbounded")
    return elem.get("type", "path"), depth


def _albedo(bsdf: Any) -> float:
    """Largest reflectance a diffuse BSDF can have; 1.0 when it cannot be read (no cap then)."""
    import mitsuba as mi

    params = mi.traverse(bsdf)
    keys = [k for k in params.keys() if k in ("reflectance.value", "reflectance.data")]  # noqa: SIM118
    if not keys or "Diffuse" not in bsdf.class_name():
        return 1.0
    return max(float(np.max(np.array(params[k]))) for k in keys)


def _surface_facts(loaded: Any) -> dict[str, Any]:
    import mitsuba as mi

    facts = {"delta": False, "glossy": False, "transmission": False, "albedo": 0.0, "lit_shapes": []}
    for shape in loaded.shapes():
        bsdf = shape.bsdf()
        flags = int(bsdf.flags())
        facts["delta"] |= bool(flags & int(mi.BSDFFlags.Delta))
        facts["glossy"] |= bool(flags & int(mi.BSDFFlags.Glossy))
        facts["transmission"] |= bool(flags & int(mi.BSDFFlags.Transmission) and
                                      not flags & int(mi.BSDFFlags.Null))
        if not shape.is_emitter():
            albedo = _albedo(bsdf)
            facts["albedo"] = max(facts["albedo"], albedo)
            if albedo > 0:
                facts["lit_shapes"].append(shape.class_name())
    facts["infinite"] = any(int(e.flags()) & int(mi.EmitterFlags.Infinite) for e in loaded.emitters())
    return facts


def depth_cap(albedo: float, tail: float = DEPTH_TAIL) -> int | None:
    """Smallest depth d whose truncated tail, sum over k >= d of a^(k-1), is below `tail`; None if a >= 1."""
    if albedo >= 1.0:
        return None
    if albedo <= 0.0:
        return 2
    return max(2, math.ceil(1 + math.log(tail * (1 - albedo)) / math.log(albedo)))


def analyse(spec: scene_mod.SceneSpec, overrides: dict[str, Any] | None = None) -> Effects:
    """Decide variant, integrator and depth for the scene; `overrides` (variant/integrator/max_depth) win."""
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    unknown = set(overrides) - set(_OVERRIDABLE)
    if unknown:
        raise SceneError(f"unknown effect override(s): {sorted(unknown)} (allowed: {list(_OVERRIDABLE)})")
    root = scene_mod.expand(spec).root
    reasons: list[str] = []
    need = _spectral_need(root)
    variant = SPECTRAL_VARIANT if need else RGB_VARIANT
    reasons.append(f"variant {variant}: " + (need or "no spectral-only input in the XML"))
    variant = _override(overrides, "variant", variant, reasons)
    loaded = scene_mod.load(spec, variant)
    facts = _surface_facts(loaded)
    scene_type, scene_depth = _scene_integrator(root)
    integrator = _choose_integrator(root, facts, scene_type, reasons)
    integrator = _override(overrides, "integrator", integrator, reasons)
    depth = _choose_depth(facts, integrator, scene_depth, root.find(".//medium") is not None, reasons)
    depth = int(_override(overrides, "max_depth", depth, reasons))
    return Effects(variant, integrator, depth, reasons)


def _override(overrides: dict[str, Any], key: str, chosen: Any, reasons: list[str]) -> Any:
    if key in overrides and overrides[key] != chosen:
        reasons.append(f"{key} {overrides[key]}: user override (analysis chose {chosen})")
        return overrides[key]
    return chosen


def _choose_integrator(root: Any, facts: dict[str, Any], scene_type: str, reasons: list[str]) -> str:
    if scene_type not in _PATH_TRACERS:
        reasons.append(f"integrator {scene_type}: the scene's own, not a path tracer, kept as is")
        return scene_type
    if root.find(".//medium") is not None:
        reasons.append("integrator volpath: the scene declares a participating medium")
        return "volpath"
    chains = facts["delta"] or facts["glossy"] or facts["transmission"]
    lit = facts["lit_shapes"]
    single_convex = len(lit) <= 1 and all(name in _CONVEX for name in lit)
    if not chains and single_convex:
        why = "no non-emitting surface reflects light" if not lit else f"a single convex {lit[0]} cannot light itself"
        reasons.append(f"integrator direct: no indirect light can reach the camera ({why})")
        return "direct"
    what = "specular/glossy/transmissive BSDFs" if chains else f"{len(lit)} reflecting surfaces light each other"
    reasons.append(f"integrator path: indirect light matters ({what})")
    return "path"


def _choose_depth(facts: dict[str, Any], integrator: str, scene_depth: int, media: bool,
                  reasons: list[str]) -> int:
    if integrator == "direct":
        reasons.append("max_depth 2: the direct integrator stops after one bounce")
        return 2
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
