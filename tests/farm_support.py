"""Helpers for tests that run farm processes by hand (Prosody deployments, the containers' roles)."""

from __future__ import annotations

import contextlib
import json
import re
import subprocess
import time
from pathlib import Path

from core.home import FARM_FILE
from farm.client import FarmClient


def log_tails(folder: Path, lines: int = 15) -> str:
    """The last lines of every log file in `folder`, for an assertion message."""
    return "\n".join(f"--- {p.name}\n" + "\n".join(p.read_text(errors="replace").splitlines()[-lines:])
                     for p in sorted(folder.glob("*.log")))


def log_time(line: str) -> float:
    """The wall-clock time a log line was written at, by the writer's clock (logging's asctime)."""
    stamp = re.match(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3})", line)
    assert stamp, line
    return time.mktime(time.strptime(stamp.group(1), "%Y-%m-%d %H:%M:%S")) + int(stamp.group(2)) / 1000


def wait_for_master_url(home: Path, procs: list[subprocess.Popen], logs: Path, timeout: float = 60.0) -> str:
    """The URL the master in `home` names in its farm.json once it is up (for its agents' --master-url)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert all(p.poll() is None for p in procs), f"a farm process exited early:\n{log_tails(logs)}"
        with contextlib.suppress(FileNotFoundError, ValueError, KeyError):
            return str(json.loads((home / FARM_FILE).read_text())["url"])
        time.sleep(0.2)
    raise AssertionError(f"the master did not come up:\n{log_tails(logs)}")


def wait_for_agents(home: Path, procs: list[subprocess.Popen], agents: int, logs: Path,
                    timeout: float = 120.0) -> FarmClient:
    """A client of the master in `home` once `agents` agents have registered; fails if a process dies."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert all(p.poll() is None for p in procs), f"a farm process exited early:\n{log_tails(logs)}"
        try:
            client = FarmClient.from_home(home)
            if sum(not a["lost"] for a in client.agents()) >= agents:
                return client
        except Exception:
            pass  # the master is not up yet
        time.sleep(0.3)
    raise AssertionError(f"farm did not come up:\n{log_tails(logs)}")
