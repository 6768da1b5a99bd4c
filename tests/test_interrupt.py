"""core.interrupt with real SIGINTs sent to this process: the first asks to stop, the second quits."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from core.interrupt import first_ctrl_c_stops


def _sigint_and_wait() -> None:
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.2)  # the handler runs in the main thread between bytecodes


def test_the_first_ctrl_c_calls_on_stop_and_the_second_raises(capfd):
    calls = []
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt), first_ctrl_c_stops(lambda: calls.append(1), "stopping now") as stop:
        _sigint_and_wait()
        assert stop.is_set() and calls == [1]
        assert "stopping now" in capfd.readouterr().err
        _sigint_and_wait()
    assert calls == [1] and signal.getsignal(signal.SIGINT) is before  # restored on the way out


def test_outside_the_main_thread_nothing_is_set():
    seen = []

    def inside() -> None:
        with first_ctrl_c_stops(lambda: seen.append("stopped"), "-") as stop:
            seen.append(stop.is_set())
            seen.append(signal.getsignal(signal.SIGINT))

    before = signal.getsignal(signal.SIGINT)
    thread = threading.Thread(target=inside)
    thread.start()
    thread.join()
    assert seen == [False, before]
