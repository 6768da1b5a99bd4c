"""The containers' roles without Docker: deploy/entrypoint.sh started as `xmpp`, `master` and two
`agent`s, configured only by the environment docker-compose.yml gives them (in-band registration
allowed from the farm's network, here loopback), rendering a job. No Docker engine runs on this
machine, so this is as close to `docker compose up --scale agent=2` as the tests can get."""

from __future__ import annotations

import os
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

pytestmark = [
    pytest.mark.slow,
    needs_prosody,
]


def test_entrypoint_roles_render_a_job(tmp_path):
    xmpp_port, http_port = free_port(), free_port()
    bin_dir = str(Path(os.sys.executable).parent)
    base = dict(os.environ, PATH=f"{bin_dir}:{os.environ['PATH']}", QUEKARO_XMPP_DOMAIN="localhost",
                QUEKARO_XMPP_SERVER="127.0.0.1", QUEKARO_XMPP_PORT=str(xmpp_port),
                QUEKARO_XMPP_INTERFACE="127.0.0.1", QUEKARO_REGISTRATION_ALLOWLIST="127.0.0.0/8",
                QUEKARO_THREADS="1")
    procs = []

    def role(name: str, **env: str) -> None:
        home = tmp_path / name
        home.mkdir()
        log = (tmp_path / f"{name}.log").open("ab")
        procs.append(subprocess.Popen([str(ENTRY), *name.split("-")[:1]], cwd=tmp_path, stdout=log,
                                      stderr=subprocess.STDOUT, env={**base, "HOME": str(home), **env}))

    try:
        role("xmpp")
        deadline = time.monotonic() + 30
        while not port_accepts("127.0.0.1", xmpp_port) and time.monotonic() < deadline:
            time.sleep(0.2)
        role("master", QUEKARO_XMPP_PASSWORD="m-pw", QUEKARO_HTTP_HOST="127.0.0.1",
             QUEKARO_HTTP_PORT=str(http_port), QUEKARO_PUBLIC_URL=f"http://127.0.0.1:{http_port}",
             QUEKARO_HOME=str(tmp_path / "farm"))
        for i in (1, 2):
            role(f"agent-{i}", QUEKARO_XMPP_PASSWORD="a-pw", QUEKARO_AGENT_NAME=f"box{i}",
                 QUEKARO_PUBLIC_URL=f"http://127.0.0.1:{http_port}")  # the master's URL, as the compose file gives
        client = wait_for_agents(tmp_path / "farm", procs, 2, tmp_path)
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
    finally:
        stop_processes(list(reversed(procs)))
