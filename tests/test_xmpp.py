"""The XMPP layer with real processes: two FarmAgents in separate processes (tests/xmpp_peer.py) talk
through a real Prosody with TLS; refusals; a server restart."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from prosody_support import needs_prosody

from core.transport.xmpp import FarmAgent
from core.transport.xmpp_server import ProsodyServer, XmppServerError, free_port, port_accepts

REPO = Path(__file__).resolve().parent.parent
NAMES = ("echo", "ping", "friend", "mallory")  # the accounts the peers log in as
pytestmark = needs_prosody
PEER = REPO / "tests" / "xmpp_peer.py"
FIGURES: dict[str, object] = {}


class Peer:
    """A tests/xmpp_peer.py child process and the JSON events it prints."""

    def __init__(self, port: int, jid: str, password: str, mode: str, *extra: str, peers: str = "",
                 register: bool = False) -> None:
        cmd = [sys.executable, str(PEER), "--jid", jid, f"--password={password}", "--port", str(port),
               "--peers", peers, *(["--register"] if register else []), *extra, mode]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)))
        self.events: queue.Queue[dict] = queue.Queue()
        self.seen: list[dict] = []
        self.stderr: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=lambda: self.stderr.extend(self.proc.stderr), daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.events.put(json.loads(line))

    def wait_for(self, event: str, timeout: float = 30.0, **match: object) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                ev = self.events.get(timeout=0.1)
            except queue.Empty:
                continue
            self.seen.append(ev)
            if ev["event"] == event and all(ev.get(k) == v for k, v in match.items()):
                return ev
            if ev["event"] == "error" and event != "error":
                raise AssertionError(f"peer failed: {ev['reason']}\n{''.join(self.stderr[-20:])}")
        raise AssertionError(f"no {event!r} event within {timeout} s; saw {self.seen[-5:]}\n"
                             + "".join(self.stderr[-20:]))

    def drain(self) -> list[dict]:
        while True:
            try:
                self.seen.append(self.events.get_nowait())
            except queue.Empty:
                return self.seen

    def stop(self, timeout: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


class Accounts:
    """A Prosody on loopback with the peers' accounts (NAMES) made ahead, each exempt from the server's
    rate per client: the figures and refusals here are the agents' own (the server's rate has its test)."""

    def __init__(self, data_dir: Path) -> None:
        self.server = ProsodyServer(data_dir, unlimited=[f"{name}@localhost" for name in NAMES])
        self.passwords = self.server.register_all(NAMES)
        self.port = self.server.port

    def spawn(self, spawner, name: str, mode: str, /, *extra: str, **kwargs: object) -> Peer:
        """Peer `name`@localhost logging in with its password (`spawner`: the `peers` fixture)."""
        return spawner(self.port, f"{name}@localhost", self.passwords[name], mode, *extra, **kwargs)


@pytest.fixture()
def xmpp(tmp_path: Path):
    accounts = Accounts(tmp_path / "prosody")
    with accounts.server:
        yield accounts


@pytest.fixture()
def peers():
    started: list[Peer] = []

    def spawn(*args: object, **kwargs: object) -> Peer:
        peer = Peer(*args, **kwargs)
        started.append(peer)
        return peer

    yield spawn
    for peer in started:
        peer.stop()


def listening_sockets(pid: int) -> list[str]:
    """Local addresses on which process `pid` listens (TCP), read with `ss`."""
    out = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True).stdout
    return [line.split()[3] for line in out.splitlines() if f"pid={pid}," in line]


def ping_figures(xmpp: Accounts, peers) -> dict:
    echo = xmpp.spawn(peers, "echo", "echo", peers="ping@localhost")
    echo.wait_for("online")
    ping = xmpp.spawn(peers, "ping", "ping", "--to", "echo@localhost", "--count", "200", "--burst", "1000",
                      peers="echo@localhost")
    online = ping.wait_for("online")
    result = ping.wait_for("result", timeout=90)
    assert ping.stop() == 0
    return {"online": online, "result": result, "echo": echo, "ping": ping}


def test_unknown_senders_oversized_and_malformed_messages_are_refused(xmpp, peers) -> None:
    echo = xmpp.spawn(peers, "echo", "echo", peers="ping@localhost")
    echo.wait_for("online")
    ping = xmpp.spawn(peers, "ping", "stream", "--to", "echo@localhost", "--interval", "0.2", peers="echo@localhost")
    ping.wait_for("pong")
    intruder = xmpp.spawn(peers, "mallory", "send", "--to", "echo@localhost")
    refusal = echo.wait_for("refused", sender="mallory@localhost")
    assert refusal["kind"] == "sender"
    intruder.wait_for("sent")
    # The agent survived all of it: pongs still come back.
    seq = max(e["seq"] for e in ping.drain() if e["event"] == "pong")
    ping.wait_for("pong", seq=seq + 2, timeout=10)


def test_known_sender_oversized_and_bad_metadata_refused(xmpp, peers) -> None:
    echo = xmpp.spawn(peers, "echo", "echo", peers="friend@localhost")
    echo.wait_for("online")
    big = xmpp.spawn(peers, "friend", "send", "--to", "echo@localhost", "--body-size", "5000", "--linger", "0.5")
    assert echo.wait_for("refused", sender="friend@localhost")["kind"] == "size"
    assert big.stop() == 0
    bad = xmpp.spawn(peers, "friend", "send", "--to", "echo@localhost", "--ontology", "", "--linger", "0.5")
    refusal = echo.wait_for("refused", sender="friend@localhost")
    assert refusal["kind"] == "metadata" and "ontology" in refusal["reason"]
    assert bad.stop() == 0
    assert echo.proc.poll() is None  # still running


def test_a_flooding_sender_is_refused_unread_past_its_rate_and_the_others_are_heard(xmpp, peers) -> None:
    echo = xmpp.spawn(peers, "echo", "echo", "--rate", "5,20", peers="ping@localhost,friend@localhost")
    echo.wait_for("online")
    flood = xmpp.spawn(peers, "friend", "send", "--to", "echo@localhost", "--copies", "400", "--linger", "1")
    flood.wait_for("sent")
    assert flood.stop() == 0
    first = echo.wait_for("refused", sender="friend@localhost")
    assert first["kind"] == "rate" and "over 5 messages a second (burst 20)" in first["reason"]
    time.sleep(1.0)
    refused = [e for e in echo.drain() if e["event"] == "refused" and e["sender"] == "friend@localhost"]
    assert 250 <= len(refused) <= 380, len(refused)  # 400 sent: the burst of 20 and 5 a second pass
    ping = xmpp.spawn(peers, "ping", "stream", "--to", "echo@localhost", "--interval", "0.3", peers="echo@localhost")
    ping.wait_for("pong", seq=3, timeout=20)  # another sender's own allowance: it is heard


def test_a_senders_allowance_is_its_burst_then_its_rate() -> None:
    from core.transport import rates as r

    rates = r.SenderRates(rate=2.0, burst=3.0)
    assert [rates.allow("a", 0.0) for _ in range(5)] == [True, True, True, False, False]
    assert rates.report("a", 0.0) == 2 and rates.allow("b", 0.0)  # each sender its own bucket
    assert rates.allow("a", 0.5) and not rates.allow("a", 0.5)
    assert rates.report("a", 0.5) == 0  # reported under REPORT_S ago: it counts toward the next
    assert [rates.allow("a", 10.0) for _ in range(4)] == [True, True, True, False]  # refilled to the burst only
    assert rates.report("a", r.REPORT_S) == 2 and rates.report("a", 100.0) == 0
    with pytest.raises(ValueError, match="rate"):
        r.SenderRates(rate=0.0, burst=3.0)


def test_the_buckets_of_quiet_senders_are_dropped_once_there_are_many(monkeypatch) -> None:
    from core.transport import rates as r

    monkeypatch.setattr(r, "MAX_SENDERS", 3)
    rates = r.SenderRates(rate=1.0, burst=2.0)
    for name in ("a", "b", "c"):
        rates.allow(name, 0.0)
    rates.allow("c", 0.0)
    rates.allow("c", 0.0)  # c is still empty at 1.0, a and b full again
    rates.allow("d", 1.0)
    assert set(rates.buckets) == {"c", "d"}


@pytest.mark.slow
def test_both_agents_reconnect_by_themselves_after_a_server_restart(tmp_path, peers) -> None:
    xmpp = Accounts(tmp_path / "prosody")
    server = xmpp.server
    server.start()
    try:
        echo = xmpp.spawn(peers, "echo", "echo", peers="ping@localhost")
        echo.wait_for("online")
        ping = xmpp.spawn(peers, "ping", "stream", "--to", "echo@localhost", "--interval", "0.1",
                          peers="echo@localhost")
        before = ping.wait_for("pong", seq=5)
        stopped_at = time.time()
        server.restart(downtime=1.0)
        up_at = time.time()
        back_ping = ping.wait_for("reconnected", timeout=30)
        back_echo = echo.wait_for("reconnected", timeout=30)
        first_after = ping.wait_for("pong", timeout=30)
        while first_after["sent"] < up_at:
            first_after = ping.wait_for("pong", timeout=30)
        later = ping.wait_for("pong", seq=first_after["seq"] + 10, timeout=30)
        assert later["rtt_ms"] < 1000
    finally:
        server.stop()
    FIGURES["restart"] = {
        "outage_ping_s": round(back_ping["outage_s"], 2), "outage_echo_s": round(back_echo["outage_s"], 2),
        "server_down_s": round(up_at - stopped_at, 2),
        "first_pong_after_server_up_s": round(first_after["t"] - up_at, 2),
    }
    print("\nrestart:", FIGURES["restart"], "last pong before:", before["seq"])
    assert back_ping["outage_s"] < (up_at - stopped_at) + 10


def test_two_processes_through_prosody_with_tls_and_closed_registration(xmpp, peers) -> None:
    # Both exempt from the config's rate per client: the figures are Prosody's own, as the master sees it.
    assert listening_sockets(xmpp.server.pid) == [f"127.0.0.1:{xmpp.port}"]
    out = ping_figures(xmpp, peers)
    assert out["online"]["tls"] is True
    result = out["result"]
    assert result["count"] == 200
    assert result["burst_received"] == result["burst"] == 1000
    FIGURES["prosody"] = {k: result[k] for k in ("rtt_median_ms", "rtt_p95_ms", "msgs_per_s")}
    print("\nprosody:", FIGURES["prosody"])
    assert listening_sockets(out["echo"].proc.pid) == []  # SPADE's web interface is never started
    # Registration is closed: a new account cannot be made in-band, so the login fails.
    stranger = peers(xmpp.port, "stranger@localhost", "whatever", "send", "--to", "echo@localhost",
                     "--connect-timeout", "3", register=True)
    assert "login refused" in stranger.wait_for("error", timeout=30)["reason"]
    wrong = peers(xmpp.port, "echo@localhost", "wrong-password", "echo", "--connect-timeout", "3")
    assert "login refused" in wrong.wait_for("error", timeout=30)["reason"]


@pytest.mark.slow
def test_prosody_slows_a_client_that_floods_and_never_the_master(tmp_path, peers) -> None:
    """deploy/prosody's mod_limits: a client sending 300 KB at once is read at its rate (32 kB/s, so over
    9 s or more: 5 s is the bound, for slack), nothing is dropped, and master@ is exempt."""
    server = ProsodyServer(tmp_path / "prosody")
    passwords = server.register_all(["sink", "friend", "master"])
    server.start()
    try:
        sink = peers(server.port, "sink@localhost", passwords["sink"], "sink",
                     peers="friend@localhost,master@localhost")
        sink.wait_for("online")

        def flood(name: str) -> list[float]:
            sender = peers(server.port, f"{name}@localhost", passwords[name], "send", "--to", "sink@localhost",
                           "--copies", "300", "--body-size", "1000", "--linger", "30")
            sender.wait_for("sent")
            times = [sink.wait_for("got", timeout=40, sender=f"{name}@localhost")["t"] for _ in range(300)]
            sender.stop()
            return times

        friend, master = flood("friend"), flood("master")
        friend_s, master_s = friend[-1] - friend[0], master[-1] - master[0]
        assert friend_s >= 5.0, friend_s
        assert master_s < min(3.0, friend_s / 2), (master_s, friend_s)
        print(f"\nflood of 300 KB: the client's read over {friend_s:.1f} s, the master's over {master_s:.2f} s")
    finally:
        server.stop()


def test_prosody_whose_chosen_port_is_taken_before_it_binds_chooses_another(tmp_path) -> None:
    """Prosody runs on, listening nowhere, when its port is taken: start() waited 30 s for a port that
    never accepted, or, where the other process listens there, returned with clients talking to it."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))  # bound, not listening: only Prosody's own bind finds it taken
        port = taken.getsockname()[1]
        server = ProsodyServer(tmp_path / "chosen")
        server.port = port  # as if another process bound the port it chose, before it started
        server._prepare()
        with server:
            assert server.port != port and port_accepts("127.0.0.1", server.port)
            assert port not in [int(a.rsplit(":", 1)[1]) for a in listening_sockets(server.pid)]
        given = ProsodyServer(tmp_path / "given", port=port)  # a port the user gave is never changed
        with pytest.raises(XmppServerError, match=f"127.0.0.1:{port} is taken by another process"):
            given.start()
        assert given.port == port and not given.running


def test_prosody_refuses_a_rate_it_would_misread_naming_the_variable(tmp_path) -> None:
    """mod_limits reads "32768" as nothing and falls back to 3000 bytes a second with one log line."""
    with pytest.raises(XmppServerError, match="QUEKARO_XMPP_C2S_RATE: 32768 is not a rate like 32kb/s"):
        ProsodyServer(tmp_path / "prosody", c2s_rate="32768").start()


class FreezingRelay:
    """A TCP relay to a server on 127.0.0.1 that can go dead the way a pulled cable does: while frozen, bytes
    of open connections are held (neither delivered nor refused: no FIN, no RST) and new connections are
    refused; thawed, it relays again on the same port."""

    def __init__(self, target: int) -> None:
        self.target, self.port = target, free_port()
        self.flowing = asyncio.Event()
        self.server: asyncio.Server | None = None
        self.tasks: set[asyncio.Task] = set()

    async def thaw(self) -> None:
        self.server = await asyncio.start_server(self._relay, "127.0.0.1", self.port)
        self.flowing.set()

    def freeze(self) -> None:
        self.flowing.clear()
        self.server.close()

    async def stop(self) -> None:
        self.freeze()
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        self.tasks.add(task)
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target)
            await asyncio.gather(self._pipe(reader, up_writer), self._pipe(up_reader, writer), return_exceptions=True)
        finally:
            self.tasks.discard(task)

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                await self.flowing.wait()
                writer.write(data)
                await writer.drain()
        finally:
            writer.close()


@pytest.mark.slow
def test_a_dead_link_is_noticed_by_the_keepalive_and_the_agent_reconnects(tmp_path) -> None:
    """A link that goes silent without closing (a pulled cable, a host cut off) is noticed by the ping
    keepalive within its timeout, and the agent is back as soon as the server can be reached again. With
    SPADE's own keepalive (55 s) the agent stayed 'online' on the dead link and came back only when the
    kernel's retransmission happened to get through (~25 s after a 30 s outage, tests/test_multihost.py)."""

    server = ProsodyServer(tmp_path / "prosody")
    password = server.register("alive")

    async def scenario() -> tuple[float, float, int]:
        relay = FreezingRelay(server.port)
        await relay.thaw()
        agent = FarmAgent("alive@localhost", password, port=relay.port, server="127.0.0.1",
                          keepalive_s=0.5, keepalive_timeout_s=1.0)
        try:
            await agent.start()
            await asyncio.sleep(1.5)  # pings answered: a live link is left alone
            assert agent.online and agent.reconnects == 0
            relay.freeze()
            frozen_at = time.monotonic()
            while agent.online and time.monotonic() - frozen_at < 10:
                await asyncio.sleep(0.05)
            noticed = time.monotonic() - frozen_at
            await asyncio.sleep(2.0)
            assert not agent.online  # still cut off: no session
            await relay.thaw()
            thawed_at = time.monotonic()
            assert await agent.wait_online(timeout=15)
            return noticed, time.monotonic() - thawed_at, agent.reconnects
        finally:
            with contextlib.suppress(Exception):
                await agent.stop()
            await relay.stop()

    with server:
        noticed, back, reconnects = asyncio.run(scenario())
    print(f"\ndead link noticed after {noticed:.2f} s; back {back:.2f} s after the link")
    assert noticed < 3.0  # keepalive 0.5 s + timeout 1 s, not SPADE's 55 s
    assert back < 5.0 and reconnects == 1


def test_empty_pyjabber_folders_of_killed_processes_are_swept_once_stale(tmp_path) -> None:
    """pyjabber makes a folder at import and never removes it; a killed process cannot at exit."""
    from core.transport.tmp_cleanup import PREFIX, STALE_S, sweep_stale

    now = time.time()
    old, fresh, full, other = (tmp_path / f"{PREFIX}{n}" for n in ("old", "fresh", "full", "x"))
    for folder in (old, fresh, full):
        folder.mkdir()
    (full / "upload").write_text("kept")
    other.write_text("a file of that name")
    for path in (old, full, other):
        os.utime(path, (now - 2 * STALE_S, now - 2 * STALE_S))
    assert sweep_stale(tmp_path, now) == 1
    assert not old.exists() and fresh.is_dir() and (full / "upload").read_text() == "kept" and other.is_file()
