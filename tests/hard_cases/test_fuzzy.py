"""Hard cases of the fuzzy engine read from rule files: degenerate trapezoids, rules that leave part of
the input space uncovered, and inputs exactly on set boundaries (of a case file and of the shipped rules)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from core.data import default_rules_path
from core.rules.outputs import LS_MAX, to_render_params
from fuzzy import Engine, load_rulebase
from hard_cases.conftest import RULES

# (x, y) -> z, worked out by hand from rules/degenerate.xml:
#  x=2,y=0 : Point and Wall+Low fire fully; the Spike singleton has no area, so the Block [6, 9] decides.
#  x=2,y=10: only the Point rule fires: the aggregate is the singleton alone, its point 1 comes out.
#  x=0 or 3 (Wall's vertical edges, inside the core) with y=8 (Low's foot): min(1, 0), nothing fires.
#  x=4.5: between Wall and Tri, nothing fires; x=6 and x=10: Tri's feet, nothing fires.
#  x=8,y=0 : Tri's peak and Low's core: the universe-wide All set, centroid 5 (not the default by chance:
#  x=8,y=2 checks the same rule at a different strength gives the same centroid).
DEGENERATE_CASES = [
    ((2.0, 0.0), 7.5), ((2.0, 10.0), 1.0), ((0.0, 8.0), 5.0), ((3.0, 8.0), 5.0), ((4.5, 0.0), 5.0),
    ((6.0, 0.0), 5.0), ((10.0, 10.0), 5.0), ((8.0, 0.0), 5.0), ((8.0, 2.0), 5.0), ((3.0, 0.0), 7.5),
]


@pytest.mark.parametrize("defuzzifier", ["centroid", "centre-of-sums"])
def test_degenerate_sets_and_uncovered_inputs_from_a_file(defuzzifier):
    engine = Engine(load_rulebase(RULES / "degenerate.xml"), defuzzifier)
    xy = np.array([c[0] for c in DEGENERATE_CASES])
    z = engine.evaluate(xy)["z"]
    np.testing.assert_allclose(z, [c[1] for c in DEGENERATE_CASES], atol=1e-9)


def test_degenerate_file_fires_what_it_should_at_the_boundaries():
    engine = Engine(load_rulebase(RULES / "degenerate.xml"))
    acts = engine.activations({"x": [2.0, 3.0, 3.0, 6.0], "y": [10.0, 0.0, 8.0, 0.0]})["z"]
    labels = [s.label for s in engine.rulebase.output("z").sets]
    fired = [{labels[j] for j in np.nonzero(row)[0]} for row in acts]
    assert fired == [{"Spike"}, {"Block"}, set(), set()]


def _shipped_boundary_grid() -> np.ndarray:
    """Every input at every vertex of the shipped sets: dynamic ones over the range (0, 1) at k/8 (their
    vertices lie at k/4 and k/2), Op at 0..4, and the midpoints between."""
    dyn = np.linspace(0.0, 1.0, 9)
    op = np.linspace(0.0, 4.0, 9)
    return np.array(list(itertools.product(dyn, dyn, dyn, op)))


def test_shipped_rules_at_every_set_boundary_give_bounded_parameters():
    engine = Engine(load_rulebase(default_rules_path()))
    assert set(engine.input_names) == {"C", "S", "Nd", "Op"}
    grid = _shipped_boundary_grid()
    inputs = {name: grid[:, ["C", "S", "Nd", "Op"].index(name)] for name in engine.input_names}
    ranges = {"C": (0.0, 1.0), "S": (0.0, 1.0), "Nd": (0.0, 1.0)}
    for defuzzifier in ("centroid", "centre-of-sums"):
        out = Engine(engine.rulebase, defuzzifier).evaluate(inputs, ranges)
        for name, values in out.items():
            lo, hi = engine.rulebase.output(name).universe
            assert np.isfinite(values).all() and (values >= lo).all() and (values <= hi).all(), name
        depth, spp, band = to_render_params(out, user_depth=8, user_spp=64)
        assert (depth >= 1).all() and (depth <= 8).all()
        assert (spp >= 1).all() and (spp <= LS_MAX * 64).all()  # samples may move up to LS_MAX x
        assert (band >= 0).all() and (band <= 4).all()  # the shipped bands stay within 4 px


def test_shipped_rules_with_an_empty_observed_range():
    """Every unit alike (lo == hi for every dynamic input): finite, and the same for every unit."""
    engine = Engine(load_rulebase(default_rules_path()))
    n = 5
    inputs = {"C": np.full(n, 0.3), "S": np.full(n, 1024.0), "Nd": np.zeros(n), "Op": np.linspace(0, 4, n)}
    ranges = {"C": (0.3, 0.3), "S": (1024.0, 1024.0), "Nd": (0.0, 0.0)}
    out = engine.evaluate(inputs, ranges)
    assert all(np.isfinite(v).all() for v in out.values())
    same = engine.evaluate({k: np.full(n, v[2]) for k, v in inputs.items()}, ranges)
    assert all(np.ptp(v) == 0 for v in same.values())
