"""The team's private CA, a certificate per role and the secure directory that holds them.

Keys are EC P-256; every certificate names ``localhost``, ``127.0.0.1`` and the given hosts.
Private keys are written readable by the owner only.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from relloc.config import TeamConfig
from relloc.live.secure.access import access_control, grants, role_config, roles
from relloc.ros.interfaces import RosInterface

__all__ = ["SecureDirError", "write_secure_dir"]

CA_DAYS = 3650
CERT_DAYS = 825


class SecureDirError(ValueError):
    """A secure directory cannot be written (it exists) or read."""


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


def _key() -> Any:
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )


def _cert_pem(cert: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return bytes(cert.public_bytes(serialization.Encoding.PEM))


def _name(common_name: str) -> Any:
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "relloc"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _ca(team: str) -> tuple[Any, Any]:
    """A self-signed CA that may sign end-entity certificates only (path length 0)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes

    key = _key()
    name = _name(f"relloc {team} CA")
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def _alt_names(hosts: Sequence[str]) -> list[Any]:
    from cryptography import x509

    names: list[Any] = []
    for host in dict.fromkeys(["localhost", "127.0.0.1", *hosts]):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def _issue(ca_key: Any, ca_cert: Any, common_name: str, hosts: Sequence[str]) -> tuple[Any, Any]:
    """An end-entity certificate for TLS servers and clients (a peer is both)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = _key()
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=CERT_DAYS))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(_alt_names(hosts)), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert


def _write(path: Path, data: bytes, private: bool) -> None:
    """Write a file; a private one is created with mode 0600 (never readable by others, not
    even for a moment)."""
    mode = 0o600 if private else 0o644
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    os.chmod(path, mode)


def write_secure_dir(
    config: TeamConfig,
    out: Path,
    *,
    hosts: Sequence[str] = (),
    interface: RosInterface | None = None,
    prefix: str = "",
    estimate_prefix: str = "relloc",
    force: bool = False,
) -> list[Path]:
    """Write the CA, a certificate and a Zenoh config per role into ``out``; the paths written.

    Raises :class:`SecureDirError` if ``out`` exists and ``force`` is not given.
    """
    if out.exists() and not force:
        raise SecureDirError(f"{out} exists: give --force to replace its CA, keys and configs")
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    granted = grants(config, interface, prefix, estimate_prefix)
    acl = access_control(granted)
    ca_key, ca_cert = _ca(config.name)
    ca_pem = _cert_pem(ca_cert)
    written = [out / "ca.pem", out / "ca.key"]
    _write(written[0], ca_pem, private=False)
    _write(written[1], _key_pem(ca_key), private=True)
    for role in roles(config):
        key, cert = _issue(ca_key, ca_cert, role, hosts)
        cert_pem, key_pem = _cert_pem(cert), _key_pem(key)
        header = (
            f"// relloc secure init: Zenoh config of role {role!r} for team {config.name!r}.\n"
            "// Mutual TLS with the team's CA and the team's access control; it holds this\n"
            "// role's private key: keep it readable by its owner only (docs/howto/secure.md).\n"
        )
        body = json.dumps(role_config(role, ca_pem, cert_pem, key_pem, acl), indent=2)
        _write(out / f"{role}.pem", cert_pem, private=False)
        _write(out / f"{role}.json5", (header + body + "\n").encode(), private=True)
        written += [out / f"{role}.pem", out / f"{role}.json5"]
    return written
