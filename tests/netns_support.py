"""Several hosts on one machine: Linux network namespaces on a bridge, for the multi-host tests.

`Network` makes one bridge in the root namespace (with the first address of a /24 test subnet of its
own, so that the test itself can reach the hosts like an admin's workstation on the LAN) and one
namespace per host, each with a veth pair whose outer end is a port of the bridge and whose inner end is
the host's `eth0` with the next free address of the subnet. A host reaches the others only through the
bridge: its namespace has nothing but `lo` and that `eth0`. `link_down(host)` pulls the host's cable (the
bridge port goes down, the host's `eth0` loses its carrier), `link_up(host)` plugs it back.

Bridged frames pass the root namespace's iptables FORWARD chain where br_netfilter is loaded, and a
Docker engine sets that chain's policy to DROP: the bridge gets its own ACCEPT rule (`-i BRIDGE -o
BRIDGE`), removed with it, so the test network works whatever the policy.

Names carry a prefix made of this process's pid (`qk` + 6 hex digits + a counter): every interface and
namespace a `Network` makes starts with it, `close()` removes them all (processes first, then links,
then namespaces) and checks that nothing is left, and a new `Network` first removes what a killed test
run left behind (names with the prefix of a pid that no longer runs). Needs root and iproute2; the
kernel here has no `netem`, so `rate_limit` uses `tbf`.
"""

from __future__ import annotations

import contextlib
import ipaddress
import itertools
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

PREFIX_RE = re.compile(r"^qk([0-9a-f]{6})[0-9a-f]")
_COUNTER = itertools.count()


class NetnsError(RuntimeError):
    """An `ip` command that failed while building or tearing down the test network."""


def ip(*args: str, check: bool = True) -> str:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if check and done.returncode != 0:
        raise NetnsError(f"ip {' '.join(args)}: {(done.stderr or done.stdout).strip()}")
    return done.stdout


def netns_missing() -> str | None:
    """Why namespaces cannot be made here (not root, no iproute2, no permission), or None."""
    if os.geteuid() != 0:
        return "needs root (network namespaces, veth pairs, a bridge)"
    if shutil.which("ip") is None:
        return "needs iproute2's `ip` (Debian package iproute2)"
    probe = f"qk{os.getpid():06x}f-probe"
    try:
        ip("netns", "add", probe)
    except NetnsError as exc:
        return f"cannot create a network namespace: {exc}"
    ip("netns", "del", probe, check=False)
    return None


def require_netns() -> None:
    """Skip the test with the reason when namespaces cannot be made, unless CI requires them
    (QUEKARO_REQUIRE_NETNS=1, set by .ci/run): then it fails, since a skipped multi-host test proves
    nothing."""
    reason = netns_missing()
    if reason is None:
        return
    if os.environ.get("QUEKARO_REQUIRE_NETNS"):
        pytest.fail(f"multi-host test required (QUEKARO_REQUIRE_NETNS) but {reason}")
    pytest.skip(reason)


@dataclass
class Host:
    """One namespace: its name, its address on the test subnet, and the bridge port of its cable."""

    name: str
    netns: str
    address: str
    port: str  # the veth end on the bridge (root namespace)
    procs: list[subprocess.Popen] = field(default_factory=list)


class Network:
    """A bridge and namespaces of one test (see the module's docstring); a context manager."""

    def __init__(self) -> None:
        sweep_leftovers()
        self.prefix = f"qk{os.getpid():06x}{next(_COUNTER) % 16:x}"
        self.bridge = f"{self.prefix}br"
        self.subnet = _free_subnet()
        hosts = self.subnet.hosts()
        self.gateway = str(next(hosts))  # the bridge's own address: the test's view of the LAN
        self._addresses = hosts
        self.hosts: dict[str, Host] = {}
        self._others: list[subprocess.Popen] = []
        self._made_bridge = False
        try:
            ip("link", "add", self.bridge, "type", "bridge")
            self._made_bridge = True
            ip("addr", "add", f"{self.gateway}/{self.subnet.prefixlen}", "dev", self.bridge)
            ip("link", "set", self.bridge, "up")
            _forward_rule("-I", self.bridge)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Network:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_host(self, name: str) -> Host:
        """A namespace `PREFIX-name` with `eth0` on the bridge and the next address of the subnet."""
        if not re.fullmatch(r"[a-z0-9]{1,4}", name) or name in self.hosts:
            raise ValueError(f"host name {name!r}: 1-4 lowercase letters or digits, unique")
        host = Host(name, f"{self.prefix}-{name}", str(next(self._addresses)), f"{self.prefix}{name}")
        self.hosts[name] = host
        ip("netns", "add", host.netns)
        ip("link", "add", host.port, "type", "veth", "peer", "name", "eth0", "netns", host.netns)
        ip("link", "set", host.port, "master", self.bridge, "up")
        ip("-n", host.netns, "addr", "add", f"{host.address}/{self.subnet.prefixlen}", "dev", "eth0")
        ip("-n", host.netns, "link", "set", "lo", "up")
        ip("-n", host.netns, "link", "set", "eth0", "up")
        return host

    # ---- the cable --------------------------------------------------------------------------------

    def link_down(self, name: str) -> None:
        """Unplug the host: its bridge port goes down (the host's eth0 keeps its address, without carrier)."""
        ip("link", "set", self.hosts[name].port, "down")

    def link_up(self, name: str) -> None:
        ip("link", "set", self.hosts[name].port, "up")

    def rate_limit(self, name: str, rate: str = "10mbit") -> None:
        """A narrow link towards the host (tbf on its bridge port; the kernel has no netem)."""
        ip("link", "show", self.hosts[name].port)  # fails clearly on an unknown host
        subprocess.run(["tc", "qdisc", "replace", "dev", self.hosts[name].port, "root", "tbf", "rate", rate,
                        "burst", "32kbit", "latency", "400ms"], check=True, capture_output=True)

    # ---- processes --------------------------------------------------------------------------------

    def spawn(self, name: str, cmd: list[str], log: Path, env: dict[str, str] | None = None,
              cwd: Path | None = None) -> subprocess.Popen:
        """Run `cmd` inside the host's namespace (`ip netns exec`, which execs it: the pid is the command's),
        in a session of its own so that `close()` can end it and its children; output appended to `log`."""
        host = self.hosts[name]
        with log.open("ab") as out:
            proc = subprocess.Popen(["ip", "netns", "exec", host.netns, *cmd], stdout=out, stderr=subprocess.STDOUT,
                                    env=env, cwd=cwd, start_new_session=True)
        host.procs.append(proc)
        return proc

    def can_connect(self, name: str, address: str, port: int, timeout: float = 2.0) -> bool:
        """Whether a TCP connection from inside the host's namespace to address:port succeeds now."""
        code = (f"import socket; socket.create_connection(({address!r}, {port}), timeout={timeout}).close()")
        done = subprocess.run(["ip", "netns", "exec", self.hosts[name].netns, sys.executable, "-c", code],
                              capture_output=True, check=False, timeout=timeout + 10)
        return done.returncode == 0

    # ---- teardown ---------------------------------------------------------------------------------

    def close(self) -> None:
        """End every process in the namespaces (SIGTERM to each session, SIGKILL after 10 s), delete the
        links and the namespaces, and check that none of them is left. Safe to call twice."""
        procs = [p for h in self.hosts.values() for p in h.procs] + self._others
        _end(procs)
        for host in self.hosts.values():  # anything else still inside (a child that left its session)
            for pid in ip("netns", "pids", host.netns, check=False).split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), signal.SIGKILL)
        for host in self.hosts.values():
            ip("link", "del", host.port, check=False)
            ip("netns", "del", host.netns, check=False)
        if self._made_bridge:
            _forward_rule("-D", self.bridge, check=False)
            ip("link", "del", self.bridge, check=False)
        left = leftovers(self.prefix)
        self.hosts.clear()
        self._made_bridge = False
        if left:
            raise NetnsError(f"left behind after the test: {', '.join(left)}")


def _end(procs: list[subprocess.Popen], timeout: float = 10.0) -> None:
    for proc in procs:
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for proc in procs:
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        with contextlib.suppress(ProcessLookupError):  # the session's other members (render children)
            os.killpg(proc.pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _forward_rule(action: str, bridge: str, check: bool = True) -> None:
    """Insert (-I) or delete (-D) the bridge's ACCEPT rule in FORWARD; nothing to do without iptables."""
    if shutil.which("iptables") is None:
        return
    done = subprocess.run(["iptables", action, "FORWARD", "-i", bridge, "-o", bridge, "-j", "ACCEPT"],
                          capture_output=True, text=True, check=False)
    if check and done.returncode != 0:
        raise NetnsError(f"iptables {action} FORWARD for {bridge}: {done.stderr.strip()}")


def _forward_bridges() -> list[str]:
    """The bridges that have a rule of `_forward_rule` in FORWARD."""
    if shutil.which("iptables") is None:
        return []
    rules = subprocess.run(["iptables", "-S", "FORWARD"], capture_output=True, text=True, check=False).stdout
    return [m.group(1) for m in re.finditer(r"^-A FORWARD -i (\S+) -o \1 -j ACCEPT$", rules, re.MULTILINE)]


def leftovers(prefix: str = "qk") -> list[str]:
    """Namespaces, links and FORWARD rules (by their bridge, `iptables:NAME`) whose names start with `prefix`."""
    names = [line.split()[0] for line in ip("netns", "list", check=False).splitlines() if line.strip()]
    links = [line.split()[0].split("@")[0] for line in ip("-br", "link", check=False).splitlines() if line.strip()]
    found = [n for n in names + links if n.startswith(prefix) and PREFIX_RE.match(n)]
    return found + [f"iptables:{b}" for b in _forward_bridges() if b.startswith(prefix) and PREFIX_RE.match(b)]


def sweep_leftovers() -> None:
    """Remove what a killed test run left behind: names with the prefix of a pid that no longer runs."""
    for name in leftovers():
        bridge = name.removeprefix("iptables:")
        pid = int(PREFIX_RE.match(bridge).group(1), 16)  # type: ignore[union-attr]
        if _alive(pid):
            continue
        if bridge != name:
            _forward_rule("-D", bridge, check=False)
        elif name in ip("netns", "list", check=False).split():
            for member in ip("netns", "pids", name, check=False).split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(member), signal.SIGKILL)
            ip("netns", "del", name, check=False)
        else:
            ip("link", "del", name, check=False)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _free_subnet() -> ipaddress.IPv4Network:
    """A random 10.x.y.0/24 that no address or route of this machine overlaps."""
    used = [ipaddress.ip_network(word, strict=False)
            for line in ip("-4", "route", "show", "table", "all", check=False).splitlines()
            + ip("-4", "-o", "addr", check=False).splitlines()
            for word in line.split() if re.fullmatch(r"\d+\.\d+\.\d+\.\d+(/\d+)?", word)]
    for _ in range(200):
        candidate = ipaddress.ip_network(f"10.{random.randrange(100, 250)}.{random.randrange(1, 255)}.0/24")
        if not any(candidate.overlaps(net) for net in used if net.prefixlen > 0):
            return candidate
    raise NetnsError("no free 10.x.y.0/24 subnet for the test network")
