"""Run the XMPP server a farm stands on, as a child process: SPADE's embedded one (pyjabber) or Prosody.

`EmbeddedXmppServer` is for one machine only: it binds 127.0.0.1 and is safe on loopback alone. Use
Prosody (`deploy/prosody/`) when agents run on other hosts; `ProsodyServer` runs one for the tests.
`python -m core.transport.xmpp_server embedded ...` (`main`) hosts pyjabber in this process: that is
what `EmbeddedXmppServer` spawns.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ipaddress
import json
import logging
import os
import pwd
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO

from core.errors import QuekaroError
from core.files import written_atomically
from core.supervision import die_with_parent, log_tail
from core.transport.tmp_cleanup import remove_upload_dir_at_exit

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


def resolves_to_loopback(domain: str) -> bool:
    """True when every IPv4 address `domain` resolves to is a loopback address."""
    try:
        infos = socket.getaddrinfo(domain, None, socket.AF_INET)
    except socket.gaierror:
        return False
    return bool(infos) and all(ipaddress.ip_address(i[4][0]).is_loopback for i in infos)


def make_self_signed_cert(directory: Path, domain: str, days: int = 30) -> tuple[Path, Path]:
    """Write `<domain>_cert.pem` and `<domain>_key.pem` (RSA 2048, SAN = domain) with openssl.

    pyjabber looks for exactly these names in its cert directory; Prosody is told the paths.
    """
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


def _first_error(path: Path) -> str:
    """pyjabber's first ERROR line in its log (a port it could not bind), else the log's last line."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return "(no log)"
    errors = [line.split(" - ", 1)[-1].strip() for line in lines if "| ERROR" in line]
    return errors[0] if errors else log_tail(path)


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


class _ChildServer:
    """What both servers share: a child process, a port on 127.0.0.1, start/stop/restart."""

    host = "127.0.0.1"

    def __init__(self, data_dir: Path | str, domain: str, port: int | None) -> None:
        self.data_dir = Path(data_dir).resolve()
        self.domain = domain
        self.port = port or 0  # 0: the subclass chooses (Prosody: a free port; pyjabber: its own bind)
        self.log_path = self.data_dir / "server.log"
        self._proc: subprocess.Popen | None = None
        self._log_file: IO[bytes] | None = None

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

    def _command(self) -> tuple[list[str], dict[str, str]]:
        raise NotImplementedError

    def _prepare(self) -> None:
        """Create what the first start needs (directories, certificate, accounts)."""

    def _await_ready(self, timeout: float) -> None:
        """Return once the child serves clients; raise XmppServerError (with its log) if it exits first."""
        raise NotImplementedError

    def start(self, timeout: float = 30.0) -> None:
        """Start the server and return once it accepts TCP connections on 127.0.0.1:port."""
        if self.running:
            return
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._prepare()
        if self.port and port_accepts(self.host, self.port, timeout=0.2):
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

    def __enter__(self) -> _ChildServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


ALLOWED_ACCOUNTS = "allowed-accounts"  # in the data dir: the only user names that may register
READY_FILE = "ready.json"  # in the data dir: the ports the server bound, written once it serves


class EmbeddedXmppServer(_ChildServer):
    """SPADE's pyjabber server in a child process: loopback only, file database, domain as host.

    It binds 127.0.0.1 alone and keeps its accounts in a file database under `data_dir`. The JID domain
    is its host: pyjabber's default host `0.0.0.0` accepts logins but delivers nothing. Loopback only,
    since its in-band registration (XEP-0077) is open to anyone who can reach the port, and the CA key
    behind its default certificate ships in the wheel.

    Registration is closed once `allow` has been called: only the user names listed in
    DATA_DIR/allowed-accounts may register (the local farm lists its master and each agent it starts),
    any other in-band registration is refused with `forbidden`. Without that file pyjabber's open
    registration stands (tests of the transport alone). `message_persistence` makes pyjabber keep
    messages to offline JIDs (off by default, as measured: messages to offline JIDs are dropped, so every
    protocol step must time out and retry).
    """

    def __init__(self, data_dir: Path | str, domain: str = "localhost", port: int | None = None,
                 s2s_port: int | None = None, message_persistence: bool = False,
                 log_level: str = "WARNING") -> None:
        if not resolves_to_loopback(domain):
            raise XmppServerError(f"embedded XMPP domain {domain!r} must resolve to 127.0.0.1 (pyjabber "
                                  "binds the domain's address): use localhost, or Prosody for several hosts")
        super().__init__(data_dir, domain, port)
        # Unless given, both ports are chosen by the server's own bind (0) and read back once it is ready:
        # a port picked here and bound later may be taken in between (a farm failed to start so).
        self.s2s_port = s2s_port or 0
        self.message_persistence = message_persistence
        self.log_level = log_level

    @property
    def database(self) -> Path:
        return self.data_dir / "pyjabber.db"

    @property
    def ready_file(self) -> Path:
        return self.data_dir / READY_FILE

    def allow(self, usernames: Iterable[str]) -> None:
        """Let these user names register (and close registration to every other)."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        path = self.data_dir / ALLOWED_ACCOUNTS
        known = path.read_text().split() if path.exists() else []
        tmp = path.with_name(f".{path.name}.part")
        tmp.write_text("\n".join(dict.fromkeys([*known, *usernames])) + "\n")
        os.replace(tmp, path)

    def _prepare(self) -> None:
        certs = self.data_dir / "certs"
        if not (certs / f"{self.domain}_cert.pem").exists():
            # Our own certificate, so that pyjabber never signs one with the CA key it ships.
            make_self_signed_cert(certs, self.domain)

    def _await_ready(self, timeout: float) -> None:
        """Wait for the ports the child writes once both its listeners are bound (the client port alone
        accepting does not say the server-to-server one was bound: pyjabber exits when it is not)."""
        _poll_until(self._proc, self._read_ports, timeout,
                    lambda code: f"XMPP server exited with code {code}: {_first_error(self.log_path)} "
                                 f"(see {self.log_path})",
                    lambda: f"XMPP server did not bind its ports within {timeout:.0f} s; see {self.log_path}:\n"
                            + log_tail(self.log_path, 15))

    def _read_ports(self) -> bool:
        try:
            ports = json.loads(self.ready_file.read_text())
        except FileNotFoundError:
            return False
        self.port, self.s2s_port = int(ports["port"]), int(ports["s2s_port"])
        return True

    def _command(self) -> tuple[list[str], dict[str, str]]:
        self.ready_file.unlink(missing_ok=True)
        cmd = [sys.executable, "-m", "core.transport.xmpp_server", "embedded", "--domain", self.domain,
               "--port", str(self.port), "--s2s-port", str(self.s2s_port), "--data-dir", str(self.data_dir),
               "--log-level", self.log_level]
        if self.message_persistence:
            cmd.append("--message-persistence")
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO_ROOT),
                                                                         os.environ.get("PYTHONPATH")])))
        return cmd, env


class ProsodyServer(_ChildServer):
    """A real Prosody 0.12 on 127.0.0.1 with the repository's config, TLS required, registration closed.

    Runs in the foreground as a child (no system service, no daemon) with `deploy/prosody/prosody.cfg.lua`,
    its own pid file, a free port and a fresh self-signed certificate; everything it writes stays in
    `data_dir`. Accounts are created with `prosodyctl register` before (or while) it runs. The tests use
    it; `quekaro` never needs the system's Prosody service.
    """

    def __init__(self, data_dir: Path | str, domain: str = "localhost", port: int | None = None,
                 config: Path = PROSODY_CONFIG, stanza_limit: int = 256 * 1024, c2s_rate: str | None = None,
                 unlimited: Iterable[str] | None = None) -> None:
        for tool in ("prosody", "prosodyctl"):
            if shutil.which(tool) is None:
                raise XmppServerError(f"{tool} is not installed (Debian package 'prosody')")
        if not Path(config).is_file():
            raise XmppServerError(f"Prosody config not found: {config}")
        super().__init__(data_dir, domain, port)
        self.port = port or free_port()  # Prosody cannot be told port 0 and report what it bound
        self._choose_port = port is None  # until it first starts: a port taken meanwhile is chosen again
        self._log_offset = 0
        self.config = Path(config)
        self.stanza_limit = stanza_limit
        self.c2s_rate, self.unlimited = c2s_rate, None if unlimited is None else ",".join(unlimited)

    @property
    def cert_dir(self) -> Path:
        return self.data_dir / "certs"

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

    def _prepare(self) -> None:
        (self.data_dir / "data").mkdir(parents=True, exist_ok=True)
        if not (self.cert_dir / f"{self.domain}_cert.pem").exists():
            make_self_signed_cert(self.cert_dir, self.domain)

    @property
    def log_file(self) -> Path:
        return self.data_dir / "prosody.log"

    def start(self, timeout: float = 30.0, attempts: int = 3) -> None:
        """As `_ChildServer.start`; a port chosen here (none given) that another process takes before
        Prosody binds it is chosen again, up to `attempts` times (Prosody itself runs on, on no port)."""
        for attempt in range(attempts):
            try:
                super().start(timeout)
                self._choose_port = False  # a restart must come back where its clients look for it
                return
            except PortTaken:
                if not self._choose_port or attempt == attempts - 1:
                    raise
                log.warning("XMPP port %d was taken before Prosody bound it: choosing another", self.port)
                self.port = free_port()

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

    def _log_since_start(self) -> str:
        try:
            with self.log_file.open("rb") as fh:
                fh.seek(self._log_offset)
                return fh.read().decode(errors="replace")
        except OSError:
            return ""

    def _command(self) -> tuple[list[str], dict[str, str]]:
        self._log_offset = self.log_file.stat().st_size if self.log_file.exists() else 0
        return ["prosody", "--config", str(self.config), "-F"], self.env()

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


def _run_embedded(args: argparse.Namespace) -> int:
    """Host pyjabber in this process until SIGTERM/SIGINT (the child side of EmbeddedXmppServer)."""
    # Lazy: pyjabber takes ~0.6 s and 80 MB to import; only the server's own process needs it.
    from loguru import logger
    from pyjabber.server import Server
    from pyjabber.server_parameters import Parameters

    remove_upload_dir_at_exit()
    logger.remove()
    logger.add(sys.stderr, level=args.log_level)
    data_dir = Path(args.data_dir)
    params = Parameters(
        host=args.domain, client_port=args.port, server_port=args.s2s_port,
        database_path=str(data_dir / "pyjabber.db"), database_in_memory=False,
        cert_path=str(data_dir / "certs"), message_persistence=args.message_persistence,
    )
    _close_registration(data_dir / ALLOWED_ACCOUNTS)
    _forget_unavailable_resources()
    server = Server(params)
    # pyjabber also listens on the host's "public" address (found by a UDP trick); a local farm must
    # stay on loopback, so that address is dropped before the listeners are created.
    server._public_ip = None
    # Its HTTP upload feature serves an admin page on a fixed port 9090 (two farms collide, and the
    # farm moves files over its own data plane). The feature itself must stay configured (pyjabber's
    # iq dispatch breaks without it), so only its web server is left unstarted.
    server._http_server = None
    asyncio.run(_serve(server, data_dir / READY_FILE))
    return 0


async def _serve(server: object, ready_file: Path) -> None:
    """Run pyjabber; once both its listeners are bound, write their ports (the OS chose those given as 0)."""
    running = asyncio.ensure_future(server.start())
    ready = asyncio.ensure_future(server.ready.wait())
    await asyncio.wait({running, ready}, return_when=asyncio.FIRST_COMPLETED)
    if ready.done() and not running.done():
        ports = {"port": server._client_listener.sockets[0].getsockname()[1],
                 "s2s_port": server._server_listener.sockets[0].getsockname()[1]}
        written_atomically(ready_file, lambda tmp: tmp.write_text(json.dumps(ports)), "the server's ports")
    ready.cancel()
    await running


def _close_registration(allowed: Path) -> None:
    """Refuse in-band registration of any user name not in `allowed` (when that file exists). pyjabber
    answers a registration IQ whether or not it advertises the feature, so its handler is wrapped."""
    from pyjabber.features.SASL import SASL as sasl_module

    original = sasl_module.SASL.handle_iq

    async def handle_iq(self, element: ET.Element) -> None:
        query = element.find("{jabber:iq:register}query")
        name = query.find("{jabber:iq:register}username") if query is not None else None
        if allowed.exists() and element.attrib.get("type") == "set" and name is not None \
                and (name.text or "") not in allowed.read_text().split():
            log.warning("in-band registration of %r refused: not an account of this farm", name.text)
            refusal = (f'<iq type="error" id="{element.attrib.get("id", "")}"><error type="auth">'
                       '<forbidden xmlns="urn:ietf:params:xml:ns:xmpp-stanzas"/></error></iq>')
            self._transport.write(refusal.encode())
            return None
        return await original(self, element)

    sasl_module.SASL.handle_iq = handle_iq


def _forget_unavailable_resources() -> None:
    """A resource that sent `unavailable` is forgotten, not kept as unavailable: pyjabber routes a message
    for a bare JID to the resources of the highest priority, and a stale entry of a cleanly stopped
    master (its old resource, with the priority it last announced) outranked the restarted master's new
    one, so a master restarted on a running server received nothing (measured: deaf for 60 s and more
    after SIGTERM and restart; fine after SIGKILL, which sends no presence)."""
    from pyjabber.features.presence import PresenceFeature as presence_module

    original = presence_module.Presence._handle_global_presence

    async def handle(self, jid, element: ET.Element):
        result = await original(self, jid, element)
        if element.attrib.get("type") == "unavailable":
            entries = self._online_status.get(jid.bare(), [])
            entries[:] = [e for e in entries if e[0] != jid.resource]
            if not entries:
                self._online_status.pop(jid.bare(), None)
        return result

    presence_module.Presence._handle_global_presence = handle


def main(argv: list[str] | None = None) -> int:
    """`embedded --domain D --port P --s2s-port Q --data-dir DIR`: host pyjabber in this process."""
    parser = argparse.ArgumentParser(prog="python -m core.transport.xmpp_server", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    emb = sub.add_parser("embedded", help="run SPADE's pyjabber server on 127.0.0.1 in the foreground")
    emb.add_argument("--domain", default="localhost", help="JID domain, also the host pyjabber binds")
    emb.add_argument("--port", type=int, default=5222, help="client port (0: a free one)")
    emb.add_argument("--s2s-port", type=int, default=5269, help="server-to-server port (loopback; 0: a free one)")
    emb.add_argument("--data-dir", required=True, help="directory of the database and certificate")
    emb.add_argument("--message-persistence", action="store_true", help="keep messages to offline JIDs")
    emb.add_argument("--log-level", default="WARNING")
    args = parser.parse_args(argv)
    if not resolves_to_loopback(args.domain):
        parser.error(f"--domain {args.domain!r} must resolve to a loopback address")
    with contextlib.suppress(KeyboardInterrupt):
        return _run_embedded(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
