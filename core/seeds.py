"""Seeds: one per (job, unit, pass), the same on every host, so that no two tiles share a noise pattern
(two renders of equal size with equal seeds do) and a retried unit renders the samples it would have."""

from __future__ import annotations

import hashlib

SEED_BITS = 31  # the protocol carries seeds as non-negative 31-bit integers


def unit_seed(job_id: str, unit: int, pass_: int) -> int:
    """A seed in [0, 2^31) distinct for every (job, unit, pass), stable across processes and hosts."""
    digest = hashlib.blake2b(f"{job_id}\x00{unit}\x00{pass_}".encode(), digest_size=4).digest()
    return int.from_bytes(digest, "little") & ((1 << SEED_BITS) - 1)
