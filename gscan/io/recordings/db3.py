"""Lost rows of a rosbag2 sqlite3 file (`.db3`), found from the data itself.

rosbag2's sqlite3 storage creates `messages(id INTEGER PRIMARY KEY, topic_id, timestamp, data)` and inserts each
message without an id (`INSERT INTO messages (timestamp, topic_id, data)`), so SQLite numbers the rows 1, 2, 3, ...
in the order they were written. A row missing from that sequence is a message the recorder wrote and the file no
longer holds (rows lost to damage, or dropped by a repair such as sqlite3's `.recover`). Which topic a lost row was
on is not stored anywhere else; the messages each topic should hold are: in a bag folder's metadata.yaml, or in
the `metadata` table that rosbag2 (Iron and later) writes into the file when the recording ends. Rows lost at the
end of the file leave no gap in the ids; only those counts tell them.
"""
from __future__ import annotations

import logging
import sqlite3
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

import yaml

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RowGap:
    """Message ids first..last (inclusive) missing from a `.db3`; the log times (ns) of the rows before and after
    the gap (None: the gap starts at id 1)."""

    file: Path
    first: int
    last: int
    before_ns: int | None
    after_ns: int

    @property
    def count(self) -> int:
        return self.last - self.first + 1


@dataclass
class Db3Rows:
    """What a `.db3` holds: its id gaps, the rows per topic, and the messages per topic its own metadata lists (None
    when it has none)."""

    gaps: list[RowGap]
    rows: dict[str, int]
    listed: dict[str, int] | None


def _connect(path: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)


def _listed(con: sqlite3.Connection) -> dict[str, int] | None:
    """topic -> message_count of the metadata rosbag2 stored in the file, None when there is none, or when it is
    the metadata of a bag split into several files (its counts are the whole bag's, not this file's)."""
    if not con.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'metadata'").fetchone():
        return None
    row = con.execute("SELECT metadata FROM metadata ORDER BY id DESC LIMIT 1").fetchone()
    if row is None:
        return None
    try:
        meta = yaml.safe_load(row[0])
        info = meta.get("rosbag2_bagfile_information", meta)
        if len(info.get("relative_file_paths") or []) > 1:
            return None
        return {str(t["topic_metadata"]["name"]): int(t["message_count"])
                for t in info["topics_with_message_count"]}
    except (yaml.YAMLError, AttributeError, KeyError, TypeError, ValueError):
        return None


def db3_rows(path: Path) -> Db3Rows:
    """The id gaps, rows per topic and listed counts of the `.db3` at `path` (sqlite3.Error when its tables cannot
    be read)."""
    with closing(_connect(path)) as con:
        gaps = [RowGap(path, (prev or 0) + 1, cur - 1, prev_ns, cur_ns) for prev, prev_ns, cur, cur_ns in con.execute(
            "SELECT prev, prev_ns, id, timestamp FROM (SELECT id, timestamp, LAG(id) OVER (ORDER BY id) AS prev, "
            "LAG(timestamp) OVER (ORDER BY id) AS prev_ns FROM messages) WHERE id - COALESCE(prev, 0) > 1")]
        rows = {str(name): int(n) for name, n in con.execute(
            "SELECT topics.name, count(messages.id) FROM topics LEFT JOIN messages ON topics.id = messages.topic_id "
            "GROUP BY topics.id")}
        return Db3Rows(gaps, rows, _listed(con))


def db3_files(path: Path) -> list[Path]:
    """The `.db3` files of a recording: the file itself, or those of a bag folder (its metadata.yaml's
    relative_file_paths, else every .db3 in it)."""
    if path.is_file():
        return [path] if path.suffix.lower() == ".db3" else []
    try:
        meta = yaml.safe_load((path / "metadata.yaml").read_text())
        names = meta["rosbag2_bagfile_information"]["relative_file_paths"]
        files = [path / Path(str(n)).name for n in names]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        files = sorted(path.glob("*.db3"))
    return [f for f in files if f.suffix.lower() == ".db3" and f.is_file()]
