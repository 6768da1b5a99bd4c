"""The HTTP data plane on a real aiohttp server on 127.0.0.1: bundle fetch and tile upload, and refusals."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import io
import socket
import tarfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from disk_support import small_tmpfs

from agents.transfer import TransferError, fetch_bundle, upload_tile
from core.errors import QuekaroError
from core.image.tiles import Tile, write_tile
from core.model.geometry import Rect
from core.scene.bundle import BundleError, make_bundle
from master.data_plane import create_app, serve

CORE = Rect(16, 8, 24, 16)
IMAGE = (640, 480)
BAND = 2
TOKEN = "t0k3n-unit-3"


class Farm:
    """The master's side for the tests: provider callbacks over plain dicts, a server in a thread."""

    def __init__(self, tmp: Path, **options) -> None:
        self.tmp = tmp
        self.units: dict[tuple[str, int], tuple[str, Rect, tuple[int, int]]] = {("job1", 3): (TOKEN, CORE, IMAGE)}
        self.bundles: dict[str, tuple[Path, str]] = {}
        self.tiles: list[tuple] = []
        self.bundle_calls = 0
        self.fail_on_tile = False
        self.keep_awarded = False
        self.options = options
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    def expected(self, job: str, unit: int, token: str):
        """The unit's rectangle and image, if `token` is its award's (the auction's check, as the master makes it)."""
        slot = self.units.get((job, unit))
        return None if slot is None or slot[0] != token else slot[1:]

    def bundle(self, job: str):
        self.bundle_calls += 1
        return self.bundles.get(job)

    async def on_tile(self, job, unit, path, sha256, token, agent):
        if self.fail_on_tile:
            raise RuntimeError("store is read-only")
        self.tiles.append((job, unit, path, sha256, agent, path.read_bytes()))
        if not self.keep_awarded:
            self.units.pop((job, unit), None)  # the unit is done: no longer awaiting a tile

    def start(self, port: int = 0) -> str:
        app = create_app(self.expected, self.bundle, self.on_tile, self.tmp / "jobs", **self.options)
        self.thread.start()
        self.runner, self.port = asyncio.run_coroutine_threadsafe(serve(app, "127.0.0.1", port),
                                                                  self.loop).result(10)
        return f"http://127.0.0.1:{self.port}"

    def stop(self) -> None:
        asyncio.run_coroutine_threadsafe(self.runner.cleanup(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)

    def leftovers(self) -> list[Path]:
        return [p for p in (self.tmp / "jobs").rglob("*") if p.is_file()]


@pytest.fixture
def farm(tmp_path):
    farm = Farm(tmp_path)
    farm.url = farm.start()
    yield farm
    farm.stop()


def _tile(tmp: Path, name: str, rect: Rect | None = None, core: Rect = CORE, seed: int = 0,
          unit: int | None = 3, job: str = "job1") -> Path:
    rect = rect or core.window(BAND, *IMAGE)
    pixels = np.random.default_rng(seed).random((rect.h, rect.w, 3), dtype=np.float32)
    meta = {"spp": 4, "band": BAND, "job_id": job, **({"unit_index": unit} if unit is not None else {})}
    return write_tile(tmp / name, Tile(pixels, rect, core, meta))


def _unit_url(farm: Farm, job: str = "job1", unit: int | str = 3) -> str:
    return f"{farm.url}/jobs/{job}/units/{unit}/tile"


async def _put(url: str, body: bytes, token: str = TOKEN, sha: str | None = None) -> tuple[int, dict]:
    import aiohttp

    headers = {"X-Quekaro-Token": token, "X-Content-SHA256": sha or hashlib.sha256(body).hexdigest()}
    async with aiohttp.ClientSession() as session, session.put(url, data=body, headers=headers) as resp:
        return resp.status, await resp.json(content_type=None)


def _refused(farm: Farm, coro, status: int, match: str) -> None:
    with pytest.raises(TransferError, match=match) as err:
        asyncio.run(coro)
    assert err.value.status == status
    assert farm.tiles == [] and farm.leftovers() == []


# ---- uploads ---------------------------------------------------------------------------------


def test_upload_is_stored_durably_then_reported(farm, tmp_path):
    path = _tile(tmp_path, "t.exr")
    answer = asyncio.run(upload_tile(_unit_url(farm), TOKEN, path, agent="agent-a@farm"))
    assert answer["status"] == "accepted"
    (job, unit, stored, sha, agent, data), = farm.tiles
    assert (job, unit, agent) == ("job1", 3, "agent-a@farm")
    assert data == path.read_bytes() and sha == hashlib.sha256(data).hexdigest() == answer["sha256"]
    assert stored == tmp_path / "jobs" / "job1" / "tiles" / "unit-3.exr"
    assert farm.leftovers() == [stored]  # no temporary file left beside it


def test_duplicate_upload_is_harmless(farm, tmp_path):
    path = _tile(tmp_path, "t.exr")
    asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))
    again = asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))
    assert again["status"] == "duplicate" and len(farm.tiles) == 1
    other = _tile(tmp_path, "other.exr", seed=1)
    with pytest.raises(TransferError, match="no current award of unit 3") as err:
        asyncio.run(upload_tile(_unit_url(farm), TOKEN, other))
    assert err.value.status == 403
    assert (tmp_path / "jobs/job1/tiles/unit-3.exr").read_bytes() == path.read_bytes()


def test_every_upload_without_the_token_gets_one_answer(farm, tmp_path):
    """Without the award's token, a PUT to an awarded unit, and to a finished one with the accepted tile or
    any other content, all get the same answer: nobody learns a unit's state or whether a sha256 matches."""
    path = _tile(tmp_path, "t.exr")
    answers = []

    def stranger(body: Path) -> None:
        with pytest.raises(TransferError) as err:
            asyncio.run(upload_tile(_unit_url(farm), "ab" * 16, body))
        answers.append((err.value.status, str(err.value).split(": ", 1)[1]))

    stranger(path)  # while the unit is awarded
    asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))
    stranger(path)  # done: the accepted tile
    stranger(_tile(tmp_path, "other.exr", seed=1))  # done: something else
    assert len(set(answers)) == 1 and answers[0][0] == 403, answers


def test_duplicate_while_still_awarded_is_not_reported_twice(farm, tmp_path):
    farm.keep_awarded = True  # the master has not acted on the tile yet: the unit still awaits one
    path = _tile(tmp_path, "t.exr")
    asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))
    assert asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))["status"] == "duplicate"
    assert len(farm.tiles) == 1


@pytest.mark.parametrize("token", ["wrong", "", TOKEN + "x"])
def test_wrong_token_is_403_and_job_unharmed(farm, tmp_path, token):
    path = _tile(tmp_path, "t.exr")
    _refused(farm, upload_tile(_unit_url(farm), token, path), 403, "matches the X-Quekaro-Token sent")
    assert asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))["status"] == "accepted"


def test_wrong_hash_is_422(farm, tmp_path):
    path = _tile(tmp_path, "t.exr")
    _refused(farm, upload_tile(_unit_url(farm), TOKEN, path, sha256="0" * 64), 422, "differs from")
    status, body = asyncio.run(_put(_unit_url(farm), path.read_bytes(), sha="not-hex"))
    assert status == 400 and "64 hex digits" in body["error"]
    assert farm.leftovers() == []


@pytest.mark.parametrize(("rect", "core", "match"), [
    (Rect(0, 0, 30, 30), Rect(2, 2, 24, 16), "is not the window"),  # another window entirely
    (Rect(14, 6, 28, 20), Rect(16, 8, 24, 16), None),  # control: band 2 is fine
    (Rect(14, 6, 29, 20), Rect(16, 8, 24, 16), "is not the window"),  # uneven band
    (Rect(16, 8, 24, 16), Rect(16, 8, 24, 16), None),  # band 0 is fine
    (Rect(15, 8, 26, 16), Rect(17, 8, 24, 16), "is not the window"),  # tile claims another unit
    (Rect(12, 4, 32, 24), Rect(14, 6, 28, 20), "tile says its unit is"),  # core attr disagrees
])
def test_wrong_dimensions_are_422(farm, tmp_path, rect, core, match):
    path = _tile(tmp_path, "t.exr", rect=rect, core=core)
    if match is None:
        assert asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))["status"] == "accepted"
        return
    _refused(farm, upload_tile(_unit_url(farm), TOKEN, path), 422, match)


@pytest.mark.parametrize(("rect", "match"), [
    (Rect(0, 0, 28, 20), None),  # the window shifted inside at the corner: both bands on the far sides
    (Rect(0, 0, 26, 18), None),  # band 1 shifted (band 2 clipped looks the same, and is as good a tile)
    (Rect(0, 0, 27, 18), "is not the window"),  # no one band: 3 px across, 2 down
    (Rect(0, 0, 30, 20), "is not the window"),  # the far side wider than the band it lacks
])
def test_a_window_at_the_image_edge_is_shifted_inside(farm, tmp_path, rect, match):
    core = Rect(0, 0, 24, 16)
    farm.units[("job1", 5)] = (TOKEN, core, IMAGE)
    path = _tile(tmp_path, "edge.exr", rect=rect, core=core, unit=5)
    if match is None:
        assert asyncio.run(upload_tile(_unit_url(farm, unit=5), TOKEN, path))["status"] == "accepted"
        return
    _refused(farm, upload_tile(_unit_url(farm, unit=5), TOKEN, path), 422, match)


def test_not_exr_and_wrong_channels_are_422(farm, tmp_path):
    import OpenEXR

    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"P6\n2 2\n255\n" + bytes(12))
    _refused(farm, upload_tile(_unit_url(farm), TOKEN, junk), 422, "not an EXR")
    fake = tmp_path / "fake.exr"
    fake.write_bytes(b"\x76\x2f\x31\x01" + bytes(400))
    _refused(farm, upload_tile(_unit_url(farm), TOKEN, fake), 422, "unreadable EXR header")
    r = CORE.window(BAND, *IMAGE)
    half = tmp_path / "half.exr"
    header = {"dataWindow": ((r.x, r.y), (r.x1 - 1, r.y1 - 1)), "quekaro_core": "16 8 24 16"}
    with OpenEXR.File(header, {"RGB": np.zeros((r.h, r.w, 3), np.float16)}) as exr:
        exr.write(str(half))
    _refused(farm, upload_tile(_unit_url(farm), TOKEN, half), 422, "float16, a tile needs float32")


def test_unknown_job_or_unit_gets_the_strangers_answer_and_malformed_ids_404(farm, tmp_path):
    path = _tile(tmp_path, "t.exr")
    for url in (_unit_url(farm, "nojob"), _unit_url(farm, unit=4)):  # well formed: no hint it does not exist
        with pytest.raises(TransferError, match="no current award of unit") as err:
            asyncio.run(upload_tile(url, TOKEN, path))
        assert err.value.status == 403
    # Not ASCII digits: '²' is a digit to str.isdigit, not to int() (a 500), and '١' (Arabic-Indic) was unit 1.
    for url in (_unit_url(farm, unit="x"), _unit_url(farm, job=".."), _unit_url(farm, unit="%C2%B2"),
                _unit_url(farm, unit="%D9%A1"), _unit_url(farm, job="job1%0A")):
        with pytest.raises(TransferError) as err:
            asyncio.run(upload_tile(url, TOKEN, path))
        assert err.value.status == 404
    assert farm.leftovers() == []


def test_too_big_is_413_declared_or_streamed(tmp_path):
    farm = Farm(tmp_path, max_tile_bytes=64 << 10)
    farm.url = farm.start()
    try:
        path = _tile(tmp_path, "t.exr")  # ~9 KiB: fits
        big = _tile(tmp_path, "big.exr", rect=Rect(0, 0, 120, 100), core=Rect(16, 8, 24, 16))
        _refused(farm, upload_tile(_unit_url(farm), TOKEN, big), 413, "exceeds the limit")

        async def chunked():
            import aiohttp

            async def body():
                for _ in range(100):
                    yield b"\0" * 4096

            headers = {"X-Quekaro-Token": TOKEN, "X-Content-SHA256": "0" * 64}
            async with aiohttp.ClientSession() as session, \
                    session.put(_unit_url(farm), data=body(), headers=headers) as resp:
                return resp.status, await resp.json()

        status, answer = asyncio.run(chunked())  # no Content-Length: caught while streaming
        assert status == 413 and "exceeds the limit" in answer["error"]
        assert farm.leftovers() == []
        assert asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))["status"] == "accepted"
    finally:
        farm.stop()


def test_on_tile_failure_is_500_file_removed_then_retry_works(farm, tmp_path):
    path = _tile(tmp_path, "t.exr")
    farm.fail_on_tile = True
    _refused(farm, upload_tile(_unit_url(farm), TOKEN, path, retries=1, backoff_s=0.01), 500,
             "could not record the tile")
    farm.fail_on_tile = False
    assert asyncio.run(upload_tile(_unit_url(farm), TOKEN, path))["status"] == "accepted"


def test_upload_retries_until_the_server_is_up(tmp_path):
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    farm = Farm(tmp_path)
    path = _tile(tmp_path, "t.exr")
    url = f"http://127.0.0.1:{port}/jobs/job1/units/3/tile"
    with pytest.raises(TransferError, match="after 2 attempts"):
        asyncio.run(upload_tile(url, TOKEN, path, retries=1, backoff_s=0.01))
    starter = threading.Timer(0.3, farm.start, args=(port,))
    starter.start()
    try:
        assert asyncio.run(upload_tile(url, TOKEN, path, retries=6, backoff_s=0.1))["status"] == "accepted"
    finally:
        starter.join()
        farm.stop()


def test_16_mib_tile_round_trip(farm, tmp_path):
    side = 1200  # 1200^2 px x 12 B of float32 RGB noise: over 16 MiB after ZIP compression
    core = Rect(BAND, BAND, side - 2 * BAND, side - 2 * BAND)
    farm.units[("job1", 7)] = (TOKEN, core, (side, side))
    path = _tile(tmp_path, "big.exr", rect=Rect(0, 0, side, side), core=core, unit=7)
    assert path.stat().st_size > 16 << 20
    start = time.perf_counter()
    answer = asyncio.run(upload_tile(_unit_url(farm, unit=7), TOKEN, path))
    elapsed = time.perf_counter() - start
    assert answer["status"] == "accepted" and answer["bytes"] == path.stat().st_size
    print(f"16 MiB tile: {elapsed * 1000:.0f} ms upload + validation")


# ---- bundles ---------------------------------------------------------------------------------


def _scene(tmp: Path) -> Path:
    folder = tmp / "src"
    (folder / "meshes").mkdir(parents=True)
    (folder / "meshes" / "a.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    scene = folder / "scene.xml"
    scene.write_text("<scene version='3.0.0'><shape type='obj'>"
                     "<string name='filename' value='meshes/a.obj'/></shape></scene>")
    return scene


def test_bundle_fetch_checks_hash_and_caches(farm, tmp_path):
    info = make_bundle(_scene(tmp_path), {"spp": "4"}, tmp_path / "b.tar")
    farm.bundles["job1"] = (info.path, info.sha256)
    dest = tmp_path / "agent" / info.sha256
    url = f"{farm.url}/jobs/job1/bundle"
    with pytest.raises(TransferError, match="differs from the job's"):
        asyncio.run(fetch_bundle(url, "f" * 64, tmp_path / "agent" / "bad"))
    assert not (tmp_path / "agent" / "bad").exists()
    scene = asyncio.run(fetch_bundle(url, info.sha256, dest))
    assert scene == dest / "scene.xml" and (dest / "meshes" / "a.obj").is_file()
    calls = farm.bundle_calls
    assert asyncio.run(fetch_bundle(url, info.sha256, dest)) == scene
    assert farm.bundle_calls == calls  # cache hit: no request
    assert sorted(p.name for p in (tmp_path / "agent").iterdir()) == [info.sha256]
    with pytest.raises(TransferError, match="no bundle for job") as err:
        asyncio.run(fetch_bundle(f"{farm.url}/jobs/job2/bundle", info.sha256, tmp_path / "agent" / "x"))
    assert err.value.status == 404


def test_hostile_bundle_with_the_right_hash_is_still_refused(farm, tmp_path):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        info = tarfile.TarInfo("../../escape.txt")
        info.size = 5
        tar.addfile(info, io.BytesIO(b"pwned"))
    path = tmp_path / "evil.tar"
    path.write_bytes(buf.getvalue())
    sha = hashlib.sha256(buf.getvalue()).hexdigest()
    farm.bundles["job1"] = (path, sha)
    with pytest.raises(BundleError):
        asyncio.run(fetch_bundle(f"{farm.url}/jobs/job1/bundle", sha, tmp_path / "agent" / sha))
    assert not (tmp_path / "agent" / sha).exists() and not (tmp_path / "escape.txt").exists()
    assert list((tmp_path / "agent").iterdir()) == []


def test_bundle_token_when_required(tmp_path):
    farm = Farm(tmp_path, authorize_bundle=lambda job, token: token == TOKEN)
    url = farm.start()
    try:
        info = make_bundle(_scene(tmp_path), None, tmp_path / "b.tar")
        farm.bundles["job1"] = (info.path, info.sha256)
        with pytest.raises(TransferError, match="X-Quekaro-Token") as err:
            asyncio.run(fetch_bundle(f"{url}/jobs/job1/bundle", info.sha256, tmp_path / "a" / "1"))
        assert err.value.status == 403
        scene = asyncio.run(fetch_bundle(f"{url}/jobs/job1/bundle", info.sha256, tmp_path / "a" / "2",
                                         token=TOKEN))
        assert scene.read_bytes() == (tmp_path / "src" / "scene.xml").read_bytes()
    finally:
        farm.stop()


def test_a_tile_whose_header_names_no_unit_or_another_is_refused(farm, tmp_path):
    """Assembly reads which unit a tile is: a header without it (or naming another) never gets in."""
    for unit in (None, 4):
        path = _tile(tmp_path, f"t{unit}.exr", unit=unit)
        _refused(farm, upload_tile(_unit_url(farm), TOKEN, path), 422, f"tile header names unit {unit}")
    assert asyncio.run(upload_tile(_unit_url(farm), TOKEN, _tile(tmp_path, "ok.exr")))["status"] == "accepted"


@pytest.fixture
def small_disk(tmp_path):
    """A real 256 KiB filesystem for the master's tiles."""
    with small_tmpfs(tmp_path / "small", "256k") as mount:
        yield mount


def test_a_full_disk_is_a_507_and_the_tile_waits_on_its_agent(small_disk, tmp_path):
    """ENOSPC on the master: 507 'disk full on the master' (never blamed on the agent); the agent keeps
    asking, and the upload goes through once space is freed."""
    farm = Farm(small_disk)
    farm.url = farm.start()
    try:
        (small_disk / "jobs").mkdir(exist_ok=True)
        filler = small_disk / "filler"
        with filler.open("wb") as fh, contextlib.suppress(OSError):
            fh.write(b"\0" * (1 << 20))  # fills the 256 KiB
        path = _tile(tmp_path, "t.exr")
        with pytest.raises(TransferError) as err:
            asyncio.run(upload_tile(_unit_url(farm), TOKEN, path, disk_full_wait_s=0.0, retries=0))
        assert err.value.status == 507 and "disk full on the master" in str(err.value)
        assert [p for p in (small_disk / "jobs").rglob("*") if p.is_file()] == []  # no partial file

        async def free_space_later() -> None:
            await asyncio.sleep(1.0)
            filler.unlink()

        async def upload_while_freeing() -> dict:
            freeing = asyncio.create_task(free_space_later())
            answer = await upload_tile(_unit_url(farm), TOKEN, path, disk_full_wait_s=30.0, retries=0,
                                       backoff_s=0.1)
            await freeing
            return answer

        assert asyncio.run(upload_while_freeing())["status"] == "accepted"
    finally:
        farm.stop()


def _idle_connection_closed_within(url: str, send: bytes, seconds: float) -> float:
    """Send `send` and nothing more; the seconds until the server closes the connection."""
    import socket
    from urllib.parse import urlparse

    where = urlparse(url)
    start = time.monotonic()
    with socket.create_connection((where.hostname, where.port), timeout=seconds) as sock:
        sock.sendall(send)
        try:
            while sock.recv(4096):
                pass
        except TimeoutError:
            return float("inf")
    return time.monotonic() - start


def test_trickled_headers_and_bodies_are_cut_off(tmp_path, monkeypatch):
    """Slowloris: a client that never finishes its headers is disconnected after the header limit; a
    body that falls behind the minimum rate gets 408. One request per connection (keep-alive off)."""
    import master.http_guard as guard

    monkeypatch.setattr(guard, "HEADER_TIMEOUT_S", 1.0)
    monkeypatch.setattr(guard, "BODY_GRACE_S", 1.0)
    farm = Farm(tmp_path)
    farm.url = farm.start()
    try:
        took = _idle_connection_closed_within(farm.url, b"PUT /jobs/job1/units/3/tile HTTP/1.1\r\nHost: x\r\n", 10)
        assert took < 5, f"a connection with unfinished headers stayed open {took:.1f} s"
        body_start = (f"PUT /jobs/job1/units/3/tile HTTP/1.1\r\nHost: x\r\nX-Quekaro-Token: {TOKEN}\r\n"
                      f"X-Content-SHA256: {'0' * 64}\r\nContent-Length: 100000\r\n\r\n").encode() + b"x" * 10
        took = _idle_connection_closed_within(farm.url, body_start, 10)
        assert took < 5, f"a stalled body kept its connection {took:.1f} s"
        answer = asyncio.run(upload_tile(_unit_url(farm), TOKEN, _tile(tmp_path, "ok.exr")))
        assert answer["status"] == "accepted"  # a normal client is not hurt
    finally:
        farm.stop()


@contextlib.contextmanager
def _unanswering_port():
    """A port whose connections are never taken, as behind a firewall that drops packets: a listening
    socket with a full accept queue, whose SYNs the kernel drops."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(0)
        port = server.getsockname()[1]
        queued = [socket.socket() for _ in range(3)]
        try:
            for sock in queued:
                sock.setblocking(False)
                with contextlib.suppress(BlockingIOError):
                    sock.connect(("127.0.0.1", port))
            time.sleep(0.5)
            yield port
        finally:
            for sock in queued:
                sock.close()


def test_a_master_that_never_takes_a_connection_fails_a_transfer_at_the_connect_timeout(tmp_path, monkeypatch):
    """A firewall that drops packets left a bundle fetch waiting its whole 300 s, past the unit's render
    deadline, the agent saying nothing of why."""
    from agents import transfer

    monkeypatch.setattr(transfer, "CONNECT_TIMEOUT_S", 2.0)
    with _unanswering_port() as port:
        url = f"http://127.0.0.1:{port}/jobs/j/bundle"
        for transfer_once in (lambda: fetch_bundle(url, "ab" * 32, tmp_path / "b", timeout_s=120),
                              lambda: upload_tile(url, TOKEN, _tile(tmp_path, "t.exr"), retries=0, timeout_s=120)):
            started = time.monotonic()
            with pytest.raises(TransferError, match=r"(?i)timeout"):
                asyncio.run(transfer_once())
            assert time.monotonic() - started < 30


def test_the_cli_says_at_once_that_a_master_never_takes_a_connection(monkeypatch):
    """`quekaro submit` to a port a firewall drops waited 2 min 15 s (the system's SYN retries)."""
    from farm import client as farm_client

    monkeypatch.setattr(farm_client, "CONNECT_TIMEOUT_S", 2.0)
    with _unanswering_port() as port:
        started = time.monotonic()
        with pytest.raises(QuekaroError, match="no answer to a connection within 2 s"):
            farm_client.FarmClient(f"http://127.0.0.1:{port}", "token").jobs()
        assert time.monotonic() - started < 30
