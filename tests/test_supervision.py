"""Supervision of the local farm: the restart policy alone, then a real `quekaro up` whose agent is killed
(restarted, the job completes) and which is itself killed with SIGKILL (no process of the farm survives)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_farm import SCENE, _children, assert_all_gone, bundle_of

from core.supervision import RestartPolicy, log_tail
from farm.client import FarmClient

REPO = Path(__file__).resolve().parent.parent


def test_what_a_child_said_last_is_its_logs_last_lines(tmp_path: Path) -> None:
    log = tmp_path / "child.log"
    assert log_tail(log) == "(no log)"
    log.write_text("")
    assert log_tail(log) == "(nothing)"
    log.write_bytes(b"starting\nbound 127.0.0.1:5222\nOSError: [Errno 98] address in use \xff\n\n")
    assert log_tail(log) == "OSError: [Errno 98] address in use \ufffd"  # the last line said, not a blank one
    assert log_tail(log, 2) == "bound 127.0.0.1:5222\nOSError: [Errno 98] address in use \ufffd"
    assert log_tail(log, 9).startswith("starting\n")


def test_backoff_doubles_and_a_crash_loop_is_given_up():
    policy = RestartPolicy(backoff_s=0.5, max_backoff_s=4.0, crash_loop=5, window_s=60.0)
    times = [policy.on_exit(100.0 + i) for i in range(5)]
    assert [t - (100.0 + i) for i, t in enumerate(times)] == [0.5, 1.0, 2.0, 4.0, 4.0]
    assert policy.on_exit(106.0) is None and policy.failed  # the sixth exit within a minute


def test_restarts_spread_out_in_time_never_fail():
    policy = RestartPolicy(crash_loop=5, window_s=60.0)
    for i in range(20):
        assert policy.on_exit(i * 61.0) is not None
    assert not policy.failed and policy.count == 20  # every restart since the start, as status reports them


def _bound_once_free(port: int, timeout: float = 10.0):
    """A listener on 127.0.0.1:port once the killed server's processes have let it go (not at once)."""
    import socket

    deadline = time.monotonic() + timeout
    while True:
        try:
            return socket.create_server(("127.0.0.1", port))
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def test_an_xmpp_server_that_cannot_come_back_ends_the_farm_naming_why(tmp_path):
    """Its port taken while it was down: it was restarted 5 times, marked failed, and the farm went on with
    nothing able to reach anyone (jobs waited for ever); processes.json said it was running meanwhile."""
    from core.errors import QuekaroError
    from core.transport.xmpp_server import XmppServerError
    from farm.local import LocalFarm

    home = tmp_path / "farm"
    with LocalFarm(home, agents=1, threads=1) as farm:  # unsupervised: the rounds are run here, in order
        port, now = farm.server.port, time.monotonic()
        farm.server.kill()
        farm.supervise(now)
        assert _states(home)["xmpp-server"] | {"pid": None} == {
            "name": "xmpp-server", "pid": None, "state": "restarting", "restarts": 1}
        with _bound_once_free(port):
            for _ in range(200):
                now += 1.0
                with contextlib.suppress(XmppServerError):
                    farm.supervise(now)
                if _states(home)["xmpp-server"]["state"] == "failed":
                    break
            assert _states(home)["xmpp-server"]["state"] == "failed"
            with pytest.raises(QuekaroError, match=f"XMPP server could not be restarted: port 127.0.0.1:{port} is "
                                                   "already in use"):
                farm.check_alive()


def _states(home: Path) -> dict[str, dict]:
    try:
        return {p["name"]: p for p in json.loads((home / "processes.json").read_text())["processes"]}
    except (OSError, ValueError):
        return {}


def _wait_for(predicate, timeout: float, what: str, up: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert up.poll() is None, f"quekaro up exited while waiting for {what}"
        if predicate():
            return
        time.sleep(0.3)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow
def test_a_killed_agent_is_restarted_and_a_killed_farm_leaves_no_orphans(tmp_path):
    home = tmp_path / "farm"
    up = subprocess.Popen([sys.executable, "-m", "quekaro", "up", "--agents", "2", "--threads", "1",
                           "--home", str(home)], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait_for(lambda: len(_states(home)) == 4 and (home / "farm.json").exists(), 120, "the farm", up)
        client = FarmClient.from_home(home)
        _wait_for(lambda: sum(not a["lost"] for a in client.agents()) >= 2, 120, "two agents", up)
        victim = _states(home)["agent-0"]["pid"]
        os.kill(victim, signal.SIGKILL)
        _wait_for(lambda: _states(home)["agent-0"]["restarts"] == 1 and _states(home)["agent-0"]["pid"] != victim
                  and _states(home)["agent-0"]["state"] == "running", 30, "the agent's restart", up)
        assert _states(home)["master"]["state"] == "running"
        status = subprocess.run([sys.executable, "-m", "quekaro", "status", "--home", str(home)], cwd=REPO,
                                capture_output=True, text=True, timeout=60)
        assert "process agent-0: running (1 restarts)" in status.stdout, status
        assert "no jobs" in status.stdout  # not an empty output
        defines = {"res": "48", "spp": "8"}
        job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "off", "units": 4})
        assert client.wait(job_id, 240, poll=0.3)["status"] == "done"
        farm = _children(up.pid)
        assert len(farm) >= 4, farm  # XMPP server (+ workers), master, two agents (+ render processes)
        up.kill()  # SIGKILL: quekaro up cannot clean up; its children must go by themselves
        up.wait(timeout=10)
        assert_all_gone(farm, 30, "a killed quekaro up")
    finally:
        if up.poll() is None:
            up.kill()


@pytest.mark.slow
def test_a_master_restarted_three_times_on_the_same_server_hears_its_agents(tmp_path):
    """Stopped cleanly (SIGTERM) and started again while the XMPP server and the agents run (with the
    embedded pyjabber server it was deaf: a stale resource outranked its new one). The agents stay connected,
    so the restarted master hears heartbeats first; it asks each for a Register and learns its speed."""
    from farm.local import LocalFarm

    home = tmp_path / "farm"
    with LocalFarm(home, agents=1, threads=1) as farm:
        farm.wait_for_agents()
        speed = farm.client().agents()[0]["speed"]
        assert speed != 1.0  # measured (a speed of exactly 1.0 would make the check below say nothing)
        master = farm.children[0]
        url = farm.url  # the port the first master bound: a restart binds it again (uploads name it)
        for _ in range(3):
            master.proc.terminate()
            master.proc.wait(timeout=30)
            (home / "farm.json").unlink()
            farm._spawn(master)
            farm._wait_for_master()
            client = farm.client()
            assert client.url == farm.url == url
            deadline = time.monotonic() + 20
            while [a["speed"] for a in client.agents() if not a["lost"]] != [speed]:
                assert time.monotonic() < deadline, f"the restarted master hears no agent, or not its speed: " \
                                                    f"{client.agents()}"
                time.sleep(0.3)
        defines = {"res": "32", "spp": "4"}
        job_id = client.submit(bundle_of(SCENE, defines), defines, {"level": "off", "units": 2})
        assert client.wait(job_id, 120, poll=0.3)["status"] == "done"


def test_a_process_listed_running_whose_pid_is_gone_or_a_zombie_reads_dead(tmp_path):
    """processes.json is the supervisor's last word; a full disk may stop its writing, so a reader checks
    each running pid: gone or a zombie (exited, not yet reaped) reads "dead", and the rest as written."""
    from core.home import PROCESSES_FILE, read_processes

    gone = subprocess.Popen(["true"])
    gone.wait()
    zombie = subprocess.Popen(["true"])
    deadline = time.monotonic() + 10
    while Path(f"/proc/{zombie.pid}/stat").read_text().rsplit(")", 1)[-1].split()[0] != "Z":
        assert time.monotonic() < deadline
        time.sleep(0.01)
    listed = [{"name": "master", "state": "running", "pid": os.getpid()},
              {"name": "agent-0", "state": "running", "pid": gone.pid},
              {"name": "agent-1", "state": "running", "pid": zombie.pid},
              {"name": "agent-2", "state": "restarting", "pid": None}]
    (tmp_path / PROCESSES_FILE).write_text(json.dumps({"processes": listed}))
    try:
        states = {p["name"]: p["state"] for p in read_processes(tmp_path)}
    finally:
        zombie.wait()
    assert states == {"master": "running", "agent-0": "dead", "agent-1": "dead", "agent-2": "restarting"}
    assert read_processes(tmp_path / "none") == []


@pytest.mark.slow
def test_a_dead_agent_is_restarted_with_the_disk_full_and_never_read_as_running_meanwhile(tmp_path):
    """A restart writes nothing (the agent's account was made at the farm's start): with its home's disk
    full, a killed agent comes back, and processes.json, which cannot be written, never reads as running
    the process that died."""
    from disk_support import fill, small_tmpfs

    from core.home import read_processes
    from farm.local import LocalFarm

    with small_tmpfs(tmp_path / "small", "300m") as disk, LocalFarm(disk / "home", agents=1, threads=1) as farm:
        farm.wait_for_agents()
        (agent,) = [c for c in farm.children if c.name == "agent-0"]
        dead = agent.proc.pid
        fill(disk, 0)
        agent.proc.kill()
        agent.proc.wait()
        now = time.monotonic()
        for step in range(40):  # the supervisor's rounds; each fails to write processes.json
            with contextlib.suppress(OSError):
                farm.supervise(now + step)
            if agent.proc.pid != dead:
                break
        assert agent.proc.pid != dead and agent.state == "running"
        time.sleep(3)
        assert agent.proc.poll() is None, log_tail(disk / "home" / "logs" / "agent-0.log")
        states = {p["name"]: (p["state"], p["pid"]) for p in read_processes(disk / "home")}
        assert states["agent-0"] in {("dead", dead), ("restarting", None)}, states
