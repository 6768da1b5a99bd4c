"""The unit planner: unit features (C, S, Nd) and the user's level -> per unit depth, spp and band.

`Planner(rules_path, defuzzifier).plan(...)` gives one `RenderParams` per unit: at level `off` the user's
depth and spp, else the user's values weighted by the fuzzy rule base (rules/pathtracing.xml unless told),
as `core.rules.outputs` says. `adaptive_params` plans an adaptive job's units. Used by the render agents
(each with its own rule file) and by the in-process pipeline.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from core.data import default_rules_path
from core.model.levels import RULE_LEVELS
from core.model.units import WorkUnit
from core.rules.outputs import masyro_render_params, to_render_params
from fuzzy import Engine, load_rulebase

FEATURES = ("C", "S", "Nd")
DEPTH_STEPS = (1.0, 0.75, 0.5)  # the fractions of the user's depth a unit may render with


def quantise_depth_factor(rl: np.ndarray) -> np.ndarray:
    """Each Rl rounded to the nearest of DEPTH_STEPS (ties go to the deeper step). Dr.Jit bakes max_depth
    into the kernel, so each distinct depth costs a compilation per window size (~0.1-0.5 s): three steps
    keep that bounded."""
    steps = np.asarray(DEPTH_STEPS)
    rl = np.asarray(rl, dtype=np.float64)
    return steps[np.argmin(np.abs(rl[:, None] - steps[None, :]), axis=1)]


@dataclass(frozen=True)
class RenderParams:
    """What one unit renders with; `outputs` holds the crisp Rl, Ls, Ibs (empty at level off)."""

    depth: int
    spp: int
    band: int
    outputs: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


def adaptive_params(units: Sequence[WorkUnit], depth: int, band: int) -> list[RenderParams]:
    """Units whose plan set their samples: an adaptive job's (planning.budgets) or a progressive job's passes,
    each at its spp, its own depth where the plan pinned one (else the job's `depth`) and the least band; the
    rules chose when the job was planned, not per unit."""
    missing = [u.index for u in units if u.spp is None]
    if missing:
        raise ValueError(f"units {missing[:8]} of an adaptive or progressive job carry no planned spp")
    return [RenderParams(int(depth if u.depth is None else u.depth), int(u.spp), int(band)) for u in units]


class Planner:
    """Compiles one rule file once; `plan` then maps many units at a time.

    No budget is normalised across units: a unit's parameters depend only on its features and the scene's
    ranges, the same in the farm (an agent plans the units it is offered) as in `quekaro render`. How many
    samples a level spends overall is the rules' doing."""

    def __init__(
        self,
        rules_path: str | os.PathLike[str] | None = None,
        defuzzifier: str | None = None,
        min_band: int = 0,
    ) -> None:
        if min_band < 0:
            raise ValueError(f"min_band must be >= 0, got {min_band}")
        self.rules_path = Path(rules_path) if rules_path is not None else default_rules_path()
        self.rulebase = load_rulebase(self.rules_path)
        self.engine = Engine(self.rulebase, defuzzifier)  # None: the file's dialect's (fuzzy.engine)
        self.min_band = int(min_band)
        needed = {*FEATURES, "Op"}
        if set(self.engine.input_names) != needed:
            raise ValueError(
                f"{self.rules_path}: a planner rule base needs inputs {sorted(needed)}, "
                f"has {sorted(self.engine.input_names)}"
            )

    def plan(
        self,
        features: Mapping[str, np.ndarray],
        level: str,
        user_depth: int,
        user_spp: int,
        ranges: Mapping[str, tuple[float, float]] | None = None,
        min_band: int = 0,
        depth_floor: Sequence[int | None] | None = None,
    ) -> list[RenderParams]:
        """One `RenderParams` per unit; `ranges` defaults to the min/max of the given features. No band is
        below `min_band` (the job's: its film filter's reach, core.model.geometry.filter_reach, 2 px for
        Mitsuba's gaussian, so every core has all the samples its filter sees) nor the planner's own. No
        unit's depth is below its `depth_floor` (planning.depthcut; None: no floor), nor is a floor above
        the user's depth. A user depth of -1 (unbounded, or no depth) is kept: there is nothing to weight."""
        cols = _feature_columns(features)
        n = len(cols["C"])
        floor = max(self.min_band, int(min_band))
        if level == "off":
            return [RenderParams(int(user_depth), int(user_spp), floor) for _ in range(n)]
        if level not in RULE_LEVELS:
            choices = ", ".join(RULE_LEVELS)
            raise ValueError(f"unknown optimisation level {level!r}; expected off or one of {choices}")
        if n == 0:
            return []
        if ranges is None:
            ranges = {k: (float(v.min()), float(v.max())) for k, v in cols.items()}
        inputs = {**cols, "Op": np.full(n, self.rulebase.op_value(level))}
        if self.rulebase.dialect == "masyro":
            outputs = self.evaluation_engine(ranges).evaluate(inputs)
            maxima = {k: self.rulebase.output(k).universe[1] for k in ("Rl", "Ls")}
            depth, spp, band = masyro_render_params(outputs, max(user_depth, 0), user_spp, maxima)
        else:
            outputs = self.engine.evaluate(inputs, ranges)
            quantised = {**outputs, "Rl": quantise_depth_factor(outputs["Rl"])}
            depth, spp, band = to_render_params(quantised, max(user_depth, 0), user_spp)
        depth = np.maximum(depth, _floors(depth_floor, n, user_depth))
        if user_depth < 1:  # unbounded (-1), or an integrator without depth: nothing to weight
            depth = np.full(n, user_depth, dtype=np.int64)
        band = np.maximum(band, floor)
        crisp = [{k: float(outputs[k][i]) for k in ("Rl", "Ls", "Ibs")} for i in range(n)]
        return [RenderParams(int(depth[i]), int(spp[i]), int(band[i]), crisp[i]) for i in range(n)]


    def evaluation_engine(self, ranges: Mapping[str, tuple[float, float]]) -> Engine:
        """The engine a job's units run: the file's own, or for a MASYRO-dialect file one whose sets of C, S
        and Nd are rebuilt for the job's ranges (fuzzy.rulebase.RuleBase.for_ranges)."""
        if self.rulebase.dialect != "masyro":
            return self.engine
        rulebase = self.rulebase.for_ranges(ranges)
        return Engine(rulebase, self.engine.defuzzifier)


def _floors(depth_floor: Sequence[int | None] | None, n: int, user_depth: int) -> np.ndarray:
    """The units' depth floors as an array (1 where a unit has none), none above the user's depth."""
    if depth_floor is None:
        return np.ones(n, dtype=np.int64)
    if len(depth_floor) != n:
        raise ValueError(f"{len(depth_floor)} depth floors for {n} units")
    given = np.array([1 if f is None else int(f) for f in depth_floor], dtype=np.int64)
    return np.clip(given, 1, max(1, user_depth))


def _feature_columns(features: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    missing = [k for k in FEATURES if k not in features]
    if missing:
        raise ValueError(f"unit features lack {', '.join(missing)} (need {', '.join(FEATURES)})")
    cols = {k: np.atleast_1d(np.asarray(features[k], dtype=np.float64)) for k in FEATURES}
    if len({c.shape for c in cols.values()}) != 1 or cols["C"].ndim != 1:
        raise ValueError("unit features C, S, Nd must be 1-D arrays of one common length")
    return cols
