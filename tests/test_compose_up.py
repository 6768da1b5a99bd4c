"""`docker compose up` for real, with docs/compose.md's commands: the base image from Debian's packages
(deploy/base-image.sh), the farm's image built by Compose, ca, xmpp, master and three agents started with
`--scale agent=3`, a scene submitted from this host's CLI over HTTPS (the farm's CA and admin token copied
out of the master), its image statistically plain Mitsuba's (tests/render_check.py) as `quekaro render`'s
is, and `down -v` leaving no container, network or volume of the project.

Needs root, Docker and debootstrap (tests/docker_support.py: skipped with the reason, failed under .ci/run,
which sets QUEKARO_REQUIRE_DOCKER=1). A dockerd the test starts leaves the host's network as it was.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from docker_support import COMPOSE, docker_engine, require_docker
from render_check import by_name, compare, file_kind, file_quantum, reference_renders

from core.image.imageio import read_image_channels
from core.transport.xmpp_server import free_port

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "cbox.xml"
DEFINES = {"res": "40", "spp": "16"}
PROJECT = "quekaro-test"  # apart from a user's farm (the file's own name is `quekaro`)
AGENTS = 3

pytestmark = [pytest.mark.slow, pytest.mark.timeout(2400)]


def run(cmd: list[str], env: dict[str, str], timeout: float = 600, check: bool = True) -> str:
    done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    if check:
        assert done.returncode == 0, f"{' '.join(map(str, cmd))} exited {done.returncode}:\n" \
                                     f"{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def compose(env: dict[str, str], *args: str, timeout: float = 600, check: bool = True) -> str:
    return run([str(COMPOSE), "-p", PROJECT, *args], env, timeout, check)


def quekaro(env: dict[str, str], *args: str, timeout: float = 600) -> str:
    return run([sys.executable, "-m", "quekaro", *args], env, timeout)


def project_left(env: dict[str, str]) -> dict[str, list[str]]:
    """The project's containers, networks and volumes that Docker still has."""
    label = f"label=com.docker.compose.project={PROJECT}"
    return {kind: run(["docker", *cmd, "--quiet", "--filter", label], env).split()
            for kind, cmd in {"containers": ["ps", "-a"], "networks": ["network", "ls"],
                              "volumes": ["volume", "ls"]}.items()}


def wait_agents(env: dict[str, str], farm: list[str], timeout: float = 180) -> list[dict]:
    deadline = time.monotonic() + timeout
    while len(agents := json.loads(quekaro(env, "agents", "--json", *farm))) < AGENTS:
        assert time.monotonic() < deadline, f"{len(agents)} of {AGENTS} agents after {timeout:.0f} s:\n" \
                                            + compose(env, "logs", "--tail", "20", "agent", check=False)
        time.sleep(1)
    return agents


def mitsuba_verdict(image_file: Path, refs, names: tuple[str, ...]):
    """render_check's verdict on one image file against the reference renders, at the file's precision."""
    image, channels = read_image_channels(image_file)
    return compare(by_name(image, channels, names), refs, quantum=file_quantum(file_kind(image_file),
                                                                                 refs.mean(axis=0)))


@pytest.mark.alone  # the images' build and a farm in containers take every CPU
def test_compose_up_renders_a_job_submitted_from_the_host(tmp_path: Path) -> None:
    require_docker()
    port = free_port()
    env = {**os.environ, "QUEKARO_MASTER_PORT": str(port), "QUEKARO_HOME": str(tmp_path / "home"),
           # pip in the build verifies the package index as this machine's pip does (docs/compose.md)
           "QUEKARO_PIP_CA": os.environ.get("PIP_CERT", "/etc/ssl/certs/ca-certificates.crt")}
    defines = [w for k, v in DEFINES.items() for w in ("-D", f"{k}={v}")]
    with docker_engine(tmp_path / "dockerd.log"):
        run(["sh", "deploy/base-image.sh"], env, timeout=900)
        compose(env, "down", "-v")  # what a killed run left
        try:
            compose(env, "build", timeout=1800)
            compose(env, "up", "-d", "--scale", f"agent={AGENTS}", timeout=600)
            compose(env, "cp", "master:/home/farm/ca/ca.pem", str(tmp_path / "farm-ca.pem"))
            compose(env, "cp", "master:/home/farm/farm/admin.token", str(tmp_path / "admin.token"))
            farm = ["--url", f"https://127.0.0.1:{port}", "--ca-file", str(tmp_path / "farm-ca.pem"),
                    "--token-file", str(tmp_path / "admin.token")]
            agents = wait_agents(env, farm)
            assert sorted(a["jid"] for a in agents) == [f"agent-{i}@xmpp" for i in range(1, AGENTS + 1)]
            # As the README's compose section: the image in one command, named after the scene.
            quekaro(env, "submit", str(SCENE), *defines, "--opt", "off", "--wait", "-o", str(tmp_path / "out"), *farm)
            out = tmp_path / "out" / f"{SCENE.stem}.exr"
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{compose(env, 'logs', '--tail', '30', check=False)}") from None
        finally:
            compose(env, "down", "-v")
        assert project_left(env) == {"containers": [], "networks": [], "volumes": []}

    report = json.loads(out.with_suffix(".json").read_text())
    assert {u["agent"] for u in report["units"]} <= {a["jid"] for a in agents}  # the containers rendered it
    variant = report["effects"]["variant"]
    local = tmp_path / "local.exr"
    quekaro(env, "render", str(SCENE), *defines, "--opt", "off", "-o", str(local), "--no-progress")
    assert json.loads(local.with_suffix(".json").read_text())["effects"]["variant"] == variant
    refs, names = reference_renders(SCENE, variant, int(DEFINES["spp"]), defines=DEFINES, as_file=True)
    for image_file in (out, local):
        verdict = mitsuba_verdict(image_file, refs, names)
        assert verdict.passed, f"{image_file.name}: {verdict}"
