"""`quekaro up` in a real terminal (a pty) says where the page, the token, the home are and how to stop it;
`quekaro down` stops it, its processes gone; `watch` off a terminal prints plain lines as the job goes."""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from core.home import ADMIN_TOKEN, FARM_FILE, read_processes
from farm.client import FarmClient

REPO = Path(__file__).resolve().parent.parent
CBOX = REPO / "scenes" / "cbox.xml"


def quekaro(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quekaro", *args], capture_output=True, text=True, timeout=timeout)


def read_until(fd: int, text: str, timeout: float) -> str:
    """What the terminal shows until `text` appears (an AssertionError with it all after `timeout`)."""
    shown, deadline = b"", time.monotonic() + timeout
    while text not in shown.decode(errors="replace"):
        ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        if not ready:
            raise AssertionError(f"{text!r} not shown within {timeout:.0f} s:\n{shown.decode(errors='replace')}")
        try:
            shown += os.read(fd, 4096)
        except OSError:  # the process closed the terminal
            raise AssertionError(f"{text!r} never shown:\n{shown.decode(errors='replace')}") from None
    return shown.decode(errors="replace")


def wait_for_agent(home: Path, timeout: float = 180) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(not a["lost"] for a in FarmClient.from_home(home).agents()):
            return
        time.sleep(0.3)
    raise AssertionError("the farm's agent did not register")


@pytest.mark.slow
def test_up_says_where_everything_is_watch_prints_lines_and_down_stops_it(tmp_path: Path) -> None:
    home = (tmp_path / "farm").resolve()
    terminal, attached = os.openpty()
    up = subprocess.Popen([sys.executable, "-m", "quekaro", "up", "--agents", "1", "--threads", "1", "--home",
                           str(home)], stdin=attached, stdout=attached, stderr=attached, start_new_session=True)
    os.close(attached)
    try:
        shown = read_until(terminal, "or Ctrl-C here", 180)
        url = json.loads((home / FARM_FILE).read_text())["url"]
        assert f"web page: {url}/ui/ (log in with the admin token in {home / ADMIN_TOKEN})" in shown, shown
        assert f"home:     {home} (logs: quekaro logs --home {home})" in shown, shown
        assert f"stop:     quekaro down --home {home}, or Ctrl-C here" in shown, shown

        wait_for_agent(home)
        sent = quekaro("submit", str(CBOX), "-D", "res=16", "--spp", "2", "--units", "4", "--home", str(home))
        assert sent.returncode == 0, sent.stderr
        job_id = sent.stdout.strip()
        watched = quekaro("watch", job_id, "--home", str(home))  # stdout is a pipe, not a terminal
        assert watched.returncode == 0, watched.stderr
        lines = watched.stdout.splitlines()
        assert lines[0] == "job: cbox.xml, level off, 2 spp, 16x16, -D res=16", lines
        progress = [line for line in lines if line.startswith(f"{job_id} ")]
        assert progress and progress[-1] == f"{job_id} done: 4/4 units, agents busy 0", lines
        assert len(progress) == len(set(progress)) and "\x1b" not in watched.stdout  # a line a change, no bar

        pids = [p["pid"] for p in read_processes(home)]
        assert len(pids) == 3 and all(pids), pids
        down = quekaro("down", "--home", str(home))
        assert down.returncode == 0, down.stderr
        assert down.stdout == f"stopped the farm in {home}: xmpp-server, master, agent-0\n", down.stdout
        assert up.wait(60) == 0
        assert not [pid for pid in [up.pid, *pids] if Path(f"/proc/{pid}").exists()]
        again = quekaro("down", "--home", str(home))
        assert again.returncode == 0 and again.stdout == f"no farm is running in {home}\n"
        stale = quekaro("status", "--home", str(home))
        assert stale.returncode == 2 and f"no farm is running in {home} (farm.json is stale)" in stale.stderr
    finally:
        if up.poll() is None:
            up.terminate()
            up.wait(60)
        os.close(terminal)
