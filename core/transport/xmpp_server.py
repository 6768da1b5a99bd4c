"""Run the XMPP server a farm stands on, Prosody, as a child process on 127.0.0.1.

A local farm, the tests and the benchmarks run `ProsodyServer`: the repository's config
(`deploy/prosody/`), accounts made ahead with `prosodyctl`, registration closed. Farms across hosts
run the same config as a service.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pwd
import secrets
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO

from core.errors import QuekaroError
from core.supervision import die_with_parent, log_tail

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
PROSODY_CONFIG = REPO_ROOT / "deploy" / "prosody" / "prosody.cfg.lua"


class XmppServerError(QuekaroError):
    """An XMPP server that could not be configured, started or stopped."""


class PortTaken(XmppServerError):
    """The server's port is held by another process (bound before the server could bind it)."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that nothing listens on at `host` right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def port_accepts(host: str, port: int, timeout: float = 0.5) -> bool:
    """True when a TCP connection to host:port succeeds now."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def make_self_signed_cert(directory: Path, domain: str, days: int = 30) -> tuple[Path, Path]:
    """Write `<domain>_cert.pem` and `<domain>_key.pem` (RSA 2048, SAN = domain) with openssl."""
    directory.mkdir(parents=True, exist_ok=True)
    cert, key = directory / f"{domain}_cert.pem", directory / f"{domain}_key.pem"
    if shutil.which("openssl") is None:
        raise XmppServerError("openssl is not installed: cannot make the XMPP server's certificate")
    cmd = [
        "openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", str(days),
        "-subj", f"/CN={domain}", "-addext", f"subjectAltName=DNS:{domain}",
        "-keyout", str(key), "-out", str(cert),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise XmppServerError(f"openssl could not make a certificate for {domain}: {done.stderr.strip()}")
    key.chmod(0o600)
    return cert, key


def _poll_until(proc: subprocess.Popen, ready: Callable[[], bool], timeout: float, exited: Callable[[int], str],
                late: Callable[[], str]) -> None:
    """Poll `ready` every 50 ms until it holds; XmppServerError saying `exited(code)` if the child exits
    first, or `late()` once `timeout` seconds have passed."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise XmppServerError(exited(proc.returncode))
        if ready():
            return
        time.sleep(0.05)
    raise XmppServerError(late())


def _stop_child(proc: subprocess.Popen | None, timeout: float) -> None:
    """SIGTERM to the server's whole process group (its workers hold the port too), SIGKILL after `timeout`;
    the group is signalled even when the server's main process is already dead."""
    if proc is None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        log.warning("XMPP server pid %d ignored SIGTERM for %.0f s: killing it", proc.pid, timeout)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=timeout)


class ProsodyServer:
    """A real Prosody 0.12 in a child process on 127.0.0.1, with the repository's config, TLS required,
    registration closed: start, stop, kill, restart.

    Runs in the foreground as a child (no system service, no daemon) with `deploy/prosody/prosody.cfg.lua`,
    its own pid file, a free port and a fresh self-signed certificate; everything it writes stays in
    `data_dir`. Accounts are created with `prosodyctl register` before (or while) it runs. The tests use
    it; `quekaro` never needs the system's Prosody service.
    """

    host = "127.0.0.1"

    def __init__(self, data_dir: Path | str, domain: str = "localhost", port: int | None = None,
                 config: Path = PROSODY_CONFIG, stanza_limit: int = 256 * 1024, c2s_rate: str | None = None,
                 unlimited: Iterable[str] | None = None) -> None:
        for tool in ("prosody", "prosodyctl"):
            if shutil.which(tool) is None:
                raise XmppServerError(f"{tool} is not installed (Debian package 'prosody')")
        if not Path(config).is_file():
            raise XmppServerError(f"Prosody config not found: {config}")
        self.data_dir = Path(data_dir).resolve()
        self.domain = domain
        self.port = port or free_port()  # Prosody cannot be told port 0 and report what it bound
        self._choose_port = port is None  # until it first starts: a port taken meanwhile is chosen again
        self.log_path = self.data_dir / "server.log"  # the child's stdout and stderr
        self._proc: subprocess.Popen | None = None
        self._log_file: IO[bytes] | None = None
        self._log_offset = 0
        self.config = Path(config)
        self.stanza_limit = stanza_limit
        self.c2s_rate, self.unlimited = c2s_rate, None if unlimited is None else ",".join(unlimited)

    @property
    def pid(self) -> int | None:
        proc = self._proc  # once: a supervisor's restart may replace it meanwhile
        return proc.pid if proc and proc.poll() is None else None

    @property
    def returncode(self) -> int | None:
        """The child's exit status once it has exited (None while it runs, or before it started)."""
        proc = self._proc
        return proc.poll() if proc else None

    @property
    def running(self) -> bool:
        return self.pid is not None

    @property
    def cert_dir(self) -> Path:
        return self.data_dir / "certs"

    @property
    def log_file(self) -> Path:
        return self.data_dir / "prosody.log"

    def env(self) -> dict[str, str]:
        """The environment the repository's prosody.cfg.lua reads its settings from."""
        return dict(
            os.environ,
            QUEKARO_XMPP_DOMAIN=self.domain,
            QUEKARO_XMPP_PORT=str(self.port),
            QUEKARO_XMPP_INTERFACE=self.host,
            QUEKARO_PROSODY_DATA=str(self.data_dir / "data"),
            QUEKARO_PROSODY_PIDFILE=str(self.data_dir / "prosody.pid"),
            QUEKARO_PROSODY_LOG=str(self.log_file),
            QUEKARO_XMPP_CERT=str(self.cert_dir / f"{self.domain}_cert.pem"),
            QUEKARO_XMPP_KEY=str(self.cert_dir / f"{self.domain}_key.pem"),
            QUEKARO_XMPP_STANZA_LIMIT=str(self.stanza_limit),
            # Running as root in a container: keep files owned by us rather than switch to `prosody`.
            QUEKARO_PROSODY_USER=_current_user(),
            **{k: v for k, v in (("QUEKARO_XMPP_C2S_RATE", self.c2s_rate),
                                 ("QUEKARO_XMPP_UNLIMITED", self.unlimited)) if v is not None},
        )

    def start(self, timeout: float = 30.0, attempts: int = 3) -> None:
        """Start the server and return once it listens on 127.0.0.1:port. A port chosen here (none given)
        that another process takes before Prosody binds it is chosen again, up to `attempts` times
        (Prosody itself runs on, on no port)."""
        for attempt in range(attempts):
            try:
                self._start_once(timeout)
                self._choose_port = False  # a restart must come back where its clients look for it
                return
            except PortTaken:
                if not self._choose_port or attempt == attempts - 1:
                    raise
                log.warning("XMPP port %d was taken before Prosody bound it: choosing another", self.port)
                self.port = free_port()

    def _start_once(self, timeout: float) -> None:
        if self.running:
            return
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._prepare()
        if port_accepts(self.host, self.port, timeout=0.2):
            raise PortTaken(f"port {self.host}:{self.port} is already in use")
        cmd, env = self._command()
        self._log_file = open(self.log_path, "ab")  # noqa: SIM115 (kept open for the child's life)
        self._proc = subprocess.Popen(cmd, stdout=self._log_file, stderr=subprocess.STDOUT, env=env,
                                      cwd=self.data_dir, start_new_session=True, preexec_fn=die_with_parent)
        try:
            self._await_ready(timeout)
        except XmppServerError:
            self.stop()
            raise
        log.info("XMPP server %s up on %s:%d (pid %d)", self.domain, self.host, self.port, self._proc.pid)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the server (SIGTERM, then SIGKILL after `timeout`); its data directory stays."""
        _stop_child(self._proc, timeout)
        self._proc = None
        if self._log_file:
            self._log_file.close()
            self._log_file = None

    def kill(self) -> None:
        """Kill the server's main process at once (SIGKILL), as a crash would; stop() ends its workers.
        The process is read once: a supervisor that sees it die may restart the server (and replace it)
        before this waits."""
        proc = self._proc
        if proc and proc.poll() is None:
            proc.kill()
            proc.wait()

    def restart(self, downtime: float = 0.0, timeout: float = 30.0) -> None:
        """Stop, stay down `downtime` seconds, start again on the same port with the same data."""
        self.stop()
        time.sleep(downtime)
        self.start(timeout=timeout)

    def __enter__(self) -> ProsodyServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _prepare(self) -> None:
        """What a start needs: the data folder and a certificate."""
        (self.data_dir / "data").mkdir(parents=True, exist_ok=True)
        if not (self.cert_dir / f"{self.domain}_cert.pem").exists():
            make_self_signed_cert(self.cert_dir, self.domain)

    def _await_ready(self, timeout: float) -> None:
        """Until Prosody's log says it listens on the port (another process's listener there accepts too)."""
        _poll_until(self._proc, self._listening, timeout,
                    lambda code: f"Prosody exited with code {code}; see {self.log_path}:\n"
                                 + log_tail(self.log_path, 15),
                    lambda: f"Prosody did not listen on {self.host}:{self.port} within {timeout:.0f} s; see "
                            f"{self.log_file}:\n" + log_tail(self.log_file, 15))

    def _listening(self) -> bool:
        """Whether Prosody listens on its port; PortTaken (Prosody stopped) where its log says it cannot."""
        started = self._log_since_start()
        if f"Failed to open server port {self.port} " in started or "'c2s' on no ports" in started:
            self.stop()
            raise PortTaken(f"port {self.host}:{self.port} is taken by another process (see {self.log_file})")
        return (f"Activated service 'c2s' on [{self.host}]:{self.port}" in started
                and port_accepts(self.host, self.port, timeout=0.2))

    def _command(self) -> tuple[list[str], dict[str, str]]:
        """Prosody's command line and environment (where its log starts is noted: `_log_since_start`)."""
        self._log_offset = self.log_file.stat().st_size if self.log_file.exists() else 0
        return ["prosody", "--config", str(self.config), "-F"], self.env()

    def _log_since_start(self) -> str:
        try:
            with self.log_file.open("rb") as fh:
                fh.seek(self._log_offset)
                return fh.read().decode(errors="replace")
        except OSError:
            return ""

    def register(self, user: str, password: str | None = None) -> str:
        """Create (or reset) account user@domain with prosodyctl; returns the password used."""
        password = password or secrets.token_hex(16)  # hex: never starts with "-" (argv-safe)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        (self.data_dir / "data").mkdir(parents=True, exist_ok=True)
        done = subprocess.run(["prosodyctl", "--config", str(self.config), "register", user, self.domain,
                               password], env=self.env(), capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise XmppServerError(f"prosodyctl register {user}@{self.domain} failed: "
                                  f"{(done.stderr or done.stdout).strip()}")
        return password

    def register_all(self, users: Iterable[str]) -> dict[str, str]:
        """Create several accounts with generated passwords: user -> password."""
        return {u: self.register(u) for u in users}


def _current_user() -> str:
    return pwd.getpwuid(os.getuid()).pw_name
