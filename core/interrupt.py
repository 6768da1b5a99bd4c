"""Ctrl-C as a request to stop, not a crash: inside `first_ctrl_c_stops`, the first SIGINT sets an event and
calls the caller's `on_stop` (which ends the work in flight), so that what is done can be kept; a second
raises KeyboardInterrupt as usual. Cycles' and Arnold's progressive renders keep their image the same way.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any


@contextlib.contextmanager
def first_ctrl_c_stops(on_stop: Callable[[], None], message: str) -> Iterator[threading.Event]:
    """While inside, the first Ctrl-C prints `message`, sets the event yielded and calls `on_stop`; a second
    Ctrl-C raises KeyboardInterrupt. Outside the main thread no handler is set: the event is never set."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum: int, frame: Any) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        with contextlib.suppress(OSError):
            os.write(sys.stderr.fileno(), f"\n{message}\n".encode())
        on_stop()

    before = signal.signal(signal.SIGINT, handler)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, before)
