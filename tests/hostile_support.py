"""A second local user attacking a farm (issue 62), for tests/test_hostile_user.py.

Two halves in one file of the standard library alone:

* the test's side (root): `intruder_missing`, `make_intruder` (a system account `quekaro-intruder`, made once
  and left in place: idempotent, safe when two runs race), `Intruder.run` (an attack run as that account with
  `setpriv`, its JSON answer returned), `vm_kib` (a process's memory from /proc);
* the intruder's side: `python3 hostile_support.py` reads one attack as JSON on stdin and prints its outcome
  as one JSON line. It needs nothing but Python's standard library: the virtualenv's interpreter is a link
  into a private home (here /root/.pyenv, /root 0700) that another user cannot read, and the repository may
  lie in such a folder too. `Intruder` copies this file into a world-readable folder of its own and runs it
  with the first interpreter the intruder can execute (the system's /usr/bin/python3 first).

The intruder's XMPP client is a bare stream (`RawStream`: a socket, STARTTLS by `ssl`, SASL PLAIN, in-band
registration), so that it can send what no library would: stanzas before authenticating, a forged `from`, a
forged authzid, megabytes of unclosed tags.
"""

from __future__ import annotations

import base64
import contextlib
import errno
import hashlib
import json
import os
import pwd
import shutil
import socket
import ssl
import subprocess
import sys
import time
import urllib.error
import urllib.request
import xml.etree.ElementTree as ET
from pathlib import Path

INTRUDER = "quekaro-intruder"
STREAMS = "http://etherx.jabber.org/streams"
SASL = "urn:ietf:params:xml:ns:xmpp-sasl"
TLS = "urn:ietf:params:xml:ns:xmpp-tls"
REGISTER = "jabber:iq:register"
REGISTER_FEATURE = "http://jabber.org/features/iq-register"
STREAM_HEADER = ("<?xml version='1.0'?><stream:stream to='{domain}' xmlns='jabber:client' "
                 "xmlns:stream='http://etherx.jabber.org/streams' version='1.0'>")


# ---- the test's side (root) ----------------------------------------------------------------------


def intruder_missing() -> str | None:
    """Why no second local account can be made and used here, or None."""
    if os.geteuid() != 0:
        return "needs root to make a second local account and run as it (CI runs as root)"
    for tool in ("useradd", "setpriv"):
        if shutil.which(tool) is None:
            return f"needs `{tool}` (Debian packages passwd, util-linux)"
    return None


def make_intruder() -> pwd.struct_passwd:
    """The account `quekaro-intruder` (a system account without home or shell), made if missing. Left in
    place afterwards: removing it while another run uses it would be the race, not making it twice."""
    try:
        return pwd.getpwnam(INTRUDER)
    except KeyError:
        pass
    done = subprocess.run(["useradd", "--system", "--no-create-home", "--shell", "/usr/sbin/nologin",
                           "--user-group", INTRUDER], capture_output=True, text=True, check=False)
    try:
        return pwd.getpwnam(INTRUDER)  # made here, or by a run beside this one (useradd then says exit 9)
    except KeyError:
        raise RuntimeError(f"useradd {INTRUDER} failed: {done.stderr.strip() or done.returncode}") from None


class Intruder:
    """Runs attacks as the account `user`: this file copied into `folder` (made world-readable), executed
    by the first interpreter of `pythons` that the account can run."""

    def __init__(self, user: pwd.struct_passwd, folder: Path, pythons: list[str]) -> None:
        self.uid, self.gid, self.name = user.pw_uid, user.pw_gid, user.pw_name
        if self.uid in (0, os.getuid()):
            raise RuntimeError(f"{self.name} is uid {self.uid}: not another user")
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        folder.chmod(0o755)
        self.script = folder / "intruder.py"
        shutil.copyfile(__file__, self.script)
        self.script.chmod(0o644)
        self.python = ""
        self.refused: dict[str, str] = {}  # interpreter -> why the intruder cannot run it
        for python in dict.fromkeys(p for p in pythons if p):
            done = self._setpriv([python, "-I", "-c", "import os, ssl; print(os.getuid())"], "", 30)
            if done.returncode == 0 and done.stdout.strip() == str(self.uid):
                self.python = python
                break
            self.refused[python] = (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]

    def _setpriv(self, cmd: list[str], stdin: str, timeout: float) -> subprocess.CompletedProcess:
        return subprocess.run(["setpriv", f"--reuid={self.uid}", f"--regid={self.gid}", "--clear-groups",
                               "--inh-caps=-all", "--reset-env", *cmd], input=stdin, capture_output=True,
                              text=True, timeout=timeout, cwd=self.folder, check=False)

    def run(self, attack: str, timeout: float = 120.0, **args: object) -> dict:
        """Run one attack as the intruder; its outcome (with `uid`, the uid it ran as)."""
        done = self._setpriv([self.python, "-I", str(self.script)], json.dumps({"attack": attack, **args}), timeout)
        lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
        assert done.returncode == 0 and lines, f"attack {attack}: exit {done.returncode}\n{done.stdout}\n{done.stderr}"
        return json.loads(lines[-1])


def vm_kib(pid: int, field: str = "VmRSS") -> int:
    """A field of /proc/PID/status in KiB (VmRSS: resident now; VmHWM: the most ever resident)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


# ---- the intruder's side -------------------------------------------------------------------------


class Closed(Exception):
    """The server closed the stream (or the connection)."""


class RawStream:
    """One client-to-server XMPP stream, written by hand."""

    def __init__(self, port: int, domain: str = "localhost", timeout: float = 10.0) -> None:
        self.domain, self.timeout = domain, timeout
        self.sock: socket.socket | ssl.SSLSocket = socket.create_connection(("127.0.0.1", port), timeout=timeout)
        self.said: list[str] = []  # every top-level element the server sent, as tag names (errors with reason)
        self.closed = False
        self._open()

    def _open(self) -> None:
        self.parser = ET.XMLPullParser(events=("start", "end"))
        self.depth = 0
        self.send(STREAM_HEADER.format(domain=self.domain))

    def send(self, text: str | bytes) -> None:
        self.sock.sendall(text.encode() if isinstance(text, str) else text)

    def element(self) -> ET.Element:
        """The next top-level element the server sends; Closed when it ends the stream or the connection."""
        deadline = time.monotonic() + self.timeout
        while True:
            for event, elem in self.parser.read_events():
                if event == "start":
                    self.depth += 1
                    continue
                self.depth -= 1
                if self.depth == 1:
                    self.said.append(_describe(elem))
                    if elem.tag == f"{{{STREAMS}}}error":
                        self.closed = True
                        raise Closed(_describe(elem))
                    return elem
                if self.depth == 0:
                    self.closed = True
                    raise Closed("</stream:stream>")
            if time.monotonic() > deadline:
                raise TimeoutError(f"no answer within {self.timeout:.0f} s")
            try:
                data = self.sock.recv(65536)
            except (ConnectionError, ssl.SSLError) as exc:
                self.closed = True
                raise Closed(f"connection {type(exc).__name__}") from None
            if not data:
                self.closed = True
                raise Closed("connection closed")
            try:
                self.parser.feed(data)
            except ET.ParseError as exc:
                raise Closed(f"not XML: {exc}") from None

    def features(self) -> ET.Element:
        while True:
            elem = self.element()
            if elem.tag == f"{{{STREAMS}}}features":
                return elem

    def starttls(self) -> ET.Element:
        """STARTTLS (the certificate is not checked: the intruder only probes), and the new stream's features."""
        self.send(f"<starttls xmlns='{TLS}'/>")
        answer = self.element()
        if answer.tag != f"{{{TLS}}}proceed":
            raise Closed(f"starttls answered {_describe(answer)}")
        context = ssl.create_default_context()
        context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
        self.sock = context.wrap_socket(self.sock, server_hostname=self.domain)
        self._open()
        return self.features()

    def answer(self) -> str:
        """What the server says next: an element's description, or how the stream ended."""
        try:
            return _describe(self.element())
        except (Closed, TimeoutError) as exc:
            return f"closed: {exc}" if isinstance(exc, Closed) else f"timeout: {exc}"


def _describe(elem: ET.Element) -> str:
    """`tag` or `tag(condition, ...)`: an element's local name and its children's (an error's condition)."""
    def local(tag: str) -> str:
        return tag.rsplit("}", 1)[-1]
    inner = [local(c.tag) for c in elem.iter() if c is not elem and local(c.tag) not in ("text",)]
    return f"{local(elem.tag)}({', '.join(inner)})" if inner else local(elem.tag)


def _mechanisms(features: ET.Element) -> list[str]:
    return [m.text or "" for m in features.iter(f"{{{SASL}}}mechanism")]


def _secure_stream(port: int) -> tuple[RawStream, ET.Element]:
    stream = RawStream(port)
    stream.features()
    return stream, stream.starttls()


def attack_register(args: dict) -> dict:
    """In-band registration (XEP-0077) of `user` before any login, after STARTTLS as a client must."""
    stream, features = _secure_stream(args["port"])
    offered = features.find(f"{{{REGISTER_FEATURE}}}register") is not None
    stream.send(f"<iq type='get' id='reg-get'><query xmlns='{REGISTER}'/></iq>")
    form = stream.answer()
    stream.send(f"<iq type='set' id='reg-set'><query xmlns='{REGISTER}'><username>{args['user']}</username>"
                f"<password>{args['password']}</password></query></iq>")
    answer = stream.answer()
    return {"offered": offered, "form": form, "answer": answer, "mechanisms": _mechanisms(features)}


def login(port: int, user: str, password: str, authzid: str = "", resource: str = "intruder"
          ) -> tuple[RawStream, dict]:
    """SASL PLAIN as `user` with `password`, naming `authzid` (another identity asked for) if given, after
    STARTTLS; on success a resource bound. The stream and {"answer", "mechanisms", "bound"}."""
    stream, features = _secure_stream(port)
    outcome: dict = {"mechanisms": _mechanisms(features), "bound": None}
    if "PLAIN" not in outcome["mechanisms"]:
        return stream, {**outcome, "answer": "no PLAIN offered"}
    plain = f"{authzid}\0{user}\0{password}".encode()
    stream.send(f"<auth xmlns='{SASL}' mechanism='PLAIN'>{base64.b64encode(plain).decode()}</auth>")
    outcome["answer"] = stream.answer()
    if outcome["answer"] == "success":
        stream._open()
        stream.features()
        stream.send("<iq type='set' id='bind'><bind xmlns='urn:ietf:params:xml:ns:xmpp-bind'>"
                    f"<resource>{resource}</resource></bind></iq>")
        bound = stream.element()
        outcome["bound"] = next((j.text for j in bound.iter("{urn:ietf:params:xml:ns:xmpp-bind}jid")), None)
        stream.send("<presence/>")
    return stream, outcome


def attack_login(args: dict) -> dict:
    """`login`; then, if it succeeded and `forged` is given, one message sent with `forged` as its `from`."""
    stream, outcome = login(args["port"], args["user"], args["password"], args.get("authzid", ""))
    if outcome["bound"] and args.get("forged"):
        stream.send(f"<message from='{args['forged']}' to='{args['to']}' type='chat'><body>{args['body']}</body>"
                    "</message>")
        time.sleep(1.0)  # the server routes it before the stream ends
    if not stream.closed:
        stream.send("</stream:stream>")
    return outcome


def attack_forge(args: dict) -> dict:
    """A message whose `from` names the master, sent without logging in: on the plain stream, and after
    STARTTLS. What the server answered to each."""
    message = (f"<message from='{args['forged']}' to='{args['to']}' type='chat'><body>{args['body']}</body>"
               "</message>")
    outcome = {}
    stream = RawStream(args["port"])
    stream.features()
    stream.send(message)
    outcome["plain"] = stream.answer()
    stream, _ = _secure_stream(args["port"])
    stream.send(message)
    outcome["tls"] = stream.answer()
    return outcome


def attack_nest(args: dict) -> dict:
    """A stream header, then `bytes` of unclosed nested tags (`<a>` after `<a>`) before any login, for at
    most `limit_s` seconds: how many bytes the connection took, whether and when the server ended it (None:
    it was still open at the end), and what it said."""
    sock = socket.create_connection(("127.0.0.1", args["port"]), timeout=args["limit_s"])
    sock.sendall(STREAM_HEADER.format(domain="localhost").encode())
    chunk, sent, error = b"<a>" * ((64 << 10) // 3), 0, ""
    started = time.monotonic()
    deadline = started + args["limit_s"]
    closed_after = None
    try:
        while sent < args["bytes"] and time.monotonic() < deadline:
            sock.settimeout(max(0.1, deadline - time.monotonic()))
            sent += sock.send(chunk[: args["bytes"] - sent])
    except TimeoutError:
        error = "timeout"
    except OSError as exc:
        error = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
        closed_after = time.monotonic() - started
    said = b""
    try:
        while closed_after is None and time.monotonic() < deadline:
            sock.settimeout(max(0.1, deadline - time.monotonic()))
            data = sock.recv(65536)
            if not data:
                closed_after = time.monotonic() - started
            said += data
    except TimeoutError:
        pass  # still open at the deadline
    except OSError as exc:
        closed_after = time.monotonic() - started
        error = error or errno.errorcode.get(exc.errno or 0, type(exc).__name__)
    if closed_after is not None and not said:  # what it said before it reset the connection, if anything
        sock.setblocking(False)
        with contextlib.suppress(OSError):
            said = sock.recv(65536)
    sock.close()
    return {"sent": sent, "error": error, "closed_after_s": closed_after, "said": said.decode(errors="replace")[-600:]}


def attack_read(args: dict) -> dict:
    """Open (or list) each path: `ok` and a hash of what was read, or the error's name."""
    found = {}
    for path in args["paths"]:
        try:
            if os.path.isdir(path):
                found[path] = "ok " + ",".join(sorted(os.listdir(path)))
            else:
                with open(path, "rb") as fh:
                    found[path] = "ok " + hashlib.sha256(fh.read()).hexdigest()
        except OSError as exc:
            found[path] = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
    return {"found": found}


def attack_signal(args: dict) -> dict:
    """SIGTERM to each pid: `ok` or the error's name."""
    found = {}
    for pid in args["pids"]:
        try:
            os.kill(pid, 15)
            found[str(pid)] = "ok"
        except OSError as exc:
            found[str(pid)] = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
    return {"found": found}


def attack_http(args: dict) -> dict:
    """Requests to the master's HTTP server without its tokens: each answer's status and start."""
    found = {}
    for name, (method, path, headers, body) in args["requests"].items():
        request = urllib.request.Request(args["url"] + path, method=method, headers=headers,
                                         data=body.encode("latin-1") if body is not None else None)
        try:
            with urllib.request.urlopen(request, timeout=20) as answer:
                found[name] = [answer.status, answer.read(200).decode(errors="replace")]
        except urllib.error.HTTPError as exc:
            found[name] = [exc.code, exc.read(200).decode(errors="replace")]
        except OSError as exc:
            found[name] = [0, f"{type(exc).__name__}: {exc}"]
    return {"found": found}


def attack_fill(args: dict) -> dict:
    """Write a file of its own at `path` until the filesystem is full: the bytes written and the error."""
    written, error = 0, ""
    block = b"\xa5" * (1 << 20)
    try:
        with open(args["path"], "wb") as fh:
            while True:
                written += fh.write(block)
                fh.flush()
    except OSError as exc:
        error = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
    stat = os.statvfs(os.path.dirname(args["path"]))
    return {"written": written, "error": error, "free": stat.f_bavail * stat.f_frsize}


def attack_remove(args: dict) -> dict:
    os.unlink(args["path"])
    return {"removed": args["path"]}


def attack_whoami(args: dict) -> dict:
    return {"uid": os.getuid(), "euid": os.geteuid(), "groups": os.getgroups()}


ATTACKS = {name[len("attack_"):]: fn for name, fn in globals().items() if name.startswith("attack_")}


def main() -> int:
    args = json.loads(sys.stdin.read())
    started = time.monotonic()
    outcome = ATTACKS[args["attack"]](args)
    print(json.dumps({**outcome, "uid": os.getuid(), "seconds": round(time.monotonic() - started, 3)}),
          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
