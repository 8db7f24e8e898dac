"""Recordings as RGB-D sequences: RealSense `.bag`, ROS 1 bags, rosbag2 (`.db3`, `.mcap`, bag folders).

    open_recording(path, color_topic=None, depth_topic=None, intrinsics=None, depth_scale=None) -> RecordingSequence
    recording_format(path) -> "bag" | "db3" | "mcap" | "rosbag2" | None

`gscan.io.sequence.open_sequence` opens a recording path through `open_recording`. Modules: `source` (one
interface over rosbags and mcap), `messages` (Image parsing), `realsense` / `ros` (which topics, intrinsics,
depth scale, extrinsics), `pairing` (timestamps), `sequence` (streaming frames; depth reprojected into the colour
camera by `gscan.io.align`).
Names are imported on first use, so that asking whether a path is a recording loads neither numba nor rosbags.
"""
from __future__ import annotations

import importlib
from typing import Any

_NAMES = {
    "RECORDING_FORMATS": "kinds", "recording_format": "kinds",
    "RecordingSequence": "sequence", "open_recording": "sequence",
    "StreamSetup": "streams",
}
__all__ = ["RECORDING_FORMATS", "RecordingSequence", "StreamSetup", "open_recording", "recording_format"]


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        return getattr(importlib.import_module(f"gscan.io.recordings.{_NAMES[name]}"), name)
    raise AttributeError(f"module 'gscan.io.recordings' has no attribute {name!r}")
