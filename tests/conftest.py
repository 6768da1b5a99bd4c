"""Every test that drives the master's auction checks its invariants after each stimulus (`Auction.validate`);
the suite's longest files are collected first."""

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


#: The suite's longest files (minutes each, `make test` prints the slowest tests), collected first: on
#: `make test`'s workers a long file started last leaves the others idle until it ends.
LONGEST_FIRST = ("test_bench_accuracy.py", "test_farm.py", "test_compat.py", "test_chaos.py", "test_multihost.py",
                 "test_accuracy.py", "test_adaptive_jobs.py", "test_hostile_user.py", "test_cli.py", "test_xmpp.py",
                 "test_progressive_farm.py", "test_depth_floors.py", "test_web_page.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
