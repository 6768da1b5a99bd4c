"""The farm across hosts, on one machine: Prosody and the master in one network namespace, each agent in
its own, all on one bridge (tests/netns_support.py), every link verified against the farm's own CA.

Set-up, as docs/hosts.md tells a user: `quekaro ca init`, `quekaro ca issue` for
Prosody (its XMPP domain) and for the master's HTTPS (its address), accounts with
deploy/prosody/make-accounts.sh, Prosody on the master's host (port 5222), `quekaro master` with
--tls-cert/--tls-key and an https --public-url (port 8765), and `quekaro agent --ca-file` on each agent
host. Cases: a job through three agent hosts; an agent's cable pulled mid-unit and plugged back; the
master's host cut off for 30 s; agents whose clocks are 10 minutes off (libfaketime); and the test
network itself under a FORWARD policy of DROP, as a Docker engine leaves it.

Needs root and iproute2 (skipped with the reason otherwise, failed instead under .ci/run, which sets
QUEKARO_REQUIRE_NETNS=1), Prosody and openssl (tests/prosody_support.py), and libfaketime for the clock.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from farm_support import log_tails, log_time
from netns_support import Network, leftovers, require_netns
from prosody_support import needs_prosody

from core.image.imageio import read_image
from core.scene.bundle import make_bundle
from core.transport.xmpp_server import ProsodyServer
from farm.client import FarmClient
from farm.local import stop_processes

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "cbox.xml"
DOMAIN = "farm.test"
XMPP_PORT = 5222
HTTP_PORT = 8765
LIBFAKETIME = next(iter(sorted(Path("/usr/lib").glob("*/faketime/libfaketimeMT.so.1"))), None)  # Debian faketime

pytestmark = [pytest.mark.slow, needs_prosody]


class NetnsProsody(ProsodyServer):
    """The repository's Prosody config, run inside a namespace, listening on that host's address, with a
    certificate issued by the farm's CA (`quekaro ca issue xmpp DOMAIN`)."""

    def __init__(self, data_dir: Path, netns: str, address: str, cert: Path, key: Path) -> None:
        super().__init__(data_dir, domain=DOMAIN, port=XMPP_PORT)
        self.host, self.netns, self.cert, self.key = address, netns, cert, key

    def env(self) -> dict[str, str]:
        return {**super().env(), "QUEKARO_XMPP_CERT": str(self.cert), "QUEKARO_XMPP_KEY": str(self.key)}

    def _prepare(self) -> None:
        (self.data_dir / "data").mkdir(parents=True, exist_ok=True)

    def _command(self) -> tuple[list[str], dict[str, str]]:
        cmd, env = super()._command()
        return ["ip", "netns", "exec", self.netns, *cmd], env


@dataclasses.dataclass
class Farm:
    net: Network
    root: Path
    home: Path
    logs: Path
    agents: list[str]  # agent host names: a1, a2, ...
    procs: dict[str, subprocess.Popen]
    client: FarmClient

    def jid(self, host: str) -> str:
        return f"agent-{host[1:]}@{DOMAIN}"

    def log(self, name: str) -> str:
        path = self.logs / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def tails(self) -> str:
        return log_tails(self.logs, 40)

    def check_alive(self) -> None:
        dead = {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}
        assert not dead, f"farm processes exited: {dead}\n{self.tails()}"

    def submit(self, res: int, spp: int, units: int) -> str:
        defines = {"res": str(res), "spp": str(spp)}
        with tempfile.TemporaryDirectory() as tmp:
            bundle = make_bundle(SCENE, defines, Path(tmp) / "b.tar").path.read_bytes()
        return self.client.submit(bundle, defines, {"level": "off", "units": units})

    def status(self, job_id: str) -> dict | None:
        """The job's status, or None while the master cannot be reached."""
        try:
            return self.client.status(job_id)
        except Exception:
            return None

    def wait_done(self, job_id: str, timeout: float) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.check_alive()
            job = self.status(job_id)
            if job is not None and job["status"] != "running":
                assert job["status"] == "done", (job, self.tails())
                return job
            time.sleep(0.3)
        raise AssertionError(f"job {job_id} not done within {timeout:.0f} s\n{self.tails()}")

    def attempts(self, job_id: str) -> list[sqlite3.Row]:
        """Every award of the job's units, from the master's store (read-only), oldest first."""
        with contextlib.closing(sqlite3.connect(f"file:{self.home / 'jobs.sqlite'}?mode=ro", uri=True,
                                                timeout=5)) as db:
            db.row_factory = sqlite3.Row
            return db.execute("SELECT * FROM attempts WHERE job_id = ? ORDER BY id", (job_id,)).fetchall()

    def results(self, job_id: str) -> list[sqlite3.Row]:
        with contextlib.closing(sqlite3.connect(f"file:{self.home / 'jobs.sqlite'}?mode=ro", uri=True,
                                                timeout=5)) as db:
            db.row_factory = sqlite3.Row
            return db.execute("SELECT * FROM results WHERE job_id = ? ORDER BY idx", (job_id,)).fetchall()

    def live_agents(self) -> set[str]:
        try:
            return {a["jid"] for a in self.client.agents() if not a["lost"]}
        except Exception:
            return set()

    def wait_agents(self, names: set[str], timeout: float) -> float:
        """Seconds until every agent in `names` is registered and not lost."""
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            self.check_alive()
            if names <= self.live_agents():
                return time.monotonic() - start
            time.sleep(0.2)
        raise AssertionError(f"agents {sorted(names - self.live_agents())} not live within {timeout:.0f} s\n"
                             + self.tails())

    def check_image(self, job_id: str, res: int) -> None:
        out = self.client.result(job_id, self.root / f"{job_id}.exr")
        image = read_image(out)
        assert image.shape == (res, res, 3) and np.isfinite(image).all() and image.mean() > 0.05


def quekaro(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "quekaro", *args], cwd=REPO, check=True, capture_output=True)


@contextlib.contextmanager
def farm_on_hosts(root: Path, agents: int = 3,
                  agent_env: dict[str, dict[str, str]] | None = None) -> Iterator[Farm]:
    """Prosody and the master on host `m`, agents on hosts a1..aN; everything ended and removed after."""
    require_netns()
    logs, home, ca = root / "logs", root / "master", root / "ca"
    logs.mkdir(parents=True)
    with contextlib.ExitStack() as stack:
        net = stack.enter_context(Network())
        master = net.add_host("m")
        names = [f"a{i}" for i in range(1, agents + 1)]
        for name in names:
            net.add_host(name)
        # The farm's CA and its two server certificates (the user's commands, as docs/hosts.md gives them).
        quekaro("ca", "init", "--dir", str(ca))
        quekaro("ca", "issue", "--dir", str(ca), "xmpp", DOMAIN)
        quekaro("ca", "issue", "--dir", str(ca), "master", master.address)
        server = NetnsProsody(root / "prosody", master.netns, master.address, ca / "xmpp.pem", ca / "xmpp.key")
        server._prepare()  # its data folder, where the accounts go
        subprocess.run(["sh", str(REPO / "deploy" / "prosody" / "make-accounts.sh"), DOMAIN, str(agents),
                        str(root / "passwords.txt")], env=server.env(), check=True, capture_output=True)
        passwords = dict(line.split() for line in (root / "passwords.txt").read_text().splitlines())
        for jid, password in passwords.items():
            (root / f"{jid.split('@')[0]}.pw").write_text(password)
        stack.enter_context(server)
        procs: dict[str, subprocess.Popen] = {}
        procs["master"] = net.spawn("m", [
            sys.executable, "-m", "quekaro", "master", "--home", str(home), "--jid", f"master@{DOMAIN}",
            "--password-file", str(root / "master.pw"), "--server", master.address, "--port", str(XMPP_PORT),
            "--ca-file", str(ca / "ca.pem"), "--http-host", master.address, "--http-port", str(HTTP_PORT),
            "--tls-cert", str(ca / "master.pem"), "--tls-key", str(ca / "master.key"),
            "--public-url", f"https://{master.address}:{HTTP_PORT}", "--threads", "1"], logs / "master.log",
            cwd=REPO)
        for name in names:
            env = {**os.environ, **(agent_env or {}).get(name, {})}
            procs[name] = net.spawn(name, [
                sys.executable, "-m", "quekaro", "agent", "--server", master.address, "--port", str(XMPP_PORT),
                "--jid", f"agent-{name[1:]}@{DOMAIN}", "--password-file", str(root / f"agent-{name[1:]}.pw"),
                "--master", f"master@{DOMAIN}", "--master-url", f"https://{master.address}:{HTTP_PORT}",
                "--ca-file", str(ca / "ca.pem"), "--threads", "1",
                "--workdir", str(root / name)], logs / f"{name}.log", env=env, cwd=REPO)
        stack.callback(stop_processes, list(procs.values()))  # before Prosody stops and the network goes
        client = _wait_for_master(home, procs, logs)
        farm = Farm(net, root, home, logs, names, procs, client)
        farm.wait_agents({farm.jid(n) for n in names}, timeout=120)
        yield farm
    assert not leftovers(net.prefix)


def _wait_for_master(home: Path, procs: dict[str, subprocess.Popen], logs: Path) -> FarmClient:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        assert all(p.poll() is None for p in procs.values()), f"a farm process exited:\n{log_tails(logs)}"
        with contextlib.suppress(Exception):
            client = dataclasses.replace(FarmClient.from_home(home), timeout=5.0)
            client.agents()
            return client
        time.sleep(0.3)
    raise AssertionError(f"the master did not come up:\n{log_tails(logs)}")


# ---- the cases ------------------------------------------------------------------------------------------


def test_the_bridge_works_whatever_the_forward_policy(tmp_path):
    """A Docker engine sets iptables' FORWARD policy to DROP, which bridged frames meet where br_netfilter
    is loaded: the test network's own ACCEPT rule keeps its hosts talking, and goes with the network. The
    policy is put back after."""
    require_netns()
    if shutil.which("iptables") is None:
        pytest.skip("no iptables here: nothing sets a FORWARD policy")
    policy = re.search(r"^-P FORWARD (\w+)$", subprocess.run(["iptables", "-S", "FORWARD"], capture_output=True,
                                                             text=True, check=True).stdout, re.MULTILINE)[1]
    with Network() as net:
        net.add_host("a")
        b = net.add_host("b")
        assert f"iptables:{net.bridge}" in leftovers(net.prefix)
        net.spawn("b", [sys.executable, "-m", "http.server", "--bind", b.address, "8000"], tmp_path / "b.log")
        deadline = time.monotonic() + 30
        while not net.can_connect("a", b.address, 8000) and time.monotonic() < deadline:
            time.sleep(0.2)
        subprocess.run(["iptables", "-P", "FORWARD", "DROP"], check=True)
        try:
            assert net.can_connect("a", b.address, 8000)
        finally:
            subprocess.run(["iptables", "-P", "FORWARD", policy], check=True)
    assert not leftovers(net.prefix)


def test_a_job_through_three_agent_hosts(tmp_path):
    """Agents in three namespaces render one job through Prosody (STARTTLS, its certificate checked
    against the farm's CA) and the master's HTTPS data plane; no agent can reach the master but through
    the bridge."""
    with farm_on_hosts(tmp_path) as farm:
        master = farm.net.hosts["m"]
        assert farm.net.can_connect("a1", master.address, XMPP_PORT)
        assert not farm.net.can_connect("a1", "127.0.0.1", XMPP_PORT)  # not the master's loopback
        started = time.monotonic()
        job_id = farm.submit(res=48, spp=16, units=9)
        farm.wait_done(job_id, timeout=120)
        took = time.monotonic() - started
        farm.check_image(job_id, 48)
        done = [a for a in farm.attempts(job_id) if a["outcome"] == "done"]
        assert len(done) == 9 == len(farm.results(job_id))
        assert {a["agent"] for a in done} == {farm.jid(n) for n in farm.agents}, done  # every host worked
        for name in farm.agents:
            assert re.search(rf"agent-{name[1:]}@{DOMAIN} connected to \S+ \(tls=True\)", farm.log(name))
        print(f"job of 9 units on 3 agent hosts: {took:.1f} s")


def _wait_for(what: str, predicate, timeout: float, farm: Farm, poll: float = 0.1):
    """The first true value of `predicate()` within `timeout` seconds (the farm's processes must live)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        farm.check_alive()
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"{what}: not within {timeout:.0f} s\n{farm.tails()}")


def test_agent_link_down_mid_unit_and_back(tmp_path):
    """An agent's cable is pulled while it renders: its units go back to auction after the heartbeat
    timeout and are rendered elsewhere; plugged back, it rejoins and is given work, and the tile it
    finished for its re-awarded unit is refused (403): the store keeps one result per unit."""
    with farm_on_hosts(tmp_path) as farm:
        victim = farm.jid("a1")
        job_id = farm.submit(res=64, spp=8192, units=12)

        def victim_rendering():
            return next((a for a in farm.attempts(job_id) if a["agent"] == victim and a["outcome"] == "running"),
                        None)

        first = _wait_for("a unit awarded to agent-1", victim_rendering, 60, farm, poll=0.05)
        time.sleep(0.5)  # the award has arrived, its render runs
        farm.net.link_down("a1")
        down = time.time()
        requeued = _wait_for("agent-1's unit back to auction", lambda: next(
            (a for a in farm.attempts(job_id)
             if a["token_sha256"] == first["token_sha256"] and a["outcome"] == "requeued"),
            None), 40, farm)
        lost_after = requeued["finished"] - down
        reawarded = _wait_for("agent-1's unit awarded again", lambda: next(
            (a for a in farm.attempts(job_id) if a["idx"] == first["idx"] and a["id"] > first["id"]), None),
            30, farm)
        # Plugged back at once: agent-1 finished that unit meanwhile (its render takes a few seconds) and is
        # still trying to upload the tile (5 tries over ~20 s: its award would be void by then anyway).
        farm.net.link_up("a1")
        up = time.time()
        rejoin_s = farm.wait_agents({victim}, timeout=90)
        sender = re.escape(farm.net.hosts["a1"].address)  # the refusal names who sent the tile
        refusal = rf"PUT /jobs/{job_id}/units/{first['idx']}/tile from {sender}:\d+ refused \(403\)"
        _wait_for("agent-1's late tile refused", lambda: re.search(refusal, farm.log("master")), 30, farm)
        farm.wait_done(job_id, timeout=120)
        # Work after the cable is back: a second job, so that there is some whatever the first one left.
        second = farm.submit(res=48, spp=64, units=9)
        farm.wait_done(second, timeout=120)
        attempts = farm.attempts(job_id) + farm.attempts(second)
        print(f"\nlost after {lost_after:.1f} s; re-awarded to {reawarded['agent']}; rejoined {rejoin_s:.1f} s "
              f"after the cable; attempts: {[(a['idx'], a['agent'][6], a['outcome']) for a in attempts]}")
        assert 10 <= lost_after <= 25, lost_after  # the master's heartbeat timeout (15 s) after its last beat
        assert reawarded["agent"] != victim
        # One result per unit, the re-awarded unit's from its new agent.
        results = {r["idx"]: r for r in farm.results(job_id)}
        assert sorted(results) == list(range(12))
        assert f'"agent": "{reawarded["agent"]}"' in results[first["idx"]]["params"].replace("'", '"')
        done = [a for a in farm.attempts(job_id) if a["outcome"] == "done"]
        assert len(done) == 12 and len({a["idx"] for a in done}) == 12
        # Once back, agent-1 rendered again.
        assert any(a["agent"] == victim and a["outcome"] == "done" and a["started"] > up for a in attempts), attempts
        farm.check_image(job_id, 64)


def test_master_host_unreachable_for_30_s(tmp_path):
    """The master's host (Prosody and the master) is cut off for 30 s in the middle of a job: the master
    gives the silent agents' units back to auction, the agents get their sessions back by themselves (no
    process restarted), and the job completes."""
    with farm_on_hosts(tmp_path) as farm:
        job_id = farm.submit(res=64, spp=8192, units=12)
        _wait_for("a unit done", lambda: any(a["outcome"] == "done" for a in farm.attempts(job_id)), 60, farm)
        pids = {name: proc.pid for name, proc in farm.procs.items()}
        farm.net.link_down("m")
        time.sleep(30)
        farm.net.link_up("m")
        rejoin_s = farm.wait_agents({farm.jid(n) for n in farm.agents}, timeout=120)
        farm.wait_done(job_id, timeout=180)
        master_log = farm.log("master")
        print(f"\nagents live again {rejoin_s:.1f} s after the master's host came back; "
              + "; ".join(f"{n}: {farm.log(n).count('back online')} reconnect(s)" for n in farm.agents))
        assert {name: proc.pid for name, proc in farm.procs.items() if proc.poll() is None} == pids
        assert rejoin_s < 10, rejoin_s  # the keepalive noticed the dead link; the reconnect loop polls the port
        for name in farm.agents:
            assert "dropping the connection" in farm.log(name) and "back online" in farm.log(name), farm.tails()
        for name in farm.agents:  # every agent went silent for the master, and came back
            assert f"agent {farm.jid(name)}: lost" in master_log, farm.tails()
            assert f"agent {farm.jid(name)}: back" in master_log, farm.tails()
        assert any(a["outcome"] == "requeued" for a in farm.attempts(job_id))
        assert len(farm.results(job_id)) == 12
        farm.check_image(job_id, 64)


def test_agents_with_clocks_10_minutes_off(tmp_path):
    """Agents whose clocks are 10 minutes ahead and 10 minutes behind (libfaketime; the one behind keeps a
    true monotonic clock, the one ahead has it shifted too) log in over TLS, verify the master's HTTPS and
    render their share: award tokens, deadlines and heartbeat timeouts are the master's, on its own clock,
    and the farm's certificates are valid from a day before they were issued."""
    if LIBFAKETIME is None:
        if os.environ.get("QUEKARO_REQUIRE_NETNS"):
            pytest.fail("multi-host tests required (QUEKARO_REQUIRE_NETNS) but libfaketime is missing")
        pytest.skip("libfaketime missing (Debian package faketime)")
    skew = {"a1": 600.0, "a2": -600.0}
    env = {"a1": {"LD_PRELOAD": str(LIBFAKETIME), "FAKETIME": "+10m"},
           "a2": {"LD_PRELOAD": str(LIBFAKETIME), "FAKETIME": "-10m", "FAKETIME_DONT_FAKE_MONOTONIC": "1"}}
    with farm_on_hosts(tmp_path, agent_env=env) as farm:
        job_id = farm.submit(res=48, spp=256, units=12)
        farm.wait_done(job_id, timeout=120)
        farm.check_image(job_id, 48)
        done = [a for a in farm.attempts(job_id) if a["outcome"] == "done"]
        assert len(done) == 12 == len(farm.results(job_id))
        master_log = farm.log("master").splitlines()
        for name, offset in skew.items():
            jid = farm.jid(name)
            assert any(a["agent"] == jid for a in done), (name, done)
            # Its clock really is off: its login, by its own log, against the master's record of it.
            own = next(line for line in farm.log(name).splitlines() if f"{jid} connected to" in line)
            seen = next(line for line in master_log if f"agent {jid}: joined" in line)
            assert abs(log_time(own) - log_time(seen) - offset) < 30, (own, seen)
        print(f"\nunits done by agent: { {n: sum(a['agent'] == farm.jid(n) for a in done) for n in farm.agents} }")
