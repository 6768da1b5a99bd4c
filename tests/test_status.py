"""The transition tables of unit and job status (core.model.status): illegal changes raise, naming what changed
and how; the tables hold exactly the changes the auction and the store make, each marked with who makes it;
and neither changes a status any other way (no bare assignment, no status literal in SQL)."""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

import pytest
from auction_support import cancel, informed, message, register, tick
from test_auction import failure, inform, make, round_trip
from test_store import HASH, info_of, new_store

import master.auction.machine
import master.store
from core.model import messages as m
from core.model import status as st
from core.model.status import JOB_TRANSITIONS, UNIT_TRANSITIONS, JobStatus, TransitionError, UnitStatus
from master import auction as au

REPO = Path(__file__).resolve().parent.parent
Seen = dict[str, set[tuple[str, str, str]]]  # who -> {(unit|job, from, to)}


def test_illegal_changes_raise_naming_the_unit_or_job_and_both_statuses() -> None:
    assert st.unit_transition("job 'j' unit 3", "pending", UnitStatus.ANNOUNCED) is UnitStatus.ANNOUNCED
    with pytest.raises(TransitionError, match=r"^job 'j' unit 3: done -> awarded is not an allowed status change"
                                              r" \(from done: pending\)$"):
        st.unit_transition("job 'j' unit 3", UnitStatus.DONE, UnitStatus.AWARDED)
    with pytest.raises(TransitionError, match=r"^job 'j': failed -> done .*\(from failed: running\)$"):
        st.job_transition("job 'j'", JobStatus.FAILED, JobStatus.DONE)
    with pytest.raises(TransitionError, match="job 'j': running -> running"):
        st.job_transition("job 'j'", "running", "running")
    with pytest.raises(TransitionError, match="job 'j' unit 1: 'sold' is not a valid UnitStatus"):
        st.unit_transition("job 'j' unit 1", "pending", "sold")


def test_the_tables_are_well_formed() -> None:
    for table, kind in ((UNIT_TRANSITIONS, UnitStatus), (JOB_TRANSITIONS, JobStatus)):
        for (old, new), (who, when) in table.items():
            assert type(old) is kind and type(new) is kind and old != new
            assert who in ("A", "S", "AS") and when
    # The store never holds ANNOUNCED, so it makes no change from or to it.
    assert UnitStatus.ANNOUNCED not in st.STORED_UNIT_STATUSES
    store_pairs = [pair for pair, (who, _) in UNIT_TRANSITIONS.items() if "S" in who]
    assert all(UnitStatus.ANNOUNCED not in pair for pair in store_pairs)


def _record(monkeypatch: pytest.MonkeyPatch) -> Seen:
    """Every transition check the auction and the store make, by whom (they import the checks by name)."""
    seen: Seen = defaultdict(set)
    for who, module in (("A", master.auction.machine), ("S", master.store)):
        for kind, real in (("unit", st.unit_transition), ("job", st.job_transition)):
            def check(what: str, old: str, new: str, who=who, kind=kind, real=real) -> str:
                out = real(what, old, new)
                seen[who].add((kind, str(old), str(new)))
                return out
            monkeypatch.setattr(module, f"{kind}_transition", check)
    return seen


def _drive_auction() -> None:
    a = make([1.0], ["A"])  # an unsold round, then awarded and done: the job is done
    tick(a, 0.0)
    tick(a, a.config.cfp_timeout_s + 1)
    award = round_trip(a, 5.0)[0]
    informed(a, award.to, inform(award, 1.0), 6.0)
    a = make([1.0], ["A"], au.Config(max_unit_failures=2))  # requeued, then failed twice: the job fails
    round_trip(a, 0.0)
    message(a, "A", m.Heartbeat(conversation="h", busy=()), a.config.award_grace_s + 1)
    register(a, "B", 20.0)
    for now in (20.0, 21.0):
        award = round_trip(a, now)[0]
        message(a, award.to, failure(award), now)
    assert a._jobs["job-1"].status == JobStatus.FAILED
    a.handle(au.JobRequeueRequested("job-1"), 22.0)  # requeued: its failed unit back to pending, the job running
    a = make([1.0, 2.0, 3.0], ["A", "B"], au.Config(slots=1))  # cancelled: two units awarded, one announced
    round_trip(a, 0.0)
    register(a, "C", 0.1)
    tick(a, 0.1)
    assert a.counts("job-1") == {"awarded": 2, "announced": 1}
    cancel(a, "job-1")
    a.handle(au.JobRequeueRequested("job-1"), 0.2)


def _drive_store(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=3)
    store.record_award("job-1", 0, "A", "aa" * 16, 101.0, 1.0)
    store.finish_attempt("aa" * 16, "failed", 102.0, reason="crash")
    store.record_award("job-1", 0, "A", "ab" * 16, 103.0, 1.0)
    tile = tmp_path / "0.exr"
    tile.write_bytes(b"tile")
    store.record_result("job-1", 0, str(tile), HASH, {}, 104.0)
    store.mark_done("job-1", 0, 104.0)
    store.record_award("job-1", 1, "A", "ac" * 16, 105.0, 1.0)
    store.resume(106.0)
    for index in (1, 2):
        store.record_award("job-1", index, "A", f"{index:032x}", 107.0, 1.0)
        store.record_result("job-1", index, str(tile), HASH, {}, 108.0)
        store.mark_done("job-1", index, 108.0)
    store.set_status("job-1", JobStatus.DONE, 109.0)
    tile.unlink()
    store.repair(["job-1"], 110.0)
    store.set_status("job-1", JobStatus.FAILED, 111.0)
    store.apply([au.JobRequeued("job-1", (0,), 1, "asked by the user")], 111.5)
    other = new_store(tmp_path / "other.db", n=1)
    other.set_status("job-1", JobStatus.CANCELLED, 112.0)
    other.apply([au.JobRequeued("job-1", (0,), 1, "asked by the user")], 113.0)


def test_the_tables_hold_exactly_the_changes_the_auction_and_the_store_make(tmp_path: Path, monkeypatch) -> None:
    seen = _record(monkeypatch)
    _drive_auction()
    _drive_store(tmp_path)
    for kind, table in (("unit", UNIT_TRANSITIONS), ("job", JOB_TRANSITIONS)):
        for who in ("A", "S"):
            made = {(old, new) for k, old, new in seen[who] if k == kind}
            marked = {(str(old), str(new)) for (old, new), (by, _) in table.items() if who in by}
            assert made == marked, (kind, who, sorted(made ^ marked))


def test_a_restored_auction_and_store_agree_without_a_change_outside_the_table(tmp_path: Path, monkeypatch):
    """Restoring is no status change: done units start done in the auction (and stay done in the store)."""
    seen = _record(monkeypatch)
    with new_store(tmp_path / "farm.db", n=2) as store:
        store.record_award("job-1", 0, "A", "aa" * 16, 101.0, 1.0)
        store.record_result("job-1", 0, "/t/0.exr", HASH, {}, 101.0)
        store.mark_done("job-1", 0, 101.0)
        seen.clear()
        store.resume(200.0)
        auction, out = au.Auction.restore(store.running_jobs(), lambda j: info_of(store.job(j)), store.credits())
    assert out == [] and seen["A"] == set()
    assert {i: u.status for i, u in auction._jobs["job-1"].units.items()} == {0: UnitStatus.DONE,
                                                                                1: UnitStatus.PENDING}


def _status_assignments(path: Path) -> list[str]:
    """Functions of `path` that assign to an attribute named `status`."""
    out = []
    for func in ast.walk(ast.parse(path.read_text())):
        if not isinstance(func, ast.FunctionDef):
            continue
        for node in ast.walk(func):
            targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
            flat = [t for target in targets if target is not None
                    for t in (target.elts if isinstance(target, ast.Tuple) else [target])]
            if any(isinstance(t, ast.Attribute) and t.attr == "status" for t in flat):
                out.append(func.name)
    return out


def test_statuses_change_only_through_the_table() -> None:
    assert sorted(_status_assignments(REPO / "master" / "auction" / "machine.py")) == ["_set_job", "_set_unit"]
    assert _status_assignments(REPO / "bench" / "simulate.py") == []
    sql = (REPO / "master" / "store.py").read_text()
    literal = re.compile(r"status\s*(=|!=|IN\s*\()\s*'")
    assert not literal.findall(sql), "a status literal in the store's SQL: take it from core.model.status"
