"""The team's roles and access control, derived from its config: who may publish what.

Each role's ``put`` grants come from the keys the live commands use; the ACL (default deny,
declarations allowed between members) is the same in every role's Zenoh config.
"""

from __future__ import annotations

import base64
from typing import Any

from relloc.config import TeamConfig
from relloc.live.publish import cmd_vel_channel
from relloc.ros.interfaces import RosInterface
from relloc.sources.zenoh_keys import route_scopes

__all__ = [
    "NAVIGATE",
    "SERVE",
    "TEAM",
    "access_control",
    "grants",
    "robot_role",
    "role_config",
    "roles",
]

SERVE = "serve"
NAVIGATE = "navigate"
TEAM = "team"
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


def robot_role(robot: str) -> str:
    """The role (and certificate common name) of a robot: ``robot-<name>``."""
    return f"robot-{robot}"


def roles(config: TeamConfig) -> list[str]:
    """Every role of a team, in the order the files are written."""
    return [SERVE, NAVIGATE, TEAM, *(robot_role(r) for r in config.robot_names)]


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
