"""Seeds: one per (job, unit, pass), the same on every host, so that no two tiles share a noise pattern
(two renders of equal size with equal seeds do) and a retried unit renders the samples it would have."""

from __future__ import annotations

import hashlib
import json
from typing import Any

SEED_BITS = 31  # the protocol carries seeds as non-negative 31-bit integers


def unit_seed(job_id: str, unit: int, pass_: int) -> int:
    """A seed in [0, 2^31) distinct for every (job, unit, pass), stable across processes and hosts."""
    digest = hashlib.blake2b(f"{job_id}\x00{unit}\x00{pass_}".encode(), digest_size=4).digest()
    return int.from_bytes(digest, "little") & ((1 << SEED_BITS) - 1)


# The options that shape a job's pre-pass (its samples, depth, integrator and sensor). A level, a rule file,
# a defuzzifier, a unit count or adaptive sampling only read the pre-pass, so they leave the seed alone.
PREPASS_OPTIONS = ("spp", "depth", "variant", "integrator", "sensor")


def plan_seed(scene_digest: str, defines: dict[str, str], options: dict[str, Any]) -> int:
    """The pre-pass seed of a job, from the scene's content and the options that shape its pre-pass.

    The same job submitted again then gets the same units: their window sizes, which Dr.Jit compiles one
    kernel for each (~0.5 s apiece, cached on disk), are reused instead of compiled anew because the
    pre-pass noise moved a split. And every level of one scene reads one pre-pass: a level's budget moves
    with the pre-pass's noise, so levels seeded apart could spend in another order than the rules'.
    """
    shaping = {k: options.get(k) for k in PREPASS_OPTIONS}
    text = json.dumps([scene_digest, sorted(defines.items()), shaping], sort_keys=True, default=str)
    return unit_seed(text, -1, 0)
