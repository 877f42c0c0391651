"""``relloc secure init``: a team's CA, certificates and Zenoh role configs (docs/howto/secure.md).

Thin layer over :func:`relloc.live.secure.certificates.write_secure_dir`: load the team config, write the
directory (never over an existing one without ``--force``), list what was written and what
each role may publish.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from relloc.cli.common import UserError, interface_from_args

__all__ = ["register"]


def _cmd_init(args: argparse.Namespace) -> int:
    from relloc.config import TeamConfig
    from relloc.live.secure.access import grants
    from relloc.live.secure.certificates import SecureDirError, write_secure_dir

    config = TeamConfig.load(args.config)
    interface = interface_from_args(args, config)
    try:
        written = write_secure_dir(
            config,
            Path(args.out),
            hosts=tuple(args.host),
            interface=interface,
            prefix=args.prefix,
            estimate_prefix=args.estimate_prefix,
            force=args.force,
        )
    except SecureDirError as exc:
        raise UserError(str(exc)) from None
    print(f"relloc secure init: {config.name}, {len(written)} files in {args.out}")
    for role, keys in grants(config, interface, args.prefix, args.estimate_prefix).items():
        shown = ", ".join(keys[:3]) + (f" and {len(keys) - 3} more" if len(keys) > 3 else "")
        print(f"  {role}.json5: may publish {shown or 'nothing'}")
    print("  keep ca.key offline; give each machine only its own <role>.json5 (it holds its key)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``secure init`` to the ``relloc`` command line."""
    secure = sub.add_parser(
        "secure",
        help="authenticated, authorised Zenoh: a team CA and a config per role",
        description="Tools for a secure deployment: mutual TLS between the team's machines and "
        "access control on who may publish what (docs/howto/secure.md).",
    )
    verbs = secure.add_subparsers(dest="secure_command", metavar="VERB", required=True)
    init = verbs.add_parser(
        "init",
        help="write a private CA, a certificate and a Zenoh config per role",
        description="Write a private CA (ca.pem, ca.key), a certificate per relloc role and per "
        "robot, and one Zenoh JSON5 config per role (serve, navigate, team for sim-robots and "
        "replay, robot-<name>) with mutual TLS and the team's access control: a robot may "
        "publish only its own topics, only serve relloc/**, only navigate cmd_vel. Give a "
        "command its role's file with --secure DIR (or --zenoh-config DIR/<role>.json5).",
    )
    init.add_argument("--config", required=True, help="team config (TOML)")
    init.add_argument("--out", required=True, metavar="DIR", help="the directory to write")
    init.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="NAME",
        help="a host name or address the certificates also name (repeatable; localhost and "
        "127.0.0.1 always)",
    )
    init.add_argument("--force", action="store_true", help="replace an existing DIR's files")
    init.add_argument(
        "--prefix", default="", help="key prefix of the robots' topics (the bridge namespace)"
    )
    init.add_argument(
        "--estimate-prefix",
        default="relloc",
        help="key prefix of serve's estimates (its --out-prefix)",
    )
    init.add_argument(
        "--ros-interface", choices=("bridge", "rmw_zenoh"), default=None,
        help="the robots' interface (default: the config's ros_interface)",
    )  # fmt: skip
    init.add_argument(
        "--domain-id", type=int, default=None, metavar="N", help="ROS domain id with rmw_zenoh"
    )
    init.set_defaults(handler=_cmd_init)
