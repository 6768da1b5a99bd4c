"""A whole farm on one machine (`quekaro up`, `quekaro demo`): Prosody on loopback, the master and N render
agents, each in its own process with its own Dr.Jit thread count and its own account, made before any
file names it.

Supervised (`supervise=True`, as `quekaro up` and `quekaro demo` run it): a child that dies is restarted
with backoff, and one that crash-loops is marked failed and left down while the rest goes on
(core.supervision); an agent comes back under its own JID. The state of every process is in
HOME/processes.json. Every child dies with the farm,
even when it is killed with SIGKILL (PR_SET_PDEATHSIG); stopping (Ctrl-C, SIGTERM, or leaving the
context) terminates the children in reverse order and waits for them. One farm at a time holds a home
(HOME/farm.lock, an flock the kernel releases when the farm's process dies, even by SIGKILL).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.parse
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from core.errors import QuekaroError
from core.home import AGENTS_ALLOW, FARM_FILE, PROCESSES_FILE, default_home, make_private, read_processes
from core.scene.bundle import check_rules
from core.supervision import RestartPolicy, die_with_parent, log_tail
from core.transport.xmpp_server import ProsodyServer, XmppServerError
from farm.client import FarmClient

DOMAIN = "localhost"
MASTER_JID = f"master@{DOMAIN}"
REPO = Path(__file__).resolve().parent.parent
START_TIMEOUT_S = 120.0
LOCK_FILE = "farm.lock"


@dataclass
class Child:
    """One supervised process: how to start it, its process now, and its restart history."""

    name: str
    command: Callable[[], list[str]]
    env: dict[str, str]
    proc: subprocess.Popen | None = None
    policy: RestartPolicy = field(default_factory=RestartPolicy)
    restart_at: float | None = None
    state: str = "running"  # running, restarting or failed

    def to_dict(self) -> dict:
        return {"name": self.name, "state": self.state, "pid": self.proc.pid if self.proc else None,
                "restarts": self.policy.count}


class LocalFarm:
    """The processes of a local farm; use as a context manager."""

    def __init__(self, home: Path | None, agents: int = 2, threads: int | None = None,
                 rules: list[Path] | None = None, http_port: int = 0, supervise: bool = False,
                 pass_samples: int | None = None) -> None:
        if agents < 1:
            raise QuekaroError(f"--agents {agents}: a farm needs at least one agent")
        if threads is not None and threads < 1:
            raise QuekaroError(f"--threads {threads}: each agent needs at least one thread (leave it out for "
                               "the cores shared among the agents)")
        if not 0 <= http_port <= 65535:
            raise QuekaroError(f"--http-port {http_port}: not a TCP port (1..65535; 0 or none: a free one)")
        self.home = Path(home or default_home()).resolve()
        self.n_agents = agents
        self.threads = threads or max(1, (os.cpu_count() or 1) // agents)
        self.rules = [Path(r).resolve() for r in rules or []]
        for path in self.rules:
            check_rules(path)  # each agent would crash-loop on it, leaving a farm without agents
        if len(self.rules) > agents:  # agent i takes rule file i mod n: the extra files would go unused
            raise QuekaroError(f"--rules: {len(self.rules)} rule files for {agents} agents; agent i takes file "
                               f"i, so {', '.join(r.name for r in self.rules[agents:])} would never be used "
                               f"(give --agents {len(self.rules)} or more)")
        self.pass_samples = pass_samples  # the master's --pass-samples (None: its default)
        self.http_port = http_port  # 0: the master binds a free one and names it in farm.json (self.url)
        self.url = f"http://127.0.0.1:{http_port}" if http_port else ""
        self.server: ProsodyServer | None = None
        self.children: list[Child] = []
        self._server_policy = RestartPolicy()
        self._server_restart_at: float | None = None
        self._server_error = ""  # why its latest restart failed (a port taken meanwhile)
        self._supervise = supervise
        self._lock = threading.Lock()
        self._states_unwritten = False  # processes.json could not be written: tried again each round
        self._stopping = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._previous_sigterm: object = None
        self._lock_fd: int | None = None
        self._caller_umask: int | None = None

    @property
    def procs(self) -> list[tuple[str, subprocess.Popen]]:
        """(name, process) of every child started and not stopped (master first)."""
        return [(c.name, c.proc) for c in self.children if c.proc is not None]

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
        self._caller_umask = os.umask(0o077)  # make_private sets it for the farm; stop() gives it back
        if make_private(self.home):  # the XMPP server's files, the logs and every child's inherit umask 077
            print(f"quekaro: --home {self.home}: others could read it; now only this user can", file=sys.stderr)
        try:
            (self.home / "logs").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise QuekaroError(f"--home {self.home}: cannot make the farm's folder there ({exc.strerror})") from None
        self._lock_home()
        (self.home / FARM_FILE).unlink(missing_ok=True)
        passwords = self._start_server()
        self._add(Child("master", self._master_command, {"QUEKARO_XMPP_PASSWORD": passwords["master"]}))
        self._wait_for_master()
        for i in range(self.n_agents):
            # The password travels in the environment: not in `ps`, and never parsed as an option.
            self._add(Child(f"agent-{i}", functools.partial(self._agent_command, i),
                            {"QUEKARO_XMPP_PASSWORD": passwords[f"agent-{i}"]}))
        self._write_states()
        if self._supervise:
            self._supervisor = threading.Thread(target=self._supervise_forever, name="supervisor", daemon=True)
            self._supervisor.start()

    def _lock_home(self) -> None:
        """Hold HOME/farm.lock for the farm's life: a second farm on the same home would delete this one's
        farm.json and XMPP accounts and empty its agents' allow-list."""
        fd = os.open(self.home / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise QuekaroError(f"a farm is already running in {self.home} (pid {holder}): stop it first, or give "
                               "another --home") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd

    def _start_server(self) -> dict[str, str]:
        """Prosody on loopback with every account made first, each with a fresh random password (a
        previous start's accounts go), registration closed; then the agents' JIDs are listed for the
        master. Nothing is written at a restart, so a full disk blocks none. Returns user -> password."""
        self.server = ProsodyServer(self.home / "xmpp", domain=DOMAIN)
        shutil.rmtree(self.server.data_dir / "data", ignore_errors=True)
        users = ["master", *(f"agent-{i}" for i in range(self.n_agents))]
        passwords = self.server.register_all(users)
        (self.home / AGENTS_ALLOW).write_text("".join(f"{u}@{DOMAIN}\n" for u in users[1:]))
        self.server.start()
        return passwords

    def add_account(self, user: str) -> str:
        """Make one more agent account on the farm's server and let the master take its bids (an agent
        started by hand beside the farm's own); returns its password."""
        password = self.server.register(user)
        with (self.home / AGENTS_ALLOW).open("a") as allow:
            allow.write(f"{user}@{DOMAIN}\n")
        return password

    def _xmpp_options(self) -> list[str]:
        """How the master and the agents reach Prosody: loopback, TLS verified against its certificate."""
        cert = self.server.cert_dir / f"{DOMAIN}_cert.pem"
        return ["--server", "127.0.0.1", "--port", str(self.server.port), "--ca-file", str(cert)]

    def _master_command(self) -> list[str]:
        # Called again at each restart: the port is then the one the first start bound (uploads name it).
        # The pre-pass takes the agents' threads together: a job's agents wait for its plan.
        return [sys.executable, "-m", "quekaro", "master", "--home", str(self.home), "--jid", MASTER_JID,
                *self._xmpp_options(), "--http-port", str(self.http_port),
                "--threads", str(self.threads * self.n_agents), "--agents-allow", str(self.home / AGENTS_ALLOW),
                *(["--pass-samples", str(self.pass_samples)] if self.pass_samples else [])]

    def _agent_command(self, i: int) -> list[str]:
        # One account per agent, made before the farm named it; a restarted agent logs in again as it.
        cmd = [sys.executable, "-m", "agents.render_agent", "--jid", f"agent-{i}@{DOMAIN}", *self._xmpp_options(),
               "--master", MASTER_JID, "--master-url", self.url,
               "--threads", str(self.threads), "--workdir", str(self.home / "agents" / f"agent-{i}")]
        if self.rules:
            cmd += ["--rules", str(self.rules[i % len(self.rules)])]
        return cmd

    def _add(self, child: Child) -> None:
        self._spawn(child)
        self.children.append(child)

    def _spawn(self, child: Child) -> None:
        with (self.home / "logs" / f"{child.name}.log").open("ab") as log:
            env = dict(os.environ, **child.env,
                       PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
            child.proc = subprocess.Popen(child.command(), stdout=log, stderr=subprocess.STDOUT, env=env, cwd=REPO,
                                          preexec_fn=die_with_parent)
        child.state, child.restart_at = "running", None

    # ---- supervision ------------------------------------------------------------------------------

    def _supervise_forever(self, tick: float = 0.25) -> None:
        while not self._stopping.wait(tick):
            try:
                self.supervise(time.monotonic())
            except Exception as exc:  # the supervisor must outlive any one failed restart
                _say(f"supervisor: {type(exc).__name__}: {exc}")

    def supervise(self, now: float) -> None:
        """One round: notice dead children, restart those whose backoff has passed, give up on crash loops."""
        with self._lock:
            if self._stopping.is_set():
                return
            changed = self._supervise_server(now)
            for child in self.children:
                changed |= self._supervise_child(child, now)
            if changed or self._states_unwritten:
                self._try_write_states()

    def _try_write_states(self) -> None:
        """Write processes.json; where it cannot (a full disk), say so once and try again every round, so that
        it never keeps a restarted process's old pid once space returns."""
        try:
            self._write_states()
        except OSError as exc:
            if not self._states_unwritten:
                _say(f"supervisor: {PROCESSES_FILE} not written ({exc}): trying again every round")
            self._states_unwritten = True
            return
        if self._states_unwritten:
            _say(f"supervisor: {PROCESSES_FILE} written again")
        self._states_unwritten = False

    def _supervise_child(self, child: Child, now: float) -> bool:
        if child.state == "running" and child.proc is not None and child.proc.poll() is not None:
            code = child.proc.returncode
            child.restart_at = child.policy.on_exit(now)
            if child.restart_at is None:
                child.state = "failed"
                goes_on = f"the farm {'cannot go' if child.name == 'master' else 'goes'} on without it"
                _say(f"{child.name} exited with status {code}: {child.policy.crash_loop} restarts within "
                     f"{child.policy.window_s:.0f} s, marked failed; {goes_on}")
            else:
                child.state = "restarting"
                _say(f"{child.name} exited with status {code}: restarting in {child.restart_at - now:.1f} s "
                     f"(restart {child.policy.count})")
            return True
        if child.state == "restarting" and now >= child.restart_at:
            self._spawn(child)
            _say(f"{child.name} restarted (pid {child.proc.pid})")
            return True
        return False

    def _supervise_server(self, now: float) -> bool:
        """As `_supervise_child`, without sleeping under the lock: the restart waits for a later round."""
        if self.server is None or self.server.running or self._server_policy.failed:
            return False
        if self._server_restart_at is None:
            code = self.server.returncode
            self.server.stop()  # its workers too: they would hold the port
            self._server_restart_at = self._server_policy.on_exit(now)
            if self._server_restart_at is None:
                _say(f"XMPP server exited with status {code}: crash-looped, marked failed; the farm cannot go on "
                     f"without it (see {self.server.log_path})")
            else:
                _say(f"XMPP server exited with status {code}: restarting in {self._server_restart_at - now:.1f} s "
                     f"(restart {self._server_policy.count})")
            return True
        if now < self._server_restart_at:
            return False
        self._server_restart_at = None
        try:
            self.server.start()
        except XmppServerError as exc:  # the supervisor says it; a later round counts it as an exit
            self._server_error = str(exc)
            raise
        _say(f"XMPP server restarted (pid {self.server.pid})")
        return True

    def _write_states(self) -> None:
        down = self.server is None or not self.server.running
        server = {"name": "xmpp-server", "pid": self.server.pid if self.server else None,
                  "state": "failed" if self._server_policy.failed else "restarting" if down else "running",
                  "restarts": self._server_policy.count}
        states = {"processes": [server, *(c.to_dict() for c in self.children)]}
        tmp = self.home / ".processes.json.part"
        tmp.write_text(json.dumps(states, indent=1))
        os.replace(tmp, self.home / PROCESSES_FILE)

    def _wait_for_master(self) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        master = self.children[0].proc
        while time.monotonic() < deadline:
            if master.poll() is not None:  # not restarted: what failed it (a port in use) fails it again
                log = self.home / "logs" / "master.log"
                raise QuekaroError(f"the master exited with status {master.returncode} as it started: "
                                   f"{log_tail(log)} (see {log})")
            if (self.home / FARM_FILE).exists():
                self._read_url()
                try:
                    urllib.request.urlopen(self.url + "/api/agents", timeout=2)
                except urllib.error.HTTPError:
                    return  # 401 without the token: the API is up
                except OSError:
                    pass
            time.sleep(0.2)
        raise QuekaroError(f"the master did not come up within {START_TIMEOUT_S:.0f} s "
                           f"(see {self.home / 'logs' / 'master.log'})")

    def _read_url(self) -> None:
        """The master's URL from its farm.json, and its port for the master's restarts."""
        with contextlib.suppress(OSError, ValueError, KeyError):
            self.url = json.loads((self.home / FARM_FILE).read_text())["url"]
            self.http_port = urllib.parse.urlsplit(self.url).port or self.http_port

    def check_alive(self) -> None:
        """Raise if a child is down for good (failed under supervision, or dead without it), or the XMPP
        server has failed (nothing reaches anyone without it), naming what its log last said."""
        if self._server_policy.failed and self.server is not None:
            why = self._server_error or log_tail(self.server.log_path)
            raise QuekaroError(f"the XMPP server could not be restarted: {why} (see {self.server.log_path})")
        for child in self.children:
            dead = child.proc is not None and child.proc.poll() is not None and not self._supervise
            if dead or (child.state == "failed" and child.name == "master"):
                log = self.home / "logs" / (child.name + ".log")
                raise QuekaroError(f"{child.name} exited with status {child.proc.returncode}: {log_tail(log)} "
                                   f"(see {log})")

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
        """Block until Ctrl-C, or until a child is down for good (see check_alive)."""
        try:
            while True:
                self.check_alive()
                time.sleep(1.0)
        except KeyboardInterrupt:
            print("stopping the farm ...")

    def stop(self) -> None:
        self._stopping.set()
        if self._supervisor is not None:
            self._supervisor.join(timeout=30)
        with self._lock:
            stop_processes([proc for _name, proc in reversed(self.procs)])
            self.children.clear()
            if self.server is not None:
                self.server.stop()
                self.server = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None
        if self._caller_umask is not None:  # a farm run inside a program (a test, a benchmark) leaves it as it was
            os.umask(self._caller_umask)
            self._caller_umask = None


def stop_farm(home: Path, timeout: float = 60.0) -> list[str] | None:
    """Stop the farm running in `home` (`quekaro down`): SIGTERM to the process holding HOME/farm.lock (`quekaro
    up` or `demo`), which stops its children as Ctrl-C does; wait until it lets the lock go. Returns the names
    of the processes it ran, None where no farm holds the home."""
    try:
        fd = os.open(Path(home) / LOCK_FILE, os.O_RDWR)
    except FileNotFoundError:
        return None
    try:
        if _try_lock(fd):
            return None
        pid = int(os.read(fd, 32).decode(errors="replace").strip() or 0)
        names = [p["name"] for p in read_processes(home) if p.get("state") == "running"]
        if pid <= 0:
            raise QuekaroError(f"the farm in {home} holds {LOCK_FILE} but names no process in it")
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while not _try_lock(fd):
            if time.monotonic() > deadline:
                raise QuekaroError(f"the farm in {home} (pid {pid}) did not stop within {timeout:.0f} s "
                                   f"(see {Path(home) / 'logs'})")
            time.sleep(0.2)
        return names
    finally:
        os.close(fd)  # lets the lock go if it was taken here


def _try_lock(fd: int) -> bool:
    """Whether this process could take the home's lock, that is, no farm holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _say(line: str) -> None:
    print(f"quekaro: {line}", file=sys.stderr, flush=True)


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
