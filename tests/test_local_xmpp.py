"""A local farm's XMPP server (issue 62): Prosody on loopback, every account made before the farm names it,
registration closed. Another client cannot register a name the farm lists, nor log in as one of its agents
without the password the farm made, nor send as another account (the server stamps the sender); a machine
without Prosody is told which package to install."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_farm import DEFINES, SCENE, bundle_of, wait_job

from core.home import AGENTS_ALLOW
from farm.local import LocalFarm

REPO = Path(__file__).resolve().parent.parent


def _peer(farm: LocalFarm, jid: str, password: str, register: bool) -> list[dict]:
    """tests/xmpp_peer.py logging in (or registering in-band) as `jid`: its JSON events."""
    cmd = [sys.executable, "tests/xmpp_peer.py", "--jid", jid, "--password", password, "--server", "127.0.0.1",
           "--port", str(farm.server.port), "--connect-timeout", "15", *(["--register"] if register else []),
           "--to", "master@localhost", "--body", "{}", "send"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def _forged_from_arrives_as(farm: LocalFarm) -> str:
    """An account of the farm's server sends a message whose `from` says master@localhost: the bare JID
    that the receiver sees (Prosody stamps the sender's own; a server that did not would pass the lie)."""
    probe = [sys.executable, "tests/raw_xmpp.py", "--port", str(farm.server.port)]
    sink = subprocess.Popen([*probe, "sink", "--jid", "agent-sink@localhost", "--password",
                             farm.add_account("agent-sink"), "--linger", "8"],
                            cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert json.loads(sink.stdout.readline())["event"] == "online"
        forged = subprocess.run([*probe, "forge", "--jid", "agent-mallory@localhost", "--password",
                                 farm.add_account("agent-mallory"), "--to", "agent-sink@localhost", "--forged",
                                 "master@localhost/spoofed"], cwd=REPO, capture_output=True, text=True, timeout=60)
        assert '"event": "sent"' in forged.stdout, forged.stdout + forged.stderr[-2000:]
        got = [json.loads(line) for line in sink.communicate(timeout=60)[0].splitlines()]
    finally:
        sink.kill()
    (message,) = [e for e in got if e["event"] == "got"]
    return message["sender"].split("/")[0]


def test_up_without_prosody_names_the_package(tmp_path: Path) -> None:
    bare = tmp_path / "bin"
    bare.mkdir()
    os.symlink(sys.executable, bare / "python3")
    env = dict(os.environ, PATH=str(bare))
    assert shutil.which("prosody", path=str(bare)) is None
    done = subprocess.run([sys.executable, "-m", "quekaro", "up", "--agents", "1", "--home", str(tmp_path / "home")],
                          cwd=REPO, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 2, done.stderr
    assert "prosody is not installed (Debian package 'prosody')" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.slow
def test_no_one_registers_or_takes_over_a_name_the_farm_lists_and_its_job_completes(tmp_path: Path) -> None:
    with LocalFarm(tmp_path / "home", agents=1, threads=1) as farm:
        farm.wait_for_agents()
        listed = (farm.home / AGENTS_ALLOW).read_text().split()
        assert listed == ["agent-0@localhost"]
        accounts = farm.server.data_dir / "data" / "localhost" / "accounts"
        assert sorted(p.stem for p in accounts.iterdir()) == ["agent%2d0", "master"]  # made by the farm
        for jid, register in (("agent-0@localhost", True), ("agent-9@localhost", True),
                              ("agent-0@localhost", False)):
            events = _peer(farm, jid, "attacker-pw-1234", register)
            assert events and events[0]["event"] == "error", (jid, register, events)
        assert sorted(p.stem for p in accounts.iterdir()) == ["agent%2d0", "master"]
        assert _forged_from_arrives_as(farm) == "agent-mallory@localhost"
        client = farm.client()
        job_id = client.submit(bundle_of(SCENE, DEFINES), DEFINES, {"level": "off", "units": 4})
        assert wait_job(farm, job_id)["status"] == "done"
        assert {a["jid"] for a in client.agents()} == {"agent-0@localhost"}
