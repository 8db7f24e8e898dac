"""The capture folder a recording goes into, checked apart from the camera and the recording loop: `gscan capture`
refuses a bad folder before OpenCV's and the motion cue's libraries load."""
from __future__ import annotations

from pathlib import Path

from gscan.errors import InputError
from gscan.io.output import check_not_input, check_output_path


def check_capture_output(output: Path, recording: Path | None = None) -> None:
    """InputError naming `output` unless it is a new folder or an empty one that can be written, apart from
    the `recording` played (`check_not_input`)."""
    check_not_input(output, [recording])
    if output.exists():
        if not output.is_dir():
            raise InputError(output, "exists and is not a folder")
        if any(output.iterdir()):
            raise InputError(output, "exists and is not empty; choose a new capture folder")
    check_output_path(output / "cam_K.txt")
