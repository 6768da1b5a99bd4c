"""A whole farm on one machine (`quekaro up`, `quekaro demo`): SPADE's embedded XMPP server, the master
and N render agents, each in its own process with its own Dr.Jit thread count and a unique JID.

Stopping (Ctrl-C, SIGTERM, or leaving the context) terminates the children in reverse order and waits
for them: a `kill` of `quekaro up` must not leave a master, agents and an XMPP server running.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from core.errors import QuekaroError
from core.xmpp_server import EmbeddedXmppServer, free_port
from quekaro.farm_client import FarmClient, default_home

DOMAIN = "localhost"
MASTER_JID = f"master@{DOMAIN}"
REPO = Path(__file__).resolve().parent.parent
DEMO_SCENE = REPO / "scenes" / "cbox.xml"
START_TIMEOUT_S = 120.0


class LocalFarm:
    """The processes of a local farm; use as a context manager."""

    def __init__(self, home: Path | None, agents: int = 2, threads: int | None = None,
                 rules: list[Path] | None = None, http_port: int = 0) -> None:
        if agents < 1:
            raise QuekaroError(f"--agents {agents}: a farm needs at least one agent")
        self.home = Path(home or default_home()).resolve()
        self.n_agents = agents
        self.threads = threads or max(1, (os.cpu_count() or 1) // agents)
        self.rules = [Path(r).resolve() for r in rules or []]
        self.http_port = http_port or free_port()
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.server: EmbeddedXmppServer | None = None
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self._previous_sigterm: object = None

    def __enter__(self) -> LocalFarm:
        self._previous_sigterm = _sigterm_as_interrupt()
        try:
            self.start()
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.stop()
        finally:
            if self._previous_sigterm is not None:
                signal.signal(signal.SIGTERM, self._previous_sigterm)
                self._previous_sigterm = None

    def start(self) -> None:
        (self.home / "logs").mkdir(parents=True, exist_ok=True)
        (self.home / "farm.json").unlink(missing_ok=True)
        self.server = EmbeddedXmppServer(self.home / "xmpp", domain=DOMAIN)
        # Accounts are made afresh at every start (new passwords, new agent JIDs): the database of a
        # previous start would refuse the master's new password, and a second `quekaro demo` would fail.
        self.server.database.unlink(missing_ok=True)
        self.server.start()
        self._spawn("master", self._master_command())
        self._wait_for_master()
        for i in range(self.n_agents):
            # The password travels in the environment: not in `ps`, and never parsed as an option.
            password = self._secret_file(f"agent-{i}.pw").read_text()
            self._spawn(f"agent-{i}", self._agent_command(i), QUEKARO_XMPP_PASSWORD=password)

    def _secret_file(self, name: str) -> Path:
        path = self.home / "secrets" / name
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        path.touch(mode=0o600)
        path.write_text(secrets.token_hex(16))
        return path

    def _master_command(self) -> list[str]:
        return [sys.executable, "-m", "quekaro", "master", "--home", str(self.home), "--jid", MASTER_JID,
                "--password-file", str(self._secret_file("master.pw")), "--server", "127.0.0.1",
                "--port", str(self.server.port), "--register", "--http-port", str(self.http_port),
                "--threads", str(self.threads)]

    def _agent_command(self, i: int) -> list[str]:
        # A JID that reconnects may never receive again on the embedded server: unique per process.
        jid = f"agent-{i}-{secrets.token_hex(3)}@{DOMAIN}"
        cmd = [sys.executable, "-m", "agents.render_agent", "--server", "127.0.0.1",
               "--port", str(self.server.port), "--jid", jid, "--master", MASTER_JID,
               "--threads", str(self.threads), "--workdir", str(self.home / "agents" / f"agent-{i}"),
               "--register"]
        if self.rules:
            cmd += ["--rules", str(self.rules[i % len(self.rules)])]
        return cmd

    def _spawn(self, name: str, cmd: list[str], **env_extra: str) -> None:
        log = (self.home / "logs" / f"{name}.log").open("ab")
        env = dict(os.environ, **env_extra,
                   PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=REPO)
        self.procs.append((name, proc))

    def _wait_for_master(self) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            self.check_alive()
            if (self.home / "farm.json").exists():
                try:
                    urllib.request.urlopen(self.url + "/api/agents", timeout=2)
                except urllib.error.HTTPError:
                    return  # 401 without the token: the API is up
                except OSError:
                    pass
            time.sleep(0.2)
        raise QuekaroError(f"the master did not come up within {START_TIMEOUT_S:.0f} s "
                           f"(see {self.home / 'logs' / 'master.log'})")

    def check_alive(self) -> None:
        for name, proc in self.procs:
            if proc.poll() is not None:
                raise QuekaroError(f"{name} exited with status {proc.returncode} "
                                   f"(see {self.home / 'logs' / (name + '.log')})")

    def client(self) -> FarmClient:
        return FarmClient.from_home(self.home)

    def wait_for_agents(self, timeout: float = START_TIMEOUT_S) -> None:
        """Until every agent has registered with the master."""
        client = self.client()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.check_alive()
            if sum(not a["lost"] for a in client.agents()) >= self.n_agents:
                return
            time.sleep(0.3)
        raise QuekaroError(f"agents did not register within {timeout:.0f} s (see {self.home / 'logs'})")

    def wait(self) -> None:
        """Block until Ctrl-C or until a process dies."""
        try:
            while True:
                self.check_alive()
                time.sleep(1.0)
        except KeyboardInterrupt:
            print("stopping the farm ...")

    def stop(self) -> None:
        stop_processes([proc for _name, proc in reversed(self.procs)])
        self.procs.clear()
        if self.server is not None:
            self.server.stop()
            self.server = None


def _sigterm_as_interrupt() -> object:
    """Make SIGTERM raise KeyboardInterrupt (so the context exits and stops the children) and return the
    handler it replaced; None off the main thread, where Python cannot set handlers."""
    def interrupt(_signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    try:
        return signal.signal(signal.SIGTERM, interrupt)
    except ValueError:
        return None


def stop_processes(procs: list[subprocess.Popen], timeout: float = 15.0) -> None:
    """SIGTERM to all (in the order given), then wait for each; SIGKILL the ones that outstay `timeout`."""
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_demo(args: argparse.Namespace) -> int:
    """Start a farm, render the demo scene on it, fetch the image, and say where everything is."""
    import tempfile

    from core.bundle import make_bundle
    from quekaro.cmd_farm import watch

    with LocalFarm(args.home, args.agents, args.threads, args.rules, args.http_port) as farm:
        print(f"farm up: master {farm.url}, {farm.n_agents} agents, home {farm.home}")
        farm.wait_for_agents()
        with tempfile.TemporaryDirectory() as tmp:
            bundle = make_bundle(DEMO_SCENE, {}, Path(tmp) / "bundle.tar").path.read_bytes()
        client = farm.client()
        job_id = client.submit(bundle, {}, {"level": args.level})
        print(f"submitted {DEMO_SCENE.relative_to(REPO)} as job {job_id} (optimisation {args.level})")
        status = watch(client, job_id)
        if status != 0:
            return status
        out = client.result(job_id, args.out)
        report = json.loads(out.with_suffix(".json").read_text())
    totals = report["totals"]
    print(f"image:  {out.resolve()}\npng:    {out.with_suffix('.png').resolve()}\n"
          f"report: {out.with_suffix('.json').resolve()}")
    print(f"{totals['units']} units, {totals['seconds']:.1f} s to compose, render seconds on agents "
          f"{totals['render_seconds']:.1f}, pre-pass {totals['prepass_seconds']:.2f} s")
    return 0
