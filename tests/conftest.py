"""Every test that drives the master's auction checks its invariants after each stimulus (`Auction.validate`)."""

from __future__ import annotations

import pytest

from master.auction import Auction


@pytest.fixture(autouse=True)
def validated_auction(monkeypatch: pytest.MonkeyPatch) -> None:
    handle = Auction.handle

    def checked(self: Auction, stimulus, now: float):
        out = handle(self, stimulus, now)
        self.validate()
        return out

    monkeypatch.setattr(Auction, "handle", checked)
