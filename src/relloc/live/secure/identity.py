"""What a Zenoh config makes of a session: authenticated (mutual TLS) or not, as whom."""

from __future__ import annotations

import base64
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["Security", "check_endpoints", "security_of"]


@dataclass(frozen=True)
class Security:
    """What a Zenoh config makes of a session: authenticated or not, as whom."""

    authenticated: bool
    """Mutual TLS on every endpoint, with a CA and a certificate of its own."""
    identity: str | None
    """The common name of its certificate."""
    issuer: str | None
    """The common name of the certificate's issuer (the team's CA)."""
    access_control: bool
    why: str
    """Why it is not authenticated (empty when it is)."""

    def describe(self) -> str:
        """One line for people."""
        acl = "access control on" if self.access_control else "no access control"
        if self.authenticated:
            return f"authenticated as {self.identity!r} (mutual TLS, {self.issuer}; {acl})"
        return f"not authenticated: {self.why} ({acl})"


def _get(config: Any, key: str) -> Any:
    try:
        return json.loads(config.get_json(key))
    except Exception:  # zenoh raises on unknown keys
        return None


def _file_tls(path: Path | None) -> dict[str, Any]:
    """The ``transport.link.tls`` section of a config file written as JSON (as
    :func:`~relloc.live.secure.certificates.write_secure_dir` does, ``//`` comments allowed);
    empty for other JSON5. Zenoh hides the embedded (base64) certificates of a loaded config,
    so they are read here."""
    if path is None:
        return {}
    try:
        text = "\n".join(
            ln for ln in path.read_text().splitlines() if not ln.lstrip().startswith("//")
        )
        return dict(json.loads(text)["transport"]["link"]["tls"])
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def _certificate(tls: dict[str, Any]) -> Any:
    from cryptography import x509

    raw = tls.get("connect_certificate_base64")
    if raw:
        return x509.load_pem_x509_certificate(base64.b64decode(raw))
    path = tls.get("connect_certificate")
    return x509.load_pem_x509_certificate(Path(path).read_bytes()) if path else None


def _common_name(name: Any) -> str:
    from cryptography.x509.oid import NameOID

    attrs = name.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(attrs[0].value) if attrs else name.rfc4514_string()


def security_of(config: Any, file: Path | None = None) -> Security:
    """The :class:`Security` of a ``zenoh.Config`` (after the command's options are applied)
    loaded from ``file``."""
    endpoints = [
        *(_get(config, "listen/endpoints") or []),
        *(_get(config, "connect/endpoints") or []),
    ]
    if isinstance(endpoints, dict):  # per-mode endpoints: judge them all
        endpoints = [e for v in endpoints.values() for e in v]
    acl = _get(config, "access_control") or {}
    acl_on = bool(acl.get("enabled"))
    tls = {k: v for k, v in (_get(config, "transport/link/tls") or {}).items() if v is not None}
    tls = {**_file_tls(file), **tls}
    protocols = _get(config, "transport/link/protocols")
    if protocols != ["tls"]:
        return Security(False, None, None, acl_on, "other protocols than tls/ are allowed")
    if not tls.get("enable_mtls"):
        return Security(False, None, None, acl_on, "mutual TLS is off")
    plain = [e for e in endpoints if not str(e).startswith("tls/")]
    if plain:
        return Security(False, None, None, acl_on, f"endpoints without TLS: {', '.join(plain)}")
    cert = _certificate(tls)
    if cert is None:
        return Security(False, None, None, acl_on, "no certificate of its own")
    return Security(True, _common_name(cert.subject), _common_name(cert.issuer), acl_on, "")


def check_endpoints(endpoints: Iterable[str]) -> None:
    """A secure session speaks TLS only: raise ``ValueError`` for any other endpoint."""
    plain = [e for e in endpoints if not e.startswith("tls/")]
    if plain:
        raise ValueError(
            f"a secure session takes tls/ endpoints only (mutual TLS), not {', '.join(plain)}"
        )
