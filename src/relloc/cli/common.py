"""What every command shares: user errors, stopping on signals, Zenoh sessions, options.

* :class:`UserError` is a problem with the user's input; :func:`is_user_error` says which
  exceptions (this one, and the library's own: bad config, bag, method, model directory, a
  run's :class:`~relloc.runs.checks.RunError`) the
  ``relloc`` entry point reports as one line with exit status 2 instead of a traceback.
* :func:`stop_on_signals` turns SIGINT/SIGTERM into a request to stop (a :class:`threading.Event`,
  and an optional callback), so a long-running command ends cleanly and prints its figures;
  the previous handlers come back when the block ends.
* :func:`add_zenoh_args` and :func:`open_command_session`: every live command (``serve``,
  ``replay``, ``navigate``, ``sim-robots``) opens its Zenoh session from the same flags, and
  :func:`interface_from_args` gives its ROS interface (``--ros-interface``, ``--domain-id``,
  else the team config's ``ros_interface`` and ``ROS_DOMAIN_ID``); ``--secure DIR`` picks the
  command's role config of ``relloc secure init`` and :func:`session_security` says what the
  session's config makes of it (authenticated, as whom).
* :func:`options_from_args` builds a command's option dataclass from the parsed arguments by
  field name, so a new option is one ``add_argument`` whose ``dest`` is the field's name.
"""

from __future__ import annotations

import argparse
import datetime
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import fields
from pathlib import Path
from typing import Any, TypeVar

from relloc.config import TeamConfig
from relloc.live.secure.identity import Security, check_endpoints, security_of
from relloc.live.secure.refusals import AccessRefusals
from relloc.live.session import ZenohOptions, open_session
from relloc.ros.interfaces import ROS_INTERFACES, RosInterface
from relloc.ros.stores import DISTROS
from relloc.runs.checks import RunError, check_warmup, check_writable

__all__ = [
    "UserError",
    "add_zenoh_args",
    "check_warmup",
    "check_writable",
    "counting_refusals",
    "format_stamp",
    "interface_from_args",
    "is_user_error",
    "open_command_session",
    "options_from_args",
    "session_security",
    "stop_on_signals",
    "zenoh_options_from_args",
]

T = TypeVar("T")


class UserError(Exception):
    """A problem with the user's input, reported as one line without a traceback."""


def is_user_error(exc: Exception) -> bool:
    """Whether ``exc`` is an expected failure (one line, exit 2) rather than a bug."""
    from relloc.config import ConfigError
    from relloc.evaluation.calibration import CalibrationError
    from relloc.methods import MethodError
    from relloc.ranging.manifest import ModelDirError
    from relloc.sources.mrclam import MrclamError
    from relloc.sources.rosbag import BagError
    from relloc.sources.table import SourceError

    known = (
        UserError,
        RunError,
        ConfigError,
        MethodError,
        BagError,
        MrclamError,
        SourceError,
        CalibrationError,
        ModelDirError,
        FileNotFoundError,
    )
    return isinstance(exc, known)


@contextmanager
def stop_on_signals(on_stop: Callable[[], None] | None = None) -> Iterator[threading.Event]:
    """An event set by SIGINT/SIGTERM while the block runs (``on_stop`` is called too). A
    second signal, while the first one's shutdown is still running, exits at once with the
    shell's code for an interrupt (130), the ``finally`` blocks still run."""
    stop = threading.Event()

    def handler(*_: Any) -> None:
        if stop.is_set():
            raise SystemExit(130)
        stop.set()
        if on_stop is not None:
            on_stop()

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def format_stamp(t: float | None) -> str:
    """A header time stamp for people: ISO 8601 (UTC) for wall-clock stamps, seconds for a
    simulator's clock (which starts near zero), "never" for none."""
    if t is None:
        return "never"
    if t > 1e8:  # after 1973: a wall clock
        stamp = datetime.datetime.fromtimestamp(t, datetime.UTC).isoformat(timespec="milliseconds")
        return f"at {stamp.replace('+00:00', 'Z')}"
    return f"at t = {t:.2f} s"


def options_from_args(cls: type[T], args: argparse.Namespace, **values: Any) -> T:
    """The dataclass ``cls`` with each field taken from the argument of its name.

    ``values`` give the fields that need more than parsing (a parsed method list, a loaded
    path); fields with neither keep their default. Arguments of other names are ignored.
    """
    given = vars(args)
    kwargs = {f.name: given[f.name] for f in fields(cls) if f.init and f.name in given}  # type: ignore[arg-type]
    kwargs.update(values)
    return cls(**kwargs)


def add_zenoh_args(p: argparse.ArgumentParser, role: str) -> None:
    """The Zenoh session options of every live command (``--mode``, ``--connect``, ...);
    ``role`` names its config in a ``relloc secure init`` directory (``--secure DIR``)."""
    g = p.add_argument_group("zenoh")
    p.set_defaults(zenoh_role=role)
    g.add_argument(
        "--mode",
        choices=("peer", "client"),
        default="peer",
        help="Zenoh mode: peer (talks to every peer) or client (through a router)",
    )
    g.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="EP",
        help="e.g. tcp/192.168.1.10:7447 (repeatable)",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="EP",
        help="e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    g.add_argument("--no-multicast", action="store_true", help="disable multicast scouting")
    g.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="a Zenoh JSON5 config (the options above override it)",
    )
    g.add_argument(
        "--secure",
        default=None,
        metavar="DIR",
        help=f"mutual TLS and access control: DIR/{role}.json5 of relloc secure init "
        "(tls/ endpoints only; docs/howto/secure.md)",
    )
    g.add_argument(
        "--prefix", default="", help="key prefix of the robots' topics (the bridge namespace)"
    )
    g.add_argument(
        "--ros-interface",
        choices=ROS_INTERFACES,
        default=None,
        help="how the robots are on Zenoh: zenoh-bridge-ros2dds keys (bridge) or rmw_zenoh's "
        "keys, attachments and liveliness tokens (default: the config's ros_interface, bridge)",
    )
    g.add_argument(
        "--ros-distro",
        choices=DISTROS,
        default=None,
        help="the robots' ROS 2 distribution: the message layouts relloc publishes and, with "
        "rmw_zenoh, the type hashes of its keys and tokens; received messages of any known "
        "layout are read (default: the config's ros_distro, jazzy)",
    )
    g.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="ROS domain id with rmw_zenoh (default: $ROS_DOMAIN_ID, else 0)",
    )


def interface_from_args(args: argparse.Namespace, config: TeamConfig) -> RosInterface:
    """The :class:`RosInterface` of a command: its flags, else the config and the environment."""
    kind = args.ros_interface or config.ros_interface
    distro = getattr(args, "ros_distro", None) or config.ros_distro
    domain = args.domain_id
    if domain is None:
        env = os.environ.get("ROS_DOMAIN_ID", "").strip()
        try:
            domain = int(env) if env else 0
        except ValueError:
            raise UserError(f"ROS_DOMAIN_ID={env!r} is not an integer") from None
    try:
        return RosInterface(kind, domain, distro)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def zenoh_options_from_args(args: argparse.Namespace) -> ZenohOptions:
    """The :class:`ZenohOptions` of arguments added by :func:`add_zenoh_args`."""
    config_file = Path(args.zenoh_config) if args.zenoh_config else None
    if args.secure:
        if config_file is not None:
            raise UserError("give --secure DIR or --zenoh-config FILE, not both")
        config_file = Path(args.secure) / f"{args.zenoh_role}.json5"
        if not config_file.is_file():
            raise UserError(f"--secure {args.secure}: no {config_file.name} (relloc secure init)")
        try:
            check_endpoints([*args.connect, *args.listen])
        except ValueError as exc:
            raise UserError(str(exc)) from None
    return ZenohOptions(
        mode=args.mode,
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        multicast=not args.no_multicast,
        config_file=config_file,
    )


def session_security(args: argparse.Namespace) -> Security:
    """Whether the session of a command is authenticated, and as whom (its config's word)."""
    options = zenoh_options_from_args(args)
    return security_of(options.to_config(), options.config_file)


@contextmanager
def counting_refusals(security: Security) -> Iterator[AccessRefusals | None]:
    """While the block runs, count what the session's access control refuses (``None``
    without access control): open the session inside the block."""
    if not security.access_control:
        yield None
        return
    refusals = AccessRefusals()
    refusals.start()
    try:
        yield refusals
    finally:
        refusals.stop()


def open_command_session(args: argparse.Namespace) -> Any:
    """The session of a command, or a one-line error (e.g. the --listen port is taken)."""
    try:
        return open_session(zenoh_options_from_args(args))
    except Exception as exc:  # zenoh.ZError and config errors
        raise UserError(f"cannot open a Zenoh session: {exc}") from None
