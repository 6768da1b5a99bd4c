"""Unit and job status, and the one table of allowed status changes for each.

The auction (`master.auction`) and the job store (`master.store`) change a status only through
`unit_transition` / `job_transition`, so a change that neither should make fails at once, naming the unit or
job and both statuses, instead of leaving the two disagreeing about a unit after a crash.
"""

from __future__ import annotations

from enum import StrEnum
from typing import TypeVar


class UnitStatus(StrEnum):
    PENDING = "pending"
    ANNOUNCED = "announced"  # in an open call for proposals: the auction's alone, never stored
    AWARDED = "awarded"
    DONE = "done"
    FAILED = "failed"


class JobStatus(StrEnum):
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


class TransitionError(ValueError):
    """A status change that the transition table does not allow (a bug, not a user's error)."""


# The statuses the store's units table holds. ANNOUNCED lives only in the auction (a round lasts seconds, and a
# restarted master opens new ones), so the store sees a unit go from pending straight to awarded.
STORED_UNIT_STATUSES: tuple[UnitStatus, ...] = tuple(s for s in UnitStatus if s is not UnitStatus.ANNOUNCED)

_U, _J = UnitStatus, JobStatus
# (from, to) -> (who makes the change: "A" the auction, "S" the store, "AS" both; when).
UNIT_TRANSITIONS: dict[tuple[UnitStatus, UnitStatus], tuple[str, str]] = {
    (_U.PENDING, _U.ANNOUNCED): ("A", "offered in a call for proposals"),
    (_U.ANNOUNCED, _U.AWARDED): ("A", "its round awarded it"),
    (_U.ANNOUNCED, _U.PENDING): ("A", "its round ended without a winner"),
    (_U.PENDING, _U.AWARDED): ("S", "awarded (the store never sees ANNOUNCED)"),
    (_U.AWARDED, _U.DONE): ("AS", "its tile is durable and the award's holder is done"),
    (_U.AWARDED, _U.PENDING): ("AS", "requeued (agent lost, award not acknowledged) or failed on its agent, to "
                                     "be retried; in the store also every award of a running job on restart"),
    (_U.PENDING, _U.FAILED): ("AS", "its job failed or was cancelled"),
    (_U.ANNOUNCED, _U.FAILED): ("A", "its job failed or was cancelled during the unit's round"),
    (_U.AWARDED, _U.FAILED): ("AS", "its job failed or was cancelled while the unit rendered"),
    (_U.DONE, _U.PENDING): ("S", "repaired as the master starts: done, but its tile is not on disk"),
    # Legal: a unit fails only with its job (its own failures send it back to pending), so a unit still
    # failed has no tile and nothing of it is on an agent; its job runs again only by the user's requeue.
    (_U.FAILED, _U.PENDING): ("AS", "its failed or cancelled job requeued by the user"),
}

JOB_TRANSITIONS: dict[tuple[JobStatus, JobStatus], tuple[str, str]] = {
    (_J.RUNNING, _J.DONE): ("AS", "every unit done"),
    (_J.RUNNING, _J.FAILED): ("AS", "a unit cannot be done, the job's messages cannot be sent, or a restarted "
                                    "master cannot describe it"),
    (_J.RUNNING, _J.CANCELLED): ("AS", "cancelled by the user"),
    (_J.DONE, _J.RUNNING): ("S", "repaired as the master starts: a done unit's tile is gone"),
    # Legal: an ended job keeps its done units' tiles and its plan; requeued, it is auctioned again from them,
    # as a restarted master takes up a running job.
    (_J.FAILED, _J.RUNNING): ("AS", "requeued by the user: its units not done go back to the auction"),
    (_J.CANCELLED, _J.RUNNING): ("AS", "requeued by the user: its units not done go back to the auction"),
}

_S = TypeVar("_S", UnitStatus, JobStatus)


def unit_transition(what: str, old: str, new: str) -> UnitStatus:
    """`new` as a UnitStatus if a unit may go from `old` to it; else TransitionError naming `what`
    (e.g. "job 'a1' unit 3") and both statuses."""
    return _check(UNIT_TRANSITIONS, UnitStatus, what, old, new)


def job_transition(what: str, old: str, new: str) -> JobStatus:
    """`new` as a JobStatus if a job may go from `old` to it; else TransitionError naming `what`."""
    return _check(JOB_TRANSITIONS, JobStatus, what, old, new)


def _check(table: dict[tuple[_S, _S], tuple[str, str]], kind: type[_S], what: str, old: str, new: str) -> _S:
    try:
        frm, to = kind(old), kind(new)
    except ValueError as exc:
        raise TransitionError(f"{what}: {exc}") from None
    if (frm, to) not in table:
        allowed = ", ".join(t for f, t in table if f == frm) or "nothing"
        raise TransitionError(f"{what}: {frm} -> {to} is not an allowed status change (from {frm}: {allowed})")
    return to
