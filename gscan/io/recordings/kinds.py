"""Which paths are recordings (no heavy import: `gscan.io.layouts.detect_format` asks this first)."""
from __future__ import annotations

from pathlib import Path

#: Recording kinds: a ROS 1 bag (RealSense `.bag` or any ROS 1 bag of sensor_msgs images), a rosbag2
#: sqlite3 file, an MCAP file, and a rosbag2 folder (metadata.yaml beside its .db3 / .mcap files).
RECORDING_FORMATS = ("bag", "db3", "mcap", "rosbag2")
SUFFIXES = {".bag": "bag", ".db3": "db3", ".mcap": "mcap"}


def recording_format(path: str | Path) -> str | None:
    """The recording kind of `path` ("bag" | "db3" | "mcap" | "rosbag2"), None when it is not a recording.

    A file counts by its suffix (it need not be readable yet: the reader names what is wrong with it);
    a folder counts when it holds a rosbag2 metadata.yaml.
    """
    p = Path(path)
    if p.is_dir():
        return "rosbag2" if (p / "metadata.yaml").is_file() else None
    return SUFFIXES.get(p.suffix.lower())
