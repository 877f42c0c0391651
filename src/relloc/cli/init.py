"""``relloc init BAG``: draft a team config (TOML, with comments) from what a bag holds.

The drafting is :mod:`relloc.drafting` (robots, UWB node mapping, reference, area, calibration);
this module parses the arguments and prints. Motion capture is found by message type
(``PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``, ``Odometry``), whatever the
topic naming (``/<body>/world``, ``/vrpn_client_node/<body>/pose``, ``/mocap/<body>/pose``): a
topic pattern with the body in one name part, not a robot's own odometry (``/<robot>/odom``);
``--mocap-topic '/{body}/world'`` gives the pattern where that cannot tell. The draft carries it as
``mocap_topic``. ``--node ROBOT=NODE`` pins a robot's node, ``--reference`` the reference robot.
A node that moves with a body already mapped is a second tag on it: the robot gets ``tags = [...]``
with each extra tag's lever arm estimated from the motion capture (standard errors in the
comment; :mod:`relloc.drafting.tags`), or zeros to be measured with ``--no-calibrate``.
Bodies whose mocap heights spread over :data:`~relloc.drafting.team.FLYING_SPREAD_M` fly: the
draft gets ``dimension = 3`` and 3D lever arms. UWB ranges are ``Range`` topics per node pair or
LinkTrack node frames per node (:mod:`relloc.drafting.frames`, ``/n<k>/range``).

With the mapping decided, what ``relloc calibrate BAG --headings`` estimates is estimated from
the same bag's motion capture (:func:`relloc.drafting.calibrate.calibrate`, written in by
:func:`~relloc.drafting.calibrate.edit_config_text`): the node-pair biases and each robot's
``heading_offset_deg``; ``--no-calibrate`` leaves them out, so that the draft owes nothing to
the ground truth it will be scored on. The file is never overwritten without ``--force``.

Exit status: 0 when the mapping is decided; 2 when it is not (the file is still written, the
mapping marked undecided in a comment: rerun with ``--node``), and for user errors (bag not
readable, file exists, bad ``--node``, too few motion-capture bodies).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from relloc.cli.common import UserError
from relloc.config import TeamConfig


def _cmd_init(args: argparse.Namespace) -> int:
    # Imported here: drafting needs scipy.optimize (about 50 MB resident), which every other
    # command, ``relloc serve`` among them, would pay for while its parser is built.
    from relloc.drafting.calibrate import edit_config_text
    from relloc.drafting.team import DraftError, calibrate_draft, draft
    from relloc.drafting.writer import distro, quirks, to_toml
    from relloc.sources.rosbag import BagError, recording_name

    bag = Path(args.bag)
    out = Path(args.out) if args.out else Path(f"{recording_name(bag)}.toml")
    if out.exists() and not args.force:
        raise UserError(f"{out} exists; --force overwrites it")
    try:
        inv, d = draft(bag, args.node or [], args.reference, args.mocap_topic)
        text = to_toml(inv, d, recording_name(bag), lever_arms=not args.no_calibrate)
        cal_notes: list[str] = []
        if not args.no_calibrate and inv.ranges:
            cal, cal_notes = calibrate_draft(bag, text, d)
            if cal is not None:
                drafted = to_toml(
                    inv,
                    d,
                    recording_name(bag),
                    list(cal.heading_offset_deg),
                    range_sigma=cal.range_sigma,
                )
                text = edit_config_text(drafted, cal)
    except (BagError, DraftError) as exc:
        raise UserError(str(exc)) from None
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    TeamConfig.load(out)  # the draft must load; a failure here is a bug
    print(f"relloc init: {bag} -> {out}")
    for r in d.robots:
        extra = f", odometry {r.odom}" if r.odom else ""
        nodes = "+".join([r.node, *(t.node for t in d.tags_of(r))]) if r.node else "-"
        print(f"  {r.name}: mocap {r.body}, UWB {nodes}{extra}")
        first = d.first_fit(r)
        for t in [*([first] if first else []), *d.tags_of(r)] if not args.no_calibrate else ():
            arm = ", ".join(
                f"{v:+.3f} +- {e:.3f}" for v, e in zip(t.lever_arm, t.stderr, strict=True)
            )
            origin = "the mocap origin" if first else r.node
            print(
                f"    {t.node} lever arm ({arm}) m from {origin}, |{math.hypot(*t.lever_arm):.3f}| m"
            )
    print(f"  area {list(d.area)}, ros_distro {distro(inv.range_layout)}")
    for line in [d.reference_note, *d.notes, *cal_notes, *quirks(inv)]:
        print(f"  {line}")
    print(f"  assignment search: {d.seconds:.2f} s")
    if not d.decided:
        print(
            f"relloc init: the node mapping is undecided; {out} is written with a guess. "
            "Rerun with --node ROBOT=NODE --force",
            file=sys.stderr,
        )
        return 2
    return 0


def register(sub: Any) -> None:
    """Add ``init`` to the subcommands."""
    p = sub.add_parser(
        "init",
        help="draft a team config (TOML) from a bag: robots, UWB nodes, reference, area",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument("bag", help="rosbag2 folder (or .db3/.mcap file)")
    p.add_argument(
        "--out", type=Path, default=None, help="the config to write (default: <recording>.toml)"
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.add_argument(
        "--node",
        action="append",
        metavar="ROBOT=NODE",
        help="pin a robot's UWB node (repeatable), e.g. turtle01=n_2",
    )
    p.add_argument(
        "--reference",
        metavar="ROBOT",
        default=None,
        help="the reference robot (default: the one whose node is in the most range messages)",
    )
    p.add_argument(
        "--mocap-topic",
        metavar="PATTERN",
        default=None,
        help="the motion-capture topics, with {body}, e.g. '/{body}/world' (default: found by "
        "message type: PoseStamped, PoseWithCovarianceStamped, TransformStamped, Odometry)",
    )
    p.add_argument(
        "--no-calibrate",
        action="store_true",
        help="leave out pair biases and heading offsets (else estimated from the bag's motion capture)",
    )
    p.set_defaults(handler=_cmd_init)
