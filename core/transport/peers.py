"""Who is at the other end of a TCP connection, for the logs of refusals.

On loopback, the address says nothing on a shared machine: the local user who owns the peer's socket
does. Linux lists every TCP socket with its owner's uid in /proc/net/tcp and /proc/net/tcp6; the
peer's socket is the one whose local end is the peer's address and whose remote end is ours.
"""

from __future__ import annotations

import ipaddress
import pwd
from pathlib import Path

PROC_TABLES = (Path("/proc/net/tcp"), Path("/proc/net/tcp6"))


def describe_peer(peer: tuple | None, ours: tuple | None) -> str:
    """'HOST:PORT', with '(local user NAME)' for a loopback peer whose socket this machine lists."""
    if not peer:
        return "(unknown peer)"
    host, port = str(peer[0]), int(peer[1])
    text = f"{host}:{port}"
    if ours and _is_loopback(host):
        uid = local_uid(port, int(ours[1]))
        if uid is not None:
            text += f" (local user {_user_name(uid)})"
    return text


def local_uid(peer_port: int, our_port: int, tables: tuple[Path, ...] = PROC_TABLES) -> int | None:
    """The uid owning the loopback socket bound to `peer_port` and connected to `our_port`, or None."""
    for table in tables:
        try:
            lines = table.read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 7 and _port(fields[1]) == peer_port and _port(fields[2]) == our_port:
                return int(fields[7])
    return None


def _port(address: str) -> int:
    """The port of /proc/net/tcp's 'HEXADDR:HEXPORT'."""
    return int(address.rsplit(":", 1)[1], 16)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.split("%")[0]).is_loopback
    except ValueError:  # not an address (a Unix socket's peer)
        return False


def _user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"
