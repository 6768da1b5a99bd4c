"""core.transport.peers: the local user at the other end of a loopback connection, read from /proc."""

from __future__ import annotations

import getpass
import socket

from core.transport.peers import describe_peer, local_uid


def test_a_loopback_peer_is_named_by_the_user_that_owns_its_socket() -> None:
    with socket.create_server(("127.0.0.1", 0)) as server, \
            socket.create_connection(server.getsockname()) as client:
        accepted, peer = server.accept()
        with accepted:
            ours = accepted.getsockname()
            assert peer == client.getsockname()
            assert describe_peer(peer, ours) == f"127.0.0.1:{peer[1]} (local user {getpass.getuser()})"
            assert local_uid(peer[1], ours[1] + 1 if ours[1] < 65535 else 1) is None  # not connected to that port


def test_a_peer_elsewhere_or_unknown_is_its_address_alone() -> None:
    assert describe_peer(("192.0.2.7", 4000), ("192.0.2.1", 8765)) == "192.0.2.7:4000"
    assert describe_peer(None, None) == "(unknown peer)"
