"""What a team config needs, estimated from a recording with motion capture (``relloc calibrate``,
``relloc init``).

:func:`calibrate` estimates UWB node-pair biases (from a bag or the UWB error CSV) and,
optionally, heading offsets (from each robot's first motion-capture pose). It never decides
where they go: :func:`edit_config_text` writes them into the *text* of the team config with a
comment-preserving TOML library (tomlkit), so a hand-written config keeps its comments, its
order and every key it does not concern, and :func:`calibration_section` is the TOML of just
what was estimated, which the command prints when asked to write nothing.

What is written for a pair: ``bias`` and ``source`` always, ``scale`` only when it was fitted
(``--scale``) or the config already sets one, ``sigma`` only when the config already sets one
for that pair. A config that leaves the per-pair sigmas unset (so that the filter's own noise
model applies) keeps them unset; the robust sigma then goes into the comment on the ``bias``
line (``# sigma 0.075``), as the shipped configs have it.

For a flying team it also measures the team's range noise (:attr:`Calibration.range_sigma`,
which ``relloc init`` writes as ``[uwb] sigma``): the 3D smoother weighs every range by that
alone (an online bias takes the pair's offset), and the default is a ground team's NLOS-aware
model's. The RMS of what the biases leave, not a robust spread: on raw ranges with NLOS spikes
the robust spread (5 cm) weighed the spikes too much (distance errors 0.026-0.038 m against
0.017-0.021 with the RMS, 0.15 m); on averaged ranges the two agree (0.040 / 0.041 m). Each
residual counts at most ``CLIP_M``: one garbage range (a driver's 100 m) must not make every
range weigh nothing.

With ``bias_errors`` (``relloc init``, a flying team) each pair's ``bias_sigma`` is its bias's
standard error on this bag, not the spread between sessions the online biases otherwise start
from: a run of the same bag starts from what its motion capture told (108 drone pair biases
each free by 5 cm took the formation's tilt for biases: docs/explanation/flying.md).
"""

from __future__ import annotations

import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit
from tomlkit.items import Item, Table

from relloc.config import ConfigError, PairCalibration, TeamConfig
from relloc.sources.table import SourceError, source_kind


@dataclass(frozen=True)
class Calibration:
    """What :func:`calibrate` estimated from one recording."""

    source: str
    pairs: dict[str, PairCalibration]
    """Per node pair (``"n_3-n_7"``): bias, scale and the robust sigma of what is left."""
    heading_offset_deg: dict[str, float] = field(default_factory=dict)
    fit_scale: bool = False
    range_sigma: float | None = None
    """A flying team's range noise (m), which ``relloc init`` writes as ``[uwb] sigma``: the
    RMS over every matched range of what its pair's bias leaves, each residual counted at most
    :data:`~relloc.drafting.tags.CLIP_M` (``None``: not measured; the module docstring says why)."""

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "source": self.source,
            "pairs": {
                k: {"bias": v.bias, "scale": v.scale, "sigma": v.sigma}
                for k, v in self.pairs.items()
            },
        }
        if self.heading_offset_deg:
            out["heading_offset_deg"] = dict(self.heading_offset_deg)
        return out


def calibrate(
    source: Path,
    config: TeamConfig,
    *,
    node_map: dict[int, str] | None = None,
    headings: bool = False,
    fit_scale: bool = False,
    span: tuple[float, float] | None = None,
    bias_errors: bool = False,
) -> Calibration:
    """Pair calibration (and optionally heading offsets) from ``source``: a recording with UWB
    ranges and motion capture (:attr:`~relloc.sources.table.SourceKind.calibrates`: a rosbag2
    bag, only the events of ``span``: seconds from its start), or a CSV of UWB errors
    (``node_map``: CSV robot number -> node). ``bias_errors``: each bag pair's ``bias_sigma``
    is its bias's standard error on this bag (module docstring)."""
    from relloc.evaluation import calibration

    range_sigma: float | None = None
    if source.suffix.lower() == ".csv":
        if headings:
            raise ConfigError(
                "heading offsets need a bag with odometry and motion capture, not a CSV"
            )
        if span is not None:
            raise ConfigError("--span needs a recording, not a CSV")
        pairs = calibration.pair_biases_from_csv(
            source, node_map or {1: "n_7", 3: "n_3", 4: "n_4", 5: "n_5"}, fit_scale=fit_scale
        )
    else:
        kind = source_kind(source)
        if not kind.calibrates:
            raise SourceError(
                f"{source} is {kind.what}: calibration needs UWB ranges with motion capture "
                "(a rosbag2 recording) or a CSV of UWB errors"
            )
        samples = calibration.pair_samples_from_bag(source, config, span=span)
        pairs = calibration.pair_biases_from_samples(samples, source, fit_scale=fit_scale)
        if config.dimension == 3:
            from relloc.drafting.tags import CLIP_M

            range_sigma = calibration.residual_rms(samples, CLIP_M)
            range_sigma = None if range_sigma is None else round(range_sigma, 3)
        if bias_errors:
            pairs = _with_bias_errors(pairs, samples)
    offsets: dict[str, float] = {}
    if headings:
        offsets = {
            r: round(deg, 2)
            for r, deg in calibration.heading_offsets_from_bag(source, config).items()
        }
    return Calibration(str(source), dict(pairs), offsets, fit_scale, range_sigma)


def _with_bias_errors(
    pairs: dict[str, PairCalibration],
    samples: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> dict[str, PairCalibration]:
    """``pairs`` with each one's ``bias_sigma`` its standard error on the matched ``samples``."""
    from relloc.drafting.tags import BLOCK_S, CLIP_M
    from relloc.evaluation.calibration import median_standard_error

    out = {}
    for key, pair in pairs.items():
        se = median_standard_error(*samples[key], block_s=BLOCK_S, clip=CLIP_M)
        out[key] = pair if se is None else replace(pair, bias_sigma=round(se, 4))
    return out


def _set(table: Table, key: str, value: Any, comment: str | None = None) -> None:
    """``table[key] = value`` keeping the old item's comment and its spacing (or ``comment``)."""
    new: Item = tomlkit.item(value)
    old = table.get(key)
    if isinstance(old, Item):
        new.trivia.comment_ws = old.trivia.comment_ws
        new.trivia.comment = old.trivia.comment
    if comment is not None:
        if not new.trivia.comment_ws:
            new.trivia.comment_ws = "  "
        new.trivia.comment = f"# {comment}"
    table[key] = new


def _pair_values(cal: PairCalibration, existing: dict[str, Any], fit_scale: bool) -> dict[str, Any]:
    values: dict[str, Any] = {"bias": cal.bias}
    if fit_scale or "scale" in existing:
        values["scale"] = cal.scale
    if "sigma" in existing and cal.sigma is not None:
        values["sigma"] = cal.sigma
    if cal.bias_sigma is not None:
        values["bias_sigma"] = cal.bias_sigma
    values["source"] = cal.source
    return values


def _sigma_comment(cal: PairCalibration, old: Any) -> str | None:
    """The ``# sigma ...`` note for a pair whose sigma stays unset: a new pair, or one whose bias
    line already carries such a note; any other comment is kept as it was."""
    if cal.sigma is None:
        return None
    note = f"sigma {cal.sigma:.3f}"
    if not isinstance(old, Item):
        return note
    return note if old.trivia.comment.lstrip("# ").startswith("sigma") else None


def edit_config_text(text: str, cal: Calibration) -> str:
    """``text`` (a team config) with ``cal`` written in, comments and layout kept."""
    doc = tomlkit.parse(text)
    uwb = doc.get("uwb")
    if uwb is None:
        uwb = tomlkit.table()
        doc["uwb"] = uwb
    pairs = uwb.get("pairs")
    if pairs is None:
        pairs = tomlkit.table(is_super_table=True)
        uwb["pairs"] = pairs
    for key, pair in sorted(cal.pairs.items()):
        pair = replace(pair, source=pair.source or Path(cal.source).name)
        entry = pairs.get(key)
        if entry is None:
            entry = tomlkit.table()
            pairs[key] = entry
        existing = dict(entry)
        for name, value in _pair_values(pair, existing, cal.fit_scale).items():
            comment = (
                _sigma_comment(pair, entry.get(name))
                if name == "bias" and "sigma" not in existing
                else None
            )
            _set(entry, name, value, comment)
    robots = doc.get("robots", [])
    for robot, deg in cal.heading_offset_deg.items():
        for entry in robots:
            if entry.get("name") == robot:
                _set(entry, "heading_offset_deg", deg)
    out = tomlkit.dumps(doc)
    try:  # what is written must load
        TeamConfig.from_dict(tomllib.loads(out))
    except (ConfigError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"the calibrated config would not load: {exc}") from None
    return out


def calibration_section(cal: Calibration, text: str) -> str:
    """The TOML of what ``cal`` changes in the config ``text``: its ``[uwb.pairs]`` tables as
    they would be written, and heading offsets as comments (they belong in ``[[robots]]``)."""
    edited = tomlkit.parse(edit_config_text(text, cal))
    doc = tomlkit.document()
    uwb = tomlkit.table()
    pairs = tomlkit.table(is_super_table=True)
    for key in sorted(cal.pairs):
        pairs[key] = edited["uwb"]["pairs"][key]
    uwb["pairs"] = pairs
    doc["uwb"] = uwb
    lines = [f"# calibration from {cal.source}"]
    for robot, deg in cal.heading_offset_deg.items():
        lines.append(f"# [[robots]] {robot}: heading_offset_deg = {deg}")
    return "\n".join(lines) + "\n" + tomlkit.dumps(doc).lstrip("\n")
