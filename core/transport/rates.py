"""Per-sender message rates: a token bucket each sender draws from before its message is read.

One peer that floods (a lying or broken agent sending stray proposals and heartbeats by the thousand)
must not fill the inbox every sender shares, nor hold the receiver's loop, nor write a log line per
message. Each sender may send `burst` messages at once and `rate` a second after that; what it sends
beyond is refused unread. Pure: the caller gives the time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

REPORT_S = 10.0
MAX_SENDERS = 4096


@dataclass
class _Bucket:
    tokens: float
    at: float
    refused: int = 0  # messages refused since the last report
    reported_at: float = float("-inf")


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
            if len(self.buckets) >= MAX_SENDERS:
                self._forget_quiet(now)
            bucket = self.buckets[sender] = _Bucket(self.burst, now)
        bucket.tokens = min(self.burst, bucket.tokens + max(0.0, now - bucket.at) * self.rate)
        bucket.at = now
        if bucket.tokens >= 1.0:
            bucket.tokens -= 1.0
            return True
        bucket.refused += 1
        return False

    def report(self, sender: str, now: float) -> int:
        """How many messages of `sender` were refused since the last report, if that was over REPORT_S ago
        (the first refusal of a flood is reported at once); else 0, and they count toward the next."""
        bucket = self.buckets.get(sender)
        if bucket is None or not bucket.refused or now - bucket.reported_at < REPORT_S:
            return 0
        count, bucket.refused, bucket.reported_at = bucket.refused, 0, now
        return count

    def _forget_quiet(self, now: float) -> None:
        full = [s for s, b in self.buckets.items() if b.tokens + (now - b.at) * self.rate >= self.burst]
        for sender in full:
            del self.buckets[sender]
