"""From crisp rule outputs to render parameters, as the paper says: they weight the user's values.

The path-tracing rule base (rules/pathtracing.xml) has three outputs: Rl weights the user's path depth,
Ls the user's samples per pixel, and Ibs is the interpolation band in pixels; where no rule fired, each
is 1.0 (keep the user's value). `to_render_params` maps them; `masyro_render_params` keeps MASYRO's own
mapping for its dialect. The optimisation level is an input, Op (`RuleBase.op_value`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from core.model.units import SPP_MAX

LS_MAX = 3.0  # most a unit's spp may grow over the user's (to_render_params says why)


def to_render_params(
    outputs: Mapping[str, np.ndarray], user_depth: int, user_spp: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth, spp, band) int64 arrays from the crisp outputs Rl, Ls, Ibs:
    depth = max(1, round(user_depth * clip(Rl, 0, 1))), band = max(0, round(Ibs)),
    spp = clip(round(user_spp * clip(Ls, 0, LS_MAX)), 1, SPP_MAX).

    Depth never exceeds the user's: it bounds the paths the image may have, and deeper paths only cost.
    Spp may reach LS_MAX times the user's: the rules move samples from simple units to noisy ones (at a
    fixed time a unit's error is least when its spp grows with its noise); the cap bounds one unit's cost.
    SPP_MAX, the most a job may ask for, keeps a job near that limit in units the farm's messages carry.
    Depth and spp are at least 1, so a unit always renders something. A planner may impose a larger
    band and quantise depth (core.rules.unit_params does)."""
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
    """(depth, spp, band) from MASYRO-dialect outputs; `maxima` holds the universe maximum of Rl and Ls.

    MASYRO's mapping (its trunk/src/FinalRender.py): the crisp Rl and Ls are floored, divided by their
    universe's maximum (9 and 13 in its file) and raised to at least 0.5, then weight the user's depth and
    spp (at least 1, at most SPP_MAX); the band is the floored Ibs. An output no rule fired for (NaN) keeps
    the user's value: factor 1, band 0."""
    rl, ls, ibs = (np.asarray(outputs[k], dtype=np.float64) for k in ("Rl", "Ls", "Ibs"))

    def factor(values: np.ndarray, top: float) -> np.ndarray:
        return np.where(np.isnan(values), 1.0, np.maximum(0.5, np.floor(np.nan_to_num(values)) / top))

    depth = np.maximum(1, (factor(rl, maxima["Rl"]) * user_depth).astype(np.int64))
    spp = np.clip((factor(ls, maxima["Ls"]) * user_spp).astype(np.int64), 1, SPP_MAX)
    band = np.where(np.isnan(ibs), 0, np.floor(np.nan_to_num(ibs))).astype(np.int64)
    return depth, spp, np.maximum(band, 0)
