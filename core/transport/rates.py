"""Per-sender message rates: a token bucket each sender draws from before its message is read.

One peer that floods (a lying or broken agent sending stray proposals and heartbeats by the thousand)
must not fill the inbox every sender shares, nor hold the receiver's loop, nor write a log line per
message. Each sender may send `burst` messages at once and `rate` a second after that; what it sends
beyond is refused unread. Pure: the caller gives the time.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class _Bucket:
    tokens: float
    at: float
    refused: int = 0  # messages refused so far


@dataclass
class SenderRates:
    """Token buckets, one per sender (`rate` messages a second, `burst` at once)."""

    rate: float
    burst: float
    buckets: dict[str, _Bucket] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.rate <= 0 or self.burst < 1:
            raise ValueError(f"a sender's rate ({self.rate}/s) must be above 0 and its burst ({self.burst}) 1 or more")

    def allow(self, sender: str, now: float) -> bool:
        """Whether `sender` may send one more message at `now` (monotonic seconds); takes its token."""
        bucket = self.buckets.get(sender)
        if bucket is None:
            bucket = self.buckets[sender] = _Bucket(self.burst, now)
        bucket.tokens = min(self.burst, bucket.tokens + max(0.0, now - bucket.at) * self.rate)
        bucket.at = now
        if bucket.tokens >= 1.0:
            bucket.tokens -= 1.0
            return True
        bucket.refused += 1
        return False

    def refused(self, sender: str) -> int:
        """Messages of `sender` refused so far."""
        bucket = self.buckets.get(sender)
        return 0 if bucket is None else bucket.refused
