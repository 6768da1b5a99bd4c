"""From crisp rule outputs to render parameters, as the paper says: they weight the user's values.

The path-tracing rule base (rules/pathtracing.xml) has three outputs:
  Rl   a factor of the user's path depth      depth = max(1, round(user_depth * clip(Rl, 0, 1)))
  Ls   a factor of the user's samples/pixel   spp   = clip(round(user_spp * clip(Ls, 0, LS_MAX)), 1, SPP_MAX)
  Ibs  the interpolation band in pixels       band  = max(0, round(Ibs))
Depth is clipped to [0, 1] of the user's: the user's depth bounds the light paths the image may have,
and deeper paths only cost. Samples may go up to LS_MAX (3) times the user's: the rules move samples
from simple units to the noisy ones, which needs factors above 1 (at a fixed time a unit's error is
least when its spp grows with its noise); the cap bounds what one unit can cost. No unit gets more than
SPP_MAX, the most a job may ask for, so that a job near that limit plans units the farm's messages carry.
The outputs' default (no rule fired) is 1.0, i.e. "keep the user's value". Results are clamped to
depth >= 1 and spp >= 1 so that a unit always renders something. A planner may impose a larger minimum
band (core.rules.unit_params does: the reconstruction filter's reach) and quantise depth.

The optimisation level is an input: `RuleBase.op_value(level)` gives the crisp Op for a level name, the
middle of that label's plateau in the rule file's own Op sets (VS=0 .. VB=4 in rules/pathtracing.xml,
2.5 .. 27.5 in MASYRO's file, whose Op universe is 0..30).

MASYRO's dialect keeps MASYRO's mapping (its trunk/src/FinalRender.py): the crisp Rl and Ls are floored,
divided by their universe's maximum (9 and 13 in its file) and raised to at least 0.5, then weight the
user's depth and samples (at least 1, at most SPP_MAX); the band is the floored Ibs. An output no rule fired for (NaN)
keeps the user's value: factor 1, band 0 (`masyro_render_params`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from core.model.units import SPP_MAX

LS_MAX = 3.0  # most a unit's spp may grow over the user's (see the module docstring)


def to_render_params(
    outputs: Mapping[str, np.ndarray], user_depth: int, user_spp: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth, spp, band) int64 arrays from the crisp outputs Rl, Ls, Ibs (see the module docstring)."""
    if user_depth < 0 or user_spp < 0:
        raise ValueError(f"user depth and spp must be >= 0 to be weighted; got {user_depth}, {user_spp}")
    rl, ls, ibs = (np.asarray(outputs[k], dtype=np.float64) for k in ("Rl", "Ls", "Ibs"))
    for name, arr in (("Rl", rl), ("Ls", ls), ("Ibs", ibs)):
        if not np.isfinite(arr).all():
            raise ValueError(f"output {name} has a non-finite value")
    depth = np.maximum(1, np.rint(user_depth * np.clip(rl, 0.0, 1.0))).astype(np.int64)
    spp = np.clip(np.rint(user_spp * np.clip(ls, 0.0, LS_MAX)), 1, SPP_MAX).astype(np.int64)
    band = np.maximum(0, np.rint(ibs)).astype(np.int64)
    return depth, spp, band


def masyro_render_params(
    outputs: Mapping[str, np.ndarray], user_depth: int, user_spp: int, maxima: Mapping[str, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth, spp, band) from MASYRO-dialect outputs (see the module docstring); `maxima` holds the
    universe maximum of Rl and Ls."""
    rl, ls, ibs = (np.asarray(outputs[k], dtype=np.float64) for k in ("Rl", "Ls", "Ibs"))

    def factor(values: np.ndarray, top: float) -> np.ndarray:
        return np.where(np.isnan(values), 1.0, np.maximum(0.5, np.floor(np.nan_to_num(values)) / top))

    depth = np.maximum(1, (factor(rl, maxima["Rl"]) * user_depth).astype(np.int64))
    spp = np.clip((factor(ls, maxima["Ls"]) * user_spp).astype(np.int64), 1, SPP_MAX)
    band = np.where(np.isnan(ibs), 0, np.floor(np.nan_to_num(ibs))).astype(np.int64)
    return depth, spp, np.maximum(band, 0)
