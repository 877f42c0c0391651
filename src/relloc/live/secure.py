"""Authenticated, authorised Zenoh for a team: a private CA, certificates and role configs.

:func:`write_secure_dir` (``relloc secure init``) writes, for one team config:

* ``ca.pem`` and ``ca.key``: a private certificate authority (EC P-256, self-signed);
* per role a certificate ``<role>.pem`` signed by it (common name = the role) and a Zenoh
  JSON5 config ``<role>.json5``: mutual TLS on ``tls/`` endpoints only (the CA, the role's
  certificate and its private key embedded in base64, so that the file alone is what a
  machine needs) and the team's access control. The roles are ``serve``, ``navigate``,
  ``team`` (``sim-robots`` and ``replay``, which speak for the whole team) and
  ``robot-<name>`` per robot.

Private keys (``ca.key`` and every ``.json5``) are written readable by the owner only. Every
certificate names ``localhost``, ``127.0.0.1`` and the given hosts (any role may listen in
peer mode).

The access control is the same in every file, because each Zenoh node judges what reaches it
by the common name of the certificate on the link it came from (``ingress``): by default
nothing may be published (``put``/``delete``); a robot may publish its own topics (its
odometry, the ranges its UWB node measures, its detections and sightings), ``team`` every
robot topic and the motion capture, ``serve`` the estimates (``relloc/**``), ``navigate`` the
commanded robots' ``cmd_vel``. Declarations (subscribers, liveliness tokens, queries) are
allowed between team members: they let a member receive, never speak. A node forwarding for
others is judged as itself, so the members must link directly (a full mesh of endpoints).

Zenoh reports a refusal only in its trace log (``zenoh::net::routing::interceptor::
access_control``, on stdout: ``... CertCommonName(r1) ... is unauthorized to Put (ingress) on
r2/odom``); :class:`AccessRefusals` captures that stream and counts them.
"""

from __future__ import annotations

import base64
import datetime
import ipaddress
import json
import os
import re
import sys
import threading
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relloc.config import TeamConfig
from relloc.live.publish import cmd_vel_channel
from relloc.ros.interfaces import RosInterface
from relloc.sources.zenoh_keys import route_scopes

__all__ = [
    "NAVIGATE",
    "SERVE",
    "TEAM",
    "AccessRefusals",
    "SecureDirError",
    "Security",
    "access_control",
    "check_endpoints",
    "grants",
    "robot_role",
    "role_config",
    "roles",
    "security_of",
    "write_secure_dir",
]

SERVE = "serve"
NAVIGATE = "navigate"
TEAM = "team"
CA_DAYS = 3650
CERT_DAYS = 825
DECLARATIONS = (
    "declare_subscriber",
    "declare_queryable",
    "declare_liveliness_subscriber",
    "liveliness_token",
    "liveliness_query",
    "query",
    "reply",
)
"""Messages that let a member receive: allowed both ways between members."""
ACL_TARGET = "zenoh::net::routing::interceptor::access_control"


class SecureDirError(ValueError):
    """A secure directory cannot be written (it exists) or read."""


def robot_role(robot: str) -> str:
    """The role (and certificate common name) of a robot: ``robot-<name>``."""
    return f"robot-{robot}"


def roles(config: TeamConfig) -> list[str]:
    """Every role of a team, in the order the files are written."""
    return [SERVE, NAVIGATE, TEAM, *(robot_role(r) for r in config.robot_names)]


# ============================================================================ who may publish what
def _expr(iface: RosInterface, topic_key: str) -> str:
    """The key expression of one topic's samples (any type name and hash with rmw_zenoh)."""
    return iface.subscription_expr(topic_key)


def grants(
    config: TeamConfig,
    interface: RosInterface | None = None,
    prefix: str = "",
    estimate_prefix: str = "relloc",
) -> dict[str, list[str]]:
    """Each role's key expressions it may publish on (``put``), derived from the team config
    with the keys the live commands use (:class:`~relloc.ros.interfaces.RosInterface`)."""
    iface = interface or RosInterface()
    own: dict[str, list[str]] = {robot_role(r): [] for r in config.robot_names}
    for route, scope in route_scopes(config):
        expr = _expr(iface, iface.topic_key(route.topic, prefix=prefix, scope=scope))
        keys = own[robot_role(route.robot)]
        if expr not in keys:
            keys.append(expr)
    team = [k for keys in own.values() for k in keys]
    for robot in config.robots:
        mocap = config.mocap_topic.format(body=robot.mocap_body or robot.name)
        team.append(_expr(iface, iface.topic_key(mocap, prefix=prefix)))
    commanded = [r for r in config.robots if r.name != config.reference]
    return {
        SERVE: [f"{iface.topic_key(estimate_prefix)}/**"],
        NAVIGATE: [_expr(iface, cmd_vel_channel(r, iface, prefix).topic_key) for r in commanded],
        TEAM: list(dict.fromkeys(team)),
        **own,
    }


def access_control(granted: dict[str, list[str]]) -> dict[str, Any]:
    """The Zenoh ``access_control`` section: default deny, each role's own ``put`` rule."""
    members = list(granted)
    rules: list[dict[str, Any]] = [
        {
            "id": "declarations",
            "messages": list(DECLARATIONS),
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": ["**", "@ros2_lv/**"],
        },
        {
            "id": "forward",
            "messages": ["put", "delete"],
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": ["**"],
        },
    ]
    subjects: list[dict[str, Any]] = [{"id": "members", "cert_common_names": members}]
    policies: list[dict[str, Any]] = [
        {"id": "members", "rules": ["declarations", "forward"], "subjects": ["members"]}
    ]
    for role, keys in granted.items():
        if not keys:
            continue
        rules.append(
            {
                "id": f"put-{role}",
                "messages": ["put"],
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": keys,
            }
        )
        subjects.append({"id": role, "cert_common_names": [role]})
        policies.append({"id": role, "rules": [f"put-{role}"], "subjects": [role]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def role_config(
    role: str, ca_pem: bytes, cert_pem: bytes, key_pem: bytes, acl: dict[str, Any]
) -> dict[str, Any]:
    """A role's Zenoh config: peer mode, no multicast scouting, ``tls/`` endpoints only (none
    listed: the commands' ``--listen``/``--connect`` give them), mutual TLS, the ACL."""

    def b64(data: bytes) -> str:
        return base64.b64encode(data).decode()

    return {
        "mode": "peer",
        "connect": {"endpoints": []},
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate_base64": b64(ca_pem),
                    "listen_private_key_base64": b64(key_pem),
                    "listen_certificate_base64": b64(cert_pem),
                    "connect_private_key_base64": b64(key_pem),
                    "connect_certificate_base64": b64(cert_pem),
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                },
            }
        },
        "access_control": acl,
    }


# ============================================================================ certificates
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
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True,
                crl_sign=True, encipher_only=False, decipher_only=False,
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
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
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
            "// role's private key: keep it readable by its owner only (docs/secure.md).\n"
        )
        body = json.dumps(role_config(role, ca_pem, cert_pem, key_pem, acl), indent=2)
        _write(out / f"{role}.pem", cert_pem, private=False)
        _write(out / f"{role}.json5", (header + body + "\n").encode(), private=True)
        written += [out / f"{role}.pem", out / f"{role}.json5"]
    return written


# ============================================================================ a session's security
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
    :func:`write_secure_dir` does, ``//`` comments allowed); empty for other JSON5. Zenoh hides
    the embedded (base64) certificates of a loaded config, so they are read here."""
    if path is None:
        return {}
    try:
        text = "\n".join(ln for ln in path.read_text().splitlines() if not ln.lstrip().startswith("//"))
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
    endpoints = [*(_get(config, "listen/endpoints") or []), *(_get(config, "connect/endpoints") or [])]
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


# ============================================================================ refusals
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_CACHING = re.compile(r"caching permissions for `([^`]*)`")
_REFUSAL = re.compile(
    r"on (?P<link>\S+) is unauthorized to (?P<message>\w+) \((?P<flow>ingress|egress)\) "
    r"on (?P<key>\S+)"
)
_CN = re.compile(r"CertCommonName\(([^)]*)\)")


class AccessRefusals:
    """Counts what this process's access control refuses, from Zenoh's trace log.

    Zenoh judges a message on a key expression its sender declared once, when it caches the
    permissions of that key for the link (a line "caching permissions for `KEY`", then one
    decision per kind of message, on the same thread), and then drops that key's messages
    without a word; it judges, and logs, every message on an undeclared key. So there are two
    counts: :attr:`counts`, refused messages, and :attr:`cached`, the (who, message, flow,
    key) refused in advance, whose messages go uncounted.

    :meth:`start` (before the session opens: Zenoh's log is set up once per process) turns on
    the access-control trace and puts a pipe under file descriptor 1 (where Zenoh writes); a
    thread reads it, counts, and passes every line that is not the access control's on to the
    real stdout. :meth:`stop` puts stdout back.
    """

    def __init__(self) -> None:
        self.counts: Counter[tuple[str, str, str, str]] = Counter()
        """Refused messages by (who, message, flow, key)."""
        self.cached: set[tuple[str, str, str, str]] = set()
        """Refused in advance for a declared key: its messages are dropped uncounted."""
        self._caching: dict[str, str] = {}
        """Per Zenoh thread, the key whose permissions it is caching."""
        self._lock = threading.Lock()
        self._saved: int | None = None
        self._thread: threading.Thread | None = None

    def feed(self, line: str) -> bool:
        """Count ``line`` if it is a refusal; whether it is an access-control line at all."""
        text = _ANSI.sub("", line)
        if ACL_TARGET not in text:
            return False
        thread_m = _THREAD.search(text)
        thread = thread_m.group(1) if thread_m else ""
        caching = _CACHING.search(text)
        if caching is not None:
            self._caching[thread] = caching.group(1)
            return True
        m = _REFUSAL.search(text)
        if m is None:
            if "is authorized to" not in text:
                self._caching.pop(thread, None)
            return True
        cn = _CN.search(m["link"])
        what = (cn.group(1) if cn else "unauthenticated", m["message"].lower(), m["flow"], m["key"])
        with self._lock:
            if self._caching.get(thread) == m["key"]:
                self.cached.add(what)
            else:
                self._caching.pop(thread, None)
                self.counts[what] += 1
        return True

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def as_dict(self) -> dict[str, Any]:
        """``messages``: ``"<who> <message> <flow> <key>" -> count``; ``in_advance``: those
        refused for a declared key (sorted)."""
        with self._lock:
            return {
                "messages": {" ".join(k): n for k, n in sorted(self.counts.items())},
                "in_advance": sorted(" ".join(k) for k in self.cached),
            }

    def start(self) -> None:
        import zenoh

        sys.stdout.flush()
        read_end, write_end = os.pipe()
        self._saved = os.dup(1)
        os.dup2(write_end, 1)
        os.close(write_end)
        self._thread = threading.Thread(
            target=self._pump, args=(read_end, self._saved), name="relloc-acl-log", daemon=True
        )
        self._thread.start()
        zenoh.init_log_from_env_or(f"error,{ACL_TARGET}=trace")

    def stop(self) -> None:
        if self._saved is None:
            return
        sys.stdout.flush()
        os.dup2(self._saved, 1)  # the pipe's last write end closes: the pump ends
        if self._thread is not None:
            self._thread.join(timeout=5)
        os.close(self._saved)
        self._saved = None

    def _pump(self, read_end: int, out: int) -> None:
        pending = b""
        with os.fdopen(read_end, "rb", buffering=0) as pipe:
            while chunk := pipe.read(65536):
                lines = (pending + chunk).split(b"\n")
                pending = lines.pop()
                passed = [ln for ln in lines if not self.feed(ln.decode(errors="replace"))]
                if passed:
                    os.write(out, b"".join(ln + b"\n" for ln in passed))
        if pending and not self.feed(pending.decode(errors="replace")):
            os.write(out, pending)

    def lines(self) -> list[str]:
        """The refusals for people: a total, then each refused message kind, most frequent
        first."""
        with self._lock:
            items = self.counts.most_common()
            cached = len(self.cached)
        head = (
            f"refused by access control: {sum(n for _, n in items)} messages judged one by one; "
            f"{cached} (sender, message, key) refused in advance (cached: their messages are "
            "dropped unreported)"
        )
        return [head] + [f"  {who} may not {msg} {key} ({flow}): {n}" for (who, msg, flow, key), n in items]
