"""The farm's own certificate authority, and TLS contexts for its links (XMPP and the HTTP data plane).

A farm spanning hosts makes one CA (`make_ca`) and issues from it a certificate for the XMPP server (its
domain) and one for the master's HTTPS (its host names and addresses); every process is given the CA's
certificate and verifies its peers against it. Keys are RSA 2048 (what Prosody and Python's ssl take
everywhere), written owner-only. Built on `cryptography` (pyca), not on calls to openssl.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import ssl
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from core.errors import QuekaroError

CA_CERT, CA_KEY = "ca.pem", "ca.key"
VALID_DAYS = 3650


class TlsError(QuekaroError):
    """A certificate or key that cannot be made, read or used, naming the file."""


def make_ca(folder: Path, name: str = "QUEKARO farm CA") -> Path:
    """Create `folder`/ca.pem and ca.key (refused if they exist: a farm keeps its CA); returns ca.pem."""
    folder.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = folder / CA_CERT, folder / CA_KEY
    if cert_path.exists() or key_path.exists():
        raise TlsError(f"{folder}: a CA is already there ({CA_CERT}, {CA_KEY}); a farm keeps its CA")
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    cert = (_builder(subject, subject, key.public_key())
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
            .sign(key, hashes.SHA256()))
    _write_key(key_path, key)
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert_path


def issue(ca_folder: Path, name: str, hosts: list[str], out: Path) -> tuple[Path, Path]:
    """A server certificate signed by the CA in `ca_folder` for `hosts` (DNS names or IP addresses):
    `out`/`name`.pem and `name`.key. Returns (certificate, key)."""
    if not hosts:
        raise TlsError(f"certificate {name!r}: give at least one host name or address")
    ca_cert, ca_key = _load_ca(ca_folder)
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hosts[0])])
    cert = (_builder(subject, ca_cert.subject, key.public_key())
            .add_extension(x509.SubjectAlternativeName([_general_name(h) for h in hosts]), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
            .sign(ca_key, hashes.SHA256()))
    out.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = out / f"{name}.pem", out / f"{name}.key"
    _write_key(key_path, key)
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert_path, key_path


def server_context(cert: Path, key: Path) -> ssl.SSLContext:
    """TLS 1.2+ for a server presenting `cert` (refused, naming the files, when they do not load)."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(str(cert), str(key))
    except (OSError, ssl.SSLError) as exc:
        raise TlsError(f"{cert} / {key}: cannot serve TLS with them: {exc}") from exc
    return context


def check_names(cert: Path, host: str, what: str) -> None:
    """Refuse (TlsError) a certificate whose names do not include `host`: every client verifying it would
    refuse the connection, far from the cause. Its names: subjectAltName's DNS names (one-label wildcards)
    and IP addresses; without that extension, its common name, as Python's clients fall back to."""
    dns, ips = _cert_names(cert)
    if _names_host(dns, ips, host):
        return
    listed = ", ".join([*dns, *(str(ip) for ip in ips)]) or "nothing"
    raise TlsError(f"{cert}: names {listed}, not {host} of {what}; clients would refuse it "
                   f"(issue one for that name: quekaro ca issue --dir CA NAME {host})")


def _cert_names(cert: Path) -> tuple[list[str], list[ipaddress.IPv4Address | ipaddress.IPv6Address]]:
    try:
        loaded = x509.load_pem_x509_certificate(cert.read_bytes())
    except (OSError, ValueError) as exc:
        raise TlsError(f"{cert}: cannot read the certificate ({exc})") from exc
    try:
        names = loaded.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return [str(a.value) for a in loaded.subject.get_attributes_for_oid(NameOID.COMMON_NAME)], []
    return names.get_values_for_type(x509.DNSName), names.get_values_for_type(x509.IPAddress)


def _names_host(dns: list[str], ips: list, host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")) in ips
    except ValueError:
        pass
    wanted = host.lower().rstrip(".")
    for name in (n.lower().rstrip(".") for n in dns):
        parent = wanted.partition(".")[2]
        if name == wanted or (name.startswith("*.") and "." in name[2:] and parent == name[2:]):
            return True
    return False


def client_context(ca_file: Path | None) -> ssl.SSLContext:
    """TLS 1.2+ for a client verifying the server's certificate and name against `ca_file` (the farm's
    CA), or against the system's CAs when None."""
    context = ssl.create_default_context()
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    if ca_file is not None:
        try:
            context.load_verify_locations(cafile=str(ca_file))
        except (OSError, ssl.SSLError) as exc:
            raise TlsError(f"{ca_file}: cannot read the CA certificate: {exc}") from exc
    return context


def is_loopback(host: str | None) -> bool:
    """Whether `host` names this machine only (127/8, ::1, localhost): plain HTTP may stay there."""
    if host in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address((host or "").strip("[]")).is_loopback
    except ValueError:
        return False


def _builder(subject: x509.Name, issuer: x509.Name, public_key: rsa.RSAPublicKey) -> x509.CertificateBuilder:
    now = dt.datetime.now(dt.UTC)
    return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer).public_key(public_key)
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(days=1)).not_valid_after(now + dt.timedelta(days=VALID_DAYS)))


def _general_name(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def _write_key(path: Path, key: rsa.RSAPrivateKey) -> None:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.TraditionalOpenSSL,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(data)


def _load_ca(folder: Path) -> tuple[x509.Certificate, rsa.RSAPrivateKey]:
    try:
        cert = x509.load_pem_x509_certificate((folder / CA_CERT).read_bytes())
        key = serialization.load_pem_private_key((folder / CA_KEY).read_bytes(), password=None)
    except (OSError, ValueError) as exc:
        raise TlsError(f"{folder}: no usable CA ({CA_CERT}, {CA_KEY}): {exc}") from exc
    return cert, key
