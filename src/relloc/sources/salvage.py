"""Reading what is left of a damaged rosbag2 recording.

A bag cut short (a robot's disk filled, the recorder was killed) still holds most of its
messages. The rosbag2 source calls these when ``rosbags`` cannot open or read a ``.db3`` bag:
:func:`salvaged_copy` copies every row sqlite can still read into a temporary bag folder that
``rosbags`` opens, and :func:`readable_rows` reads the rest of a bag whose stream broke off.
Both stop at the first unreadable page of a file and keep what came before it; MCAP bags are
not salvaged (a broken MCAP stream ends where it breaks).
"""

from __future__ import annotations

import shutil
import sqlite3
import tempfile
from pathlib import Path
from typing import Any

__all__ = ["listed_messages", "readable_rows", "salvaged_copy"]


def salvaged_copy(path: Path) -> tuple[Path, str] | None:
    """A copy of a damaged ``.db3`` bag folder holding every message row sqlite can still read
    (in storage order, up to the first unreadable page of each file), with how many of the
    messages its metadata lists that is; ``None`` when nothing can be read."""
    if not path.is_dir() or not (path / "metadata.yaml").exists():
        return None
    folder = Path(tempfile.mkdtemp(prefix="relloc-salvage-"))
    shutil.copy(path / "metadata.yaml", folder / "metadata.yaml")
    kept = 0
    for db in sorted(path.glob("*.db3")):
        try:
            src = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
            dst = sqlite3.connect(folder / db.name)
            tables = src.execute(
                "SELECT name, sql FROM sqlite_master WHERE type = 'table'"
            ).fetchall()
        except sqlite3.Error:
            continue
        for name, sql in tables:
            dst.execute(sql)
            try:
                for row in src.execute(f'SELECT * FROM "{name}"'):
                    dst.execute(f'INSERT INTO "{name}" VALUES ({", ".join("?" * len(row))})', row)
                    kept += name == "messages"
            except sqlite3.Error:
                pass  # the first damaged page: what came before it is kept
        dst.commit()
        dst.close()
        src.close()
    if not kept:
        shutil.rmtree(folder, ignore_errors=True)
        return None
    listed = listed_messages(path / "metadata.yaml")
    lost = max(listed - kept, 0)
    return (
        folder,
        f"{kept} of its {listed} messages readable, {lost} ({100.0 * lost / max(listed, 1):.0f} %) lost",
    )


def listed_messages(metadata: Path) -> int:
    """The message count a bag's metadata lists (0 if it cannot say)."""
    from ruamel.yaml import YAML

    try:
        info = YAML(typ="safe").load(metadata.read_text())["rosbag2_bagfile_information"]
        return int(info["message_count"])
    except Exception:
        return 0


def readable_rows(path: Path, conns: list[Any], after: int) -> list[tuple[Any, int, bytes]]:
    """What sqlite can still read of a damaged ``.db3`` bag: its message rows in storage order
    up to the first unreadable page, for ``conns``' topics, in receive order, less the first
    ``after`` (already read in order). Empty for other storage."""
    files = [path] if path.suffix == ".db3" else sorted(path.glob("*.db3"))
    by_topic = {c.topic: c for c in conns}
    rows: list[tuple[Any, int, bytes]] = []
    for db in files:
        try:
            con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        except sqlite3.Error:
            continue
        try:
            topics = {
                i: by_topic[n]
                for i, n in con.execute("SELECT id, name FROM topics")
                if n in by_topic
            }
            for topic_id, stamp, data in con.execute(
                "SELECT topic_id, timestamp, data FROM messages"
            ):
                if topic_id in topics:
                    rows.append((topics[topic_id], int(stamp), bytes(data)))
        except sqlite3.Error:
            pass  # the first damaged page: what came before it is kept
        finally:
            con.close()
    rows.sort(key=lambda r: r[1])
    return rows[after:]
