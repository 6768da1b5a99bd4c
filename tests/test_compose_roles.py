"""The containers' roles without Docker: deploy/entrypoint.sh started as `xmpp`, `master` and two
`agent`s, configured only by the environment docker-compose.yml gives them, rendering a job. No Docker
engine runs on this machine, so this is as close to `docker compose up --scale agent=2` as the tests can get.

Registration is closed (issue 62): the xmpp role makes every account before Prosody listens, each with its
own random password in the secrets folder (the compose file's farm-secrets volume, here in tmp); each agent
claims a free account of the pool, and one agent more than the pool exits saying how to make it larger."""

from __future__ import annotations

import os
import signal
import socket
import ssl
import stat
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
from farm_support import log_tails, wait_for_agents
from prosody_support import needs_prosody

from core.scene.bundle import make_bundle
from core.transport.xmpp_server import free_port, port_accepts
from farm.local import stop_processes

REPO = Path(__file__).resolve().parent.parent
ENTRY = REPO / "deploy" / "entrypoint.sh"
DOMAIN = "localhost"

pytestmark = [
    pytest.mark.slow,
    needs_prosody,
]


def _read_until(sock: socket.socket, *marks: bytes, timeout: float = 10.0) -> str:
    data = b""
    deadline = time.monotonic() + timeout
    while not any(mark in data for mark in marks) and time.monotonic() < deadline:
        sock.settimeout(max(0.1, deadline - time.monotonic()))
        try:
            chunk = sock.recv(65536)
        except TimeoutError:
            break
        if not chunk:
            break
        data += chunk
    return data.decode(errors="replace")


def in_band_registration(port: int, user: str, password: str) -> tuple[str, str]:
    """What any client on the network can try (XEP-0077), as a bare stream: after STARTTLS, before any
    login, ask to register user@DOMAIN. Returns the server's stream features and its answer."""
    header = (f"<?xml version='1.0'?><stream:stream to='{DOMAIN}' xmlns='jabber:client' "
              "xmlns:stream='http://etherx.jabber.org/streams' version='1.0'>").encode()
    with socket.create_connection(("127.0.0.1", port), 10) as raw:
        raw.sendall(header)
        assert "starttls" in _read_until(raw, b"</stream:features>")
        raw.sendall(b"<starttls xmlns='urn:ietf:params:xml:ns:xmpp-tls'/>")
        assert "<proceed" in _read_until(raw, b"<proceed", b"<failure")
        context = ssl.create_default_context()
        context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
        with context.wrap_socket(raw, server_hostname=DOMAIN) as tls:
            tls.sendall(header)
            features = _read_until(tls, b"</stream:features>")
            tls.sendall(f"<iq type='set' id='reg1'><query xmlns='jabber:iq:register'><username>{user}</username>"
                        f"<password>{password}</password></query></iq>".encode())
            return features, _read_until(tls, b"</iq>", b"<stream:error")


def _wait_for(predicate, what: str, logs: Path, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"{what} within {timeout:.0f} s:\n{log_tails(logs)}"
        time.sleep(0.2)


def test_entrypoint_roles_render_a_job(tmp_path):
    xmpp_port, http_port = free_port(), free_port()
    bin_dir = str(Path(os.sys.executable).parent)
    secrets = tmp_path / "secrets"  # the farm-secrets volume
    base = {k: v for k, v in os.environ.items() if k != "QUEKARO_XMPP_PASSWORD"}  # from the secrets only
    base.update(PATH=f"{bin_dir}:{os.environ['PATH']}", QUEKARO_XMPP_DOMAIN=DOMAIN,
                QUEKARO_XMPP_SERVER="127.0.0.1", QUEKARO_XMPP_PORT=str(xmpp_port),
                QUEKARO_XMPP_INTERFACE="127.0.0.1", QUEKARO_SECRETS_DIR=str(secrets), QUEKARO_THREADS="1")
    master_url = f"http://127.0.0.1:{http_port}"  # the master's URL, as the compose file gives it
    procs: list[subprocess.Popen] = []
    others: list[subprocess.Popen] = []  # started and ended by the test: not watched by wait_for_agents

    def role(name: str, keep: bool = True, **env: str) -> subprocess.Popen:
        home = tmp_path / name
        home.mkdir(exist_ok=True)
        log = (tmp_path / f"{name}.log").open("ab")
        proc = subprocess.Popen([str(ENTRY), name.split("-")[0]], cwd=tmp_path, stdout=log,
                                stderr=subprocess.STDOUT, env={**base, "HOME": str(home), **env})
        (procs if keep else others).append(proc)
        return proc

    def agent(name: str, keep: bool = True) -> subprocess.Popen:
        return role(f"agent-{name}", keep, QUEKARO_AGENT_NAME=name, QUEKARO_PUBLIC_URL=master_url)

    def claims() -> dict[str, str]:
        """account -> the agent holding (or last holding) it"""
        return {p.name: p.read_text().strip() for p in (secrets / "claims").iterdir()}

    accounts = tmp_path / "xmpp" / "prosody" / "data" / DOMAIN / "accounts"
    try:
        xmpp = role("xmpp", QUEKARO_AGENT_SLOTS="2")
        _wait_for(lambda: port_accepts("127.0.0.1", xmpp_port), "Prosody listening", tmp_path)
        # Every account exists before anything names it, each with its own password, private to its user.
        assert sorted(p.name for p in accounts.iterdir()) == ["agent%2d1.dat", "agent%2d2.dat", "master.dat"]
        files = sorted(secrets.glob("*.password"))
        assert [p.name for p in files] == ["agent-1.password", "agent-2.password", "master.password"]
        assert stat.S_IMODE(secrets.stat().st_mode) == 0o700
        assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in files)
        passwords = {p.name: p.read_text().strip() for p in files}
        assert len(set(passwords.values())) == 3 and all(len(pw) >= 16 for pw in passwords.values())
        # Registration is closed: not offered, and refused when asked for all the same (a new name, a
        # name of the pool).
        for user in ("agent-3", "agent-1"):
            features, answer = in_band_registration(xmpp_port, user, "attacker-pw-1234")
            assert "<mechanisms" in features and "iq-register" not in features, features
            assert "type='error'" in answer and "reg1" in answer, answer
        assert sorted(p.name for p in accounts.iterdir()) == ["agent%2d1.dat", "agent%2d2.dat", "master.dat"]

        role("master", QUEKARO_HTTP_HOST="127.0.0.1", QUEKARO_HTTP_PORT=str(http_port),
             QUEKARO_PUBLIC_URL=master_url, QUEKARO_HOME=str(tmp_path / "farm"))
        box1, box2 = agent("box1"), agent("box2")
        client = wait_for_agents(tmp_path / "farm", procs, 2, tmp_path)
        # Each agent under its own account of the pool, and the master sees those two.
        held = claims()
        assert sorted(held) == ["agent-1", "agent-2"] and sorted(held.values()) == ["box1", "box2"], held
        assert {a["jid"] for a in client.agents()} == {"agent-1@localhost", "agent-2@localhost"}
        # One agent more than the pool: a clear one-line refusal, nothing taken.
        box3 = agent("box3", keep=False)
        assert box3.wait(timeout=30) == 1
        said = (tmp_path / "agent-box3.log").read_text().strip()
        assert len(said.splitlines()) == 1 and "QUEKARO_AGENT_SLOTS" in said and "are taken" in said, said
        assert claims() == held

        defines = {"res": "32", "spp": "8"}
        with tempfile.TemporaryDirectory() as tmp:
            bundle = make_bundle(REPO / "scenes" / "cbox.xml", defines, Path(tmp) / "b.tar").path.read_bytes()
        job_id = client.submit(bundle, defines, {"level": "N", "units": 4})
        deadline = time.monotonic() + 180
        while (job := client.status(job_id))["status"] == "running" and time.monotonic() < deadline:
            time.sleep(0.3)
        assert job["status"] == "done", (job, log_tails(tmp_path))
        # docker-compose.yml's healthchecks, run as a container would, against the running roles.
        master_env = {**base, "QUEKARO_HTTP_PORT": str(http_port)}
        for name in ("xmpp", "master"):
            assert subprocess.run([str(ENTRY), "health", name], env=master_env, timeout=30).returncode == 0
        dead = {**base, "QUEKARO_HTTP_PORT": str(free_port()), "QUEKARO_XMPP_PORT": str(free_port())}
        for name in ("xmpp", "master"):
            assert subprocess.run([str(ENTRY), "health", name], env=dead, capture_output=True,
                                  timeout=30).returncode != 0

        # Agents killed outright leave no stale claim (the kernel drops a dead process's lock), and an
        # agent restarted under its name takes its own account back, agent-2, though agent-1 is free too.
        for proc in (box1, box2):
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=30)
            procs.remove(proc)
        name = held["agent-2"]
        log = tmp_path / f"agent-{name}.log"
        again = agent(name, keep=False)
        _wait_for(lambda: "logs in as" in log.read_text(), f"{name} restarted", tmp_path)
        assert f"agent: {name} logs in as agent-2@localhost" in log.read_text()
        assert claims() == held
        stop_processes([again])

        # The xmpp role restarted (here with a smaller pool): the passwords kept, the surplus account gone.
        stop_processes([xmpp])
        procs.remove(xmpp)
        role("xmpp", QUEKARO_AGENT_SLOTS="1")
        _wait_for(lambda: port_accepts("127.0.0.1", xmpp_port), "Prosody listening again", tmp_path)
        assert {p.name: p.read_text().strip() for p in secrets.glob("*.password")} == {
            k: v for k, v in passwords.items() if k != "agent-2.password"}
        assert sorted(p.name for p in accounts.iterdir()) == ["agent%2d1.dat", "master.dat"]
    finally:
        stop_processes(list(reversed(procs + others)))
