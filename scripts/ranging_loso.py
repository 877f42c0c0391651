"""Leave-one-session-out (LOSO) selection of the range-error models on the shared sessions.

An in-session split picks models that fit one session; what matters is another day. This
script turns every shared recording with UWB ranges and motion capture into an error CSV (the
code of ``relloc ranging bag-csv``), then, for each session held out in turn, trains each
candidate configuration (variant, hidden size, dropout, weight decay, n_steps) on the other
sessions merged, and scores it on the held-out one with the project's evaluation
(:func:`relloc.ranging.evaluate.evaluate`, ``--part all``), without and with the run-time
support guard, beside the baselines (zero, the training constant, the per-pair bias). Only the
pairs of the held-out session that some other session has are trained and scored.

Recommendation rule: the row with the lowest LOSO mean, the mean over held-out sessions of the
session's mean per-pair MSE (every session weighs the same); a baseline can win. With fewer
than two held-out sessions that share a pair with another session there is no choice to make.

    python scripts/ranging_loso.py --page docs/results/ranging_loso_generated.md

``--quick`` trains one small configuration per variant (a smoke run); ``--epochs`` and
``--patience`` bound the training time (defaults: the whole table in well under 20 min on two
cores). Scratch files go to ``--work`` (default ``out/ranging_loso``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from relloc.events import pair_key
from relloc.ranging.dataset import CSV_COLUMNS, DEFAULT_NODE_MAP, load_csv
from relloc.ranging.evaluate import evaluate

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

BAGS: dict[str, tuple[str, str]] = {
    "chair_20220923": ("tiers/pair_chair_moving_20220923", "n_7=turtlebot1_cap,n_3=turtlebot3_cap"),
    "range_20220907": ("tiers/pair_range_20220907_1725", "n_2=turtlebot01_cap,n_3=turtlebot03_cap"),
    "case4_static": (
        "tiers_uwb_rel/case4_test1_static",
        ",".join(f"n_{k}=turtlebot{k}" for k in range(1, 8)),
    ),
}
"""Shared bags with UWB and motion capture: session -> (folder under the data root, bodies).
``tiers/multi4_shortbag_20221011`` is left out: its ranges are rows of the training CSV (the
same run), so it is not another session."""
TRAINING_CSV = ("train_20221219", "tiers/uwb_error/train_20221219.csv")
SESSION_GAP_S = 1000.0
"""Seconds between sessions in a merged CSV (each pair's rows stay session after session)."""
BASELINE_ROWS = {"zero": "zero", "constant": "training constant", "bias": "per-pair bias"}


@dataclass(frozen=True)
class Candidate:
    """One configuration to train: ``relloc ranging train`` options."""

    label: str
    variant: str
    hidden: tuple[int, ...] = (16,)
    dropout: float = 0.3
    weight_decay: float = 1e-4
    n_steps: int = 10

    def describe(self) -> str:
        h = "x".join(str(v) for v in self.hidden)
        return f"{self.variant} h={h} dropout={self.dropout:g} wd={self.weight_decay:g} n_steps={self.n_steps}"


def candidates(quick: bool = False) -> list[Candidate]:
    """The configurations of the table: per variant a base and three regularisations."""
    out: list[Candidate] = []
    for v in ("stacked", "bilstm", "convlstm"):
        out.append(Candidate(f"{v}-base", v))
        if quick:
            continue
        out += [
            Candidate(f"{v}-h8-d0.5", v, hidden=(8,), dropout=0.5),
            Candidate(f"{v}-wd1e-2", v, weight_decay=1e-2),
            Candidate(f"{v}-n5", v, n_steps=5),
        ]
    return out


@dataclass
class LosoResult:
    """Per held-out session: the scored pairs and each row's per-pair MSE."""

    sessions: list[str]
    pairs: dict[str, list[str]]
    """Held-out session -> pairs scored (present in it and in another session)."""
    per_pair: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    """Row name -> held-out session -> pair -> MSE (m²)."""
    descriptions: dict[str, str] = field(default_factory=dict)
    out_of_support: dict[str, dict[str, int]] = field(default_factory=dict)
    """Guarded row -> held-out session -> windows that fell back to the constant."""
    train_seconds: float = 0.0

    def session_mean(self, row: str, session: str) -> float:
        values = self.per_pair[row].get(session, {})
        return float(np.mean(list(values.values()))) if values else math.nan

    def loso_mean(self, row: str) -> float:
        values = [self.session_mean(row, s) for s in self.scored_sessions()]
        return float(np.mean(values)) if values else math.nan

    def worst_pair(self, row: str) -> tuple[str, float]:
        items = [(f"{p} ({s})", v) for s, d in self.per_pair[row].items() for p, v in d.items()]
        return max(items, key=lambda kv: kv[1]) if items else ("-", math.nan)

    def scored_sessions(self) -> list[str]:
        return [s for s in self.sessions if self.pairs.get(s)]

    def recommended(self) -> str | None:
        """The row with the lowest LOSO mean; None with fewer than two scored sessions."""
        if len(self.scored_sessions()) < 2:
            return None
        return min(self.per_pair, key=self.loso_mean)


def pair_matrix(sessions: Mapping[str, Path]) -> dict[str, dict[str, int]]:
    """Pair -> session -> rows (the loader's node ids)."""
    out: dict[str, dict[str, int]] = {}
    for name, path in sessions.items():
        for pair, series in load_csv(path).items():
            out.setdefault(pair, {})[name] = len(series)
    return dict(sorted(out.items()))


def merge_csvs(paths: Sequence[Path], out: Path, pairs: set[str]) -> Path:
    """One CSV of ``pairs`` from ``paths`` in turn: node ids (the training CSV's robot numbers
    mapped by the default node map) and timestamps shifted so the sessions follow each other."""
    offset = 0.0
    rows: list[list[Any]] = []
    for path in paths:
        with Path(path).open(newline="") as fh:
            reader = csv.DictReader(fh)
            session_rows = []
            for r in reader:
                a, b = (_node_id(r[k]) for k in ("node1", "node2"))
                if pair_key(a, b) not in pairs:
                    continue
                session_rows.append({**r, "node1": a, "node2": b})
        if not session_rows:
            continue
        t = np.array([float(r["timestamp"]) for r in session_rows])
        for r, ti in zip(session_rows, t - t.min() + offset, strict=True):
            rows.append([f"{ti:.6f}", *(r[c] for c in CSV_COLUMNS[1:])])
        offset = float(t.max() - t.min()) + offset + SESSION_GAP_S
    with out.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        writer.writerows(rows)
    return out


def _node_id(value: str) -> str:
    """A CSV node column as a node id: robot numbers (``"1"``, ``"1.0"``) by the default map."""
    text = value.strip()
    try:
        text = str(int(float(text)))
    except ValueError:
        return text
    return DEFAULT_NODE_MAP.get(text, text)


def run_loso(
    sessions: Mapping[str, Path],
    work: Path,
    configs: Sequence[Candidate],
    *,
    epochs: int = 30,
    patience: int = 6,
    seed: int = 0,
    log: Any = None,
) -> LosoResult:
    """Train on all sessions but one, score on that one, for every session (module docstring)."""
    from relloc.ranging.models import Architecture
    from relloc.ranging.train import TrainConfig, train_directory

    matrix = pair_matrix(sessions)
    names = list(sessions)
    result = LosoResult(names, {})
    t0 = time.perf_counter()
    for held in names:
        pairs = sorted(p for p, d in matrix.items() if held in d and len(d) >= 2)
        result.pairs[held] = pairs
        if not pairs:
            continue
        fold = work / held
        fold.mkdir(parents=True, exist_ok=True)
        train_csv = merge_csvs(
            [sessions[s] for s in names if s != held], fold / "train.csv", set(pairs)
        )
        dirs = []
        for c in configs:
            arch = Architecture(variant=c.variant, hidden=c.hidden, dropout=c.dropout)
            config = TrainConfig(
                n_steps=c.n_steps,
                epochs=epochs,
                patience=patience,
                weight_decay=c.weight_decay,
                seed=seed,
                split=(0.8, 0.2, 0.0),
            )
            if log:
                log(f"{held}: training {c.label} on {len(pairs)} pair(s)")
            train_directory(train_csv, fold / c.label, arch, config, node_map={})
            dirs.append(fold / c.label)
        for guard in (False, True):
            report = evaluate(
                sessions[held], dirs, part="all", timing_samples=1, support_guard=guard
            )
            by_dir = {
                Path(m.get("directory", "")).name: (n, m) for n, m in report["methods"].items()
            }
            for c in configs:
                _, entry = by_dir[c.label]
                row = f"{c.label}+guard" if guard else c.label
                result.per_pair.setdefault(row, {})[held] = entry["per_pair_mse"]
                result.descriptions[row] = c.describe() + (", support guard" if guard else "")
                if guard:
                    result.out_of_support.setdefault(row, {})[held] = int(entry["out_of_support"])
            if not guard:
                for key, label in BASELINE_ROWS.items():
                    result.per_pair.setdefault(label, {})[held] = report["methods"][key][
                        "per_pair_mse"
                    ]
    result.train_seconds = time.perf_counter() - t0
    return result


def markdown(result: LosoResult, matrix: Mapping[str, Mapping[str, int]], command: str) -> str:
    """The generated page: pair/session matrix, LOSO table, the rule and the recommendation."""
    sessions = result.sessions
    lines = [
        "# Range-error models: leave-one-session-out selection (generated)",
        "",
        f"Generated by `{command}`; do not edit by hand. For each held-out session the models are "
        "trained on the other sessions merged and scored there with `relloc ranging eval` "
        "(`--part all`). Only pairs of the held-out session present in another session are scored.",
        "",
        "## Rows per pair and session",
        "",
        "`multi4_shortbag_20221011` is not a session of its own: its ranges are rows of the "
        "training CSV (the same run). Node ids are taken to name the same transceivers in every "
        "recording.",
        "",
        "| pair | " + " | ".join(sessions) + " |",
        "|---|" + "---|" * len(sessions),
    ]
    for pair, d in matrix.items():
        lines.append(f"| {pair} | " + " | ".join(str(d.get(s, "")) for s in sessions) + " |")
    scored = result.scored_sessions()
    lines += [
        "",
        "## Mean MSE per held-out session (m²)",
        "",
        "Mean over the session's scored pairs; LOSO mean: the mean over held-out sessions; worst "
        "pair: the largest per-pair MSE over all folds.",
        "",
        "| row | "
        + " | ".join(f"{s} ({len(result.pairs[s])} pairs)" for s in scored)
        + " | LOSO mean | worst pair |",
        "|---|" + "---|" * (len(scored) + 2),
    ]
    rows = sorted(result.per_pair, key=result.loso_mean)
    best = result.recommended()
    for row in rows:
        worst, value = result.worst_pair(row)
        cells = [f"{result.session_mean(row, s):.4f}" for s in scored]
        mean = f"{result.loso_mean(row):.4f}"
        name = f"**{row}**" if row == best else row
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {mean} | {worst} {value:.4f} |")
    described = [f"`{r}`: {d}" for r, d in result.descriptions.items() if not r.endswith("+guard")]
    lines += [
        "",
        "Rows: " + "; ".join(described) + "; `+guard`: the same models with the run-time "
        "support guard (a window outside the training support gets the pair's constant).",
    ]
    if result.out_of_support:
        lines += [
            "",
            "Windows outside the training support (guarded rows): "
            + "; ".join(
                f"{r} " + ", ".join(f"{s} {n}" for s, n in d.items())
                for r, d in result.out_of_support.items()
            )
            + ".",
        ]
    lines += ["", "## Recommendation", ""]
    lines.append(
        "Rule: the row with the lowest LOSO mean (each held-out session weighs the same); a "
        "baseline can win, and then no model configuration is recommended."
    )
    lines.append("")
    if best is None:
        lines.append(
            f"No choice: only {len(scored)} held-out session(s) share a pair with another session."
        )
    else:
        lines.append(
            f"Lowest LOSO mean: **{best}** ({result.loso_mean(best):.4f} m²), "
            f"{result.descriptions.get(best, 'a baseline')}."
        )
        lines.append("")
        lines.append(
            f"Sessions scored: {len(scored)}; pairs scored per session: "
            + ", ".join(f"{s} {len(result.pairs[s])}" for s in scored)
            + ". Training time of the "
            f"table: {result.train_seconds / 60:.1f} min."
        )
    return "\n".join(lines) + "\n"


def build_sessions(data: Path, work: Path) -> dict[str, Path]:
    """The training CSV and a ``bag-csv`` of every bag of :data:`BAGS` (cached in ``work``)."""
    from relloc.evaluation.range_errors import MOCAP_TOPIC, bag_rows, parse_bodies, write_csv

    sessions = {TRAINING_CSV[0]: data / TRAINING_CSV[1]}
    work.mkdir(parents=True, exist_ok=True)
    for name, (folder, bodies) in BAGS.items():
        path = work / f"{name}.csv"
        if not path.exists():
            write_csv(bag_rows(data / folder, parse_bodies(bodies), MOCAP_TOPIC), path)
        sessions[name] = path
    return sessions


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA, help="shared data root")
    ap.add_argument(
        "--work", type=Path, default=ROOT / "out" / "ranging_loso", help="scratch folder"
    )
    ap.add_argument("--epochs", type=int, default=30, help="maximum epochs per model")
    ap.add_argument("--patience", type=int, default=6, help="early-stopping patience")
    ap.add_argument("--quick", action="store_true", help="one small configuration per variant")
    ap.add_argument("--page", type=Path, help="write the markdown page here")
    ap.add_argument("--json", type=Path, help="write the per-pair figures here")
    args = ap.parse_args(argv)
    sessions = build_sessions(args.data, args.work)
    matrix = pair_matrix(sessions)
    result = run_loso(
        sessions,
        args.work,
        candidates(args.quick),
        epochs=args.epochs,
        patience=args.patience,
        log=lambda m: print(m, file=sys.stderr, flush=True),
    )
    command = "python scripts/ranging_loso.py" + (" --quick" if args.quick else "")
    if args.epochs != 30 or args.patience != 6:
        command += f" --epochs {args.epochs} --patience {args.patience}"
    page = markdown(result, matrix, command + " --page docs/results/ranging_loso_generated.md")
    print(page)
    if args.page:
        args.page.write_text(page)
    if args.json:
        args.json.write_text(
            json.dumps({"pairs": result.pairs, "per_pair": result.per_pair}, indent=1)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
