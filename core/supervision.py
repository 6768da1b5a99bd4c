"""Keeping a local farm's processes alive, as systemd or supervisord would: restart a dead child with
backoff, give up on one that keeps crashing, and make every child die with its parent.

`RestartPolicy` is pure (times in, decisions out): a child that exits is restarted after a delay that
doubles with each recent restart (BACKOFF_S up to MAX_BACKOFF_S); one that has been restarted CRASH_LOOP
times within CRASH_WINDOW_S is marked failed and left down. `die_with_parent` is the `preexec_fn` that
asks Linux to send SIGTERM to a child when its parent dies, even by SIGKILL (PR_SET_PDEATHSIG), so that
killing `quekaro up` leaves no orphans. `log_tail` is what a child that exited said last.
"""

from __future__ import annotations

import ctypes
import signal
import sys
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

BACKOFF_S = 0.5
MAX_BACKOFF_S = 30.0
CRASH_LOOP = 5
CRASH_WINDOW_S = 60.0
_PR_SET_PDEATHSIG = 1


def log_tail(path: Path, lines: int = 1) -> str:
    """A child's log's last `lines` lines: what it said last (a port in use, a traceback's error)."""
    try:
        text = path.read_text(errors="replace").strip()
    except OSError:
        return "(no log)"
    return "\n".join(text.splitlines()[-lines:]) or "(nothing)"


def die_with_parent() -> None:
    """In a child, before exec: SIGTERM when the parent process dies (Linux; elsewhere nothing)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


@dataclass
class RestartPolicy:
    """When to restart one supervised child, and when to give up on it."""

    backoff_s: float = BACKOFF_S
    max_backoff_s: float = MAX_BACKOFF_S
    crash_loop: int = CRASH_LOOP
    window_s: float = CRASH_WINDOW_S
    restarts: deque[float] = field(default_factory=deque)  # those within the crash-loop window
    failed: bool = False
    count: int = 0  # restarts since the farm started (what status reports)

    def on_exit(self, now: float) -> float | None:
        """The child exited at `now`: the time to restart it, or None when it has crash-looped (failed)."""
        while self.restarts and now - self.restarts[0] > self.window_s:
            self.restarts.popleft()
        if len(self.restarts) >= self.crash_loop:
            self.failed = True
            return None
        delay = min(self.max_backoff_s, self.backoff_s * 2 ** len(self.restarts))
        self.restarts.append(now + delay)
        self.count += 1
        return now + delay
