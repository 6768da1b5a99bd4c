"""Starting the render process that core.render.process runs units in: a plain subprocess joined to this
one by a socket pair, and a way to start one early. Standard library only, so that a command can start
it before its own imports: `quekaro render` does, and the child imports Mitsuba (~0.3 s) while the
command imports the rest.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from multiprocessing.connection import Connection
from pathlib import Path

from core.supervision import die_with_parent

Child = tuple[subprocess.Popen, Connection]

_early: Child | None = None


def spawn() -> Child:
    """A new render process and this side's end of its pipe; it imports Mitsuba and then says "ready"."""
    # A plain subprocess, not multiprocessing: spawn would re-import the caller's __main__, and fork
    # would copy a process that may hold Dr.Jit threads.
    ours, theirs = socket.socketpair()
    root = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path}
    code = f"import core.render.process as r; r._child_entry({theirs.fileno()})"
    proc = subprocess.Popen([sys.executable, "-c", code], pass_fds=(theirs.fileno(),), env=env,
                            stdin=subprocess.DEVNULL, preexec_fn=_child_setup)
    theirs.close()
    return proc, Connection(ours.detach())


def _child_setup() -> None:
    """In the child before it runs Python: it dies with its parent, and ignores SIGINT from its start (Python
    then keeps it ignored). A terminal's Ctrl-C reaches the whole process group: the parent decides."""
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def start_early() -> None:
    """Start a render process now, for the next `take` (a command, before its own imports)."""
    global _early
    if _early is None:
        _early = spawn()


def take() -> Child:
    """The render process started early, if it is still running, else a new one."""
    global _early
    early, _early = _early, None
    if early is not None and early[0].poll() is None:
        return early
    if early is not None:
        _end(early)
    return spawn()


def discard_early() -> None:
    """End a render process started early that nothing took (the command stopped before rendering)."""
    global _early
    early, _early = _early, None
    if early is not None:
        _end(early)


def _end(child: Child) -> None:
    proc, conn = child
    conn.close()
    if proc.poll() is None:
        proc.kill()  # it has done nothing yet but import: nothing to lose, no reason to wait for it
    proc.wait()
