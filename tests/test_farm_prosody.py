"""The multi-host set-up on one machine: a real Prosody (TLS required, registration closed, accounts made
with prosodyctl), the master and two agents as separate processes started with their own commands
(`quekaro master`, `quekaro agent`), verifying Prosody's certificate, and a job rendered through them."""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from farm_support import log_tails, wait_for_agents, wait_for_master_url
from prosody_support import needs_prosody

from core.image.imageio import read_image
from core.scene.bundle import make_bundle
from core.transport.xmpp_server import ProsodyServer
from farm.local import stop_processes

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "cbox.xml"

# CI sets QUEKARO_REQUIRE_PROSODY=1 so that a missing install fails instead of skipping.
pytestmark = [
    pytest.mark.slow,
    needs_prosody,
]


def _spawn(cmd: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen(cmd, cwd=REPO, stdout=log.open("ab"), stderr=subprocess.STDOUT)


def test_master_and_two_agents_render_through_prosody(tmp_path):
    server = ProsodyServer(tmp_path / "prosody", domain="localhost")
    passwords = server.register_all(["master", "agent-1", "agent-2"])
    ca = server.cert_dir / "localhost_cert.pem"
    home, logs = tmp_path / "master", tmp_path / "logs"
    logs.mkdir()
    procs: list[subprocess.Popen] = []
    with server:
        try:
            (tmp_path / "master.pw").write_text(passwords["master"])
            procs.append(_spawn([sys.executable, "-m", "quekaro", "master", "--home", str(home), "--jid",
                                 "master@localhost", "--password-file", str(tmp_path / "master.pw"),
                                 "--server", "127.0.0.1", "--port", str(server.port), "--ca-file", str(ca),
                                 "--http-port", "0", "--threads", "1"], logs / "master.log"))
            url = wait_for_master_url(home, procs, logs)
            for name in ("agent-1", "agent-2"):
                procs.append(_spawn([sys.executable, "-m", "quekaro", "agent", "--server", "127.0.0.1",
                                     "--port", str(server.port), "--jid", f"{name}@localhost",
                                     f"--password={passwords[name]}", "--master", "master@localhost",
                                     "--master-url", url,
                                     "--ca-file", str(ca), "--threads", "1",
                                     "--workdir", str(tmp_path / name)], logs / f"{name}.log"))
            client = wait_for_agents(home, procs, 2, logs)
            defines = {"res": "48", "spp": "16"}
            with tempfile.TemporaryDirectory() as tmp:
                bundle = make_bundle(SCENE, defines, Path(tmp) / "b.tar").path.read_bytes()
            job_id = client.submit(bundle, defines, {"level": "S", "units": 6})
            deadline = time.monotonic() + 240
            while (job := client.status(job_id))["status"] == "running" and time.monotonic() < deadline:
                time.sleep(0.3)
            assert job["status"] == "done", (job, log_tails(logs))
            out = client.result(job_id, tmp_path / "out.exr")
            image = read_image(out)
            assert image.shape == (48, 48, 3) and np.isfinite(image).all() and image.mean() > 0.05
            master_log = (logs / "master.log").read_text()
            assert "agent-1@localhost" in master_log or "agent-2@localhost" in master_log
        finally:
            stop_processes(procs)


def test_an_agent_given_the_wrong_ca_file_says_so_at_once(tmp_path):
    """It tried for 30 s, logged slixmpp's 'Invalid certificate trust chain' about 50 times and exited
    with 'no session', naming neither the certificate nor the CA file."""
    server = ProsodyServer(tmp_path / "prosody", domain="localhost")
    passwords = server.register_all(["agent-1"])
    subprocess.run([sys.executable, "-m", "quekaro", "ca", "init", "--dir", str(tmp_path / "other")], cwd=REPO,
                   check=True, capture_output=True)
    wrong = tmp_path / "other" / "ca.pem"
    with server:
        started = time.monotonic()
        done = subprocess.run([sys.executable, "-m", "quekaro", "agent", "--server", "127.0.0.1", "--port",
                               str(server.port), "--jid", "agent-1@localhost", f"--password={passwords['agent-1']}",
                               "--master", "master@localhost", "--master-url", "https://127.0.0.1:1",
                               "--ca-file", str(wrong), "--threads", "1",
                               "--workdir", str(tmp_path / "agent")], cwd=REPO, capture_output=True, text=True,
                              timeout=120)
    said = done.stdout + done.stderr
    assert done.returncode != 0 and f"its certificate is not trusted by the CA file {wrong}" in said, said[-3000:]
    assert time.monotonic() - started < 25, "it gave up only at the session timeout"
