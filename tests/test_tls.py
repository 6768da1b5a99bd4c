"""The farm's CA and the data plane's TLS: certificates that verify against the farm's CA only and for
the names they were issued for, a real HTTPS data plane (the master's guarded aiohttp server), and the
master refusing plain HTTP across a network unless told --insecure-http."""

from __future__ import annotations

import asyncio
import datetime as dt
import ssl
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web
from cryptography import x509

from agents.render_agent import url_refusal
from core.errors import QuekaroError
from core.transport.tls import TlsError, check_names, client_context, is_loopback, issue, make_ca, server_context
from master.data_plane import serve
from master.service import MasterConfig


@pytest.fixture(scope="module")
def ca(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("ca")
    make_ca(folder)
    issue(folder, "master", ["127.0.0.1", "master.farm.test"], folder)
    return folder


async def fetch(url: str, context: ssl.SSLContext) -> int:
    async with aiohttp.ClientSession() as session, session.get(url, ssl=context) as resp:
        return resp.status


async def with_https_server(ca: Path, check) -> None:
    async def healthz(_request: web.Request) -> web.Response:
        return web.json_response({"ok": True})

    app = web.Application()
    app.router.add_get("/healthz", healthz)
    runner, port = await serve(app, "127.0.0.1", 0, ssl_context=server_context(ca / "master.pem", ca / "master.key"))
    try:
        await check(port)
    finally:
        await runner.cleanup()


def test_https_verifies_against_the_farms_ca_only(ca: Path, tmp_path: Path) -> None:
    make_ca(tmp_path / "other")

    async def check(port: int) -> None:
        assert await fetch(f"https://127.0.0.1:{port}/healthz", client_context(ca / "ca.pem")) == 200
        with pytest.raises(aiohttp.ClientConnectorCertificateError):
            await fetch(f"https://127.0.0.1:{port}/healthz", client_context(tmp_path / "other" / "ca.pem"))
        with pytest.raises(aiohttp.ClientConnectorCertificateError):  # the system's CAs do not know it
            await fetch(f"https://127.0.0.1:{port}/healthz", client_context(None))
        with pytest.raises(aiohttp.ClientConnectorCertificateError):  # a name it was not issued for
            await fetch(f"https://localhost:{port}/healthz", client_context(ca / "ca.pem"))

    asyncio.run(with_https_server(ca, check))


def test_a_farm_keeps_its_ca_and_bad_files_are_named(ca: Path, tmp_path: Path) -> None:
    with pytest.raises(TlsError, match="already there"):
        make_ca(ca)
    with pytest.raises(TlsError, match=str(tmp_path)):
        issue(tmp_path, "x", ["h"], tmp_path)
    (tmp_path / "bad.pem").write_text("not a certificate")
    with pytest.raises(TlsError, match=r"bad\.pem"):
        server_context(tmp_path / "bad.pem", ca / "master.key")
    assert oct((ca / "ca.key").stat().st_mode & 0o777) == "0o600"


@pytest.mark.parametrize(("host", "loopback"), [("127.0.0.1", True), ("127.8.0.1", True), ("::1", True),
                                                ("[::1]", True), ("localhost", True), ("10.0.0.2", False),
                                                ("0.0.0.0", False), ("master", False), (None, False)])
def test_loopback(host: str | None, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_a_certificate_that_does_not_name_the_masters_public_host_is_refused_naming_both(ca: Path,
                                                                                         tmp_path: Path) -> None:
    """The master started with it, and every agent then refused its data plane (a hostname mismatch)."""
    cert = ca / "master.pem"
    for host in ("127.0.0.1", "master.farm.test", "MASTER.farm.test."):
        check_names(cert, host, "--public-url")
    with pytest.raises(TlsError, match=r"master.pem: names master.farm.test, 127.0.0.1, not master-host of "
                                       r"--public-url"):
        check_names(cert, "master-host", "--public-url")
    with pytest.raises(TlsError, match=r"not 10\.0\.0\.2"):
        check_names(cert, "10.0.0.2", "--public-url")
    issue(ca, "wild", ["*.farm.test"], tmp_path)
    check_names(tmp_path / "wild.pem", "agent.farm.test", "--public-url")
    with pytest.raises(TlsError):  # a wildcard covers one label only
        check_names(tmp_path / "wild.pem", "a.b.farm.test", "--public-url")


def test_the_master_says_how_its_data_plane_travels(ca: Path, tmp_path: Path) -> None:
    cert, key = ca / "master.pem", ca / "master.key"
    assert MasterConfig(tmp_path).data_plane() == "http (loopback)"
    https = MasterConfig(tmp_path, http_host="0.0.0.0", tls_cert=cert, tls_key=key,
                         public_url="https://master.farm.test:8765")
    assert https.data_plane() == "https"
    assert MasterConfig(tmp_path, http_host="0.0.0.0", tls_cert=cert, tls_key=key).url.startswith("https://")
    with pytest.raises(QuekaroError, match="--insecure-http"):
        MasterConfig(tmp_path, http_host="0.0.0.0", public_url="http://10.0.0.2:8765").data_plane()
    with pytest.raises(QuekaroError, match="--insecure-http"):  # bound to loopback, announced elsewhere
        MasterConfig(tmp_path, public_url="http://master-host:8765").data_plane()
    insecure = MasterConfig(tmp_path, http_host="0.0.0.0", public_url="http://10.0.0.2:8765", insecure_http=True)
    assert "insecure" in insecure.data_plane()
    with pytest.raises(QuekaroError, match="HTTPS needs"):
        MasterConfig(tmp_path, public_url="https://10.0.0.2:8765").data_plane()
    with pytest.raises(QuekaroError, match="go together"):
        MasterConfig(tmp_path, tls_cert=cert).data_plane()
    with pytest.raises(QuekaroError, match="with --http-port 0: the port is chosen at start"):
        MasterConfig(tmp_path, http_port=0, public_url="http://127.0.0.1:8765").data_plane()
    assert MasterConfig(tmp_path, http_port=0).data_plane() == "http (loopback)"  # its URL names the bound port
    with pytest.raises(QuekaroError, match="use https"):
        MasterConfig(tmp_path, tls_cert=cert, tls_key=key, public_url="http://127.0.0.1:1").data_plane()
    with pytest.raises(QuekaroError, match=r"names master\.farm\.test, 127\.0\.0\.1, not master-host of --public-url"):
        MasterConfig(tmp_path, tls_cert=cert, tls_key=key, public_url="https://master-host:8765").data_plane()


def test_an_agent_refuses_plain_http_across_a_network_unless_told() -> None:
    assert url_refusal("https://10.0.0.2:8765/jobs/j/bundle", False) is None
    assert url_refusal("http://127.0.0.1:8765/jobs/j/bundle", False) is None
    assert "--insecure-http" in url_refusal("http://10.0.0.2:8765/jobs/j/bundle", False)
    assert url_refusal("http://10.0.0.2:8765/jobs/j/bundle", True) is None


def test_certificates_hold_for_hosts_whose_clocks_are_off(ca: Path) -> None:
    """A host whose clock is 10 minutes behind (or ahead) still accepts the farm's certificates
    (tests/test_multihost.py runs such agents under libfaketime): valid from a day before issuance."""
    now = dt.datetime.now(dt.UTC)
    for name in ("ca.pem", "master.pem"):
        cert = x509.load_pem_x509_certificate((ca / name).read_bytes())
        assert cert.not_valid_before_utc <= now - dt.timedelta(minutes=10)
        assert cert.not_valid_after_utc >= now + dt.timedelta(days=365)
