"""`scan(source, output, options)`: the scan stage's Python entry point, what `gscan scan` runs."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from gscan.progress import Progress
from gscan.scanning.config import ScanConfig, load_config
from gscan.scanning.options import ScanOptions
from gscan.scanning.pipeline import ScanResult, run_scan

_OPTION_NAMES = frozenset(f.name for f in fields(ScanOptions))


def scan(source: str | Path | Sequence[str | Path], output: str | Path, options: ScanOptions | None = None, *,
         progress: Progress | None = None, **changes: Any) -> ScanResult:
    """Register every view of an RGB-D capture (or of several captures of one object) into one object frame and
    write a template database.

    Args:
        source: the capture folder (capture, Open3D, TUM or BOP layout), or a recording (a RealSense or ROS 1
            .bag, a rosbag2 .db3 / .mcap or its folder); or a list of them, captures of one object (upright,
            upside down, another day: the object may have moved against the table), joined into one template,
            their frames named `CAPTURE/FRAME`; or a BOP dataset folder whose onboarding captures of the object
            `obj_id` are read as its captures (`gscan.io.captures`).
        output: the template database to write (`OBJ.gscan`).
        options: the scan's options (`ScanOptions`: input layout, intrinsics, depth scale and depth camera, mode,
            segmentation, resume / force, the stages' settings `config`, ...); None: the defaults.
        progress: stage progress reporting (`gscan.progress.Progress`), none by default.
        changes: `ScanOptions` fields changed from `options`, by name (`gscan.scan(src, out, mode="moving-object")`);
            `config` may also be a YAML file (`gscan config dump` shows its keys).

    Returns:
        ScanResult: frames read and registered, the unregistered and skipped frames by name, edges accepted and
        rejected, the capture mode, mesh size, keyframes and seconds per stage. The poses T_obj_cam [4 x 4] of
        the views are in the database (`TemplateDB.poses`).

    Raises:
        InputError: bad input, naming the file (an unreadable capture, an existing output without `force`, a
            configuration that does not validate).
        ValueError: an unknown option, `format` or `mode`.
        TypeError: an option that is not a `ScanOptions` field.
    """
    unknown = sorted(set(changes) - _OPTION_NAMES)
    if unknown:
        raise TypeError(f"scan() got unknown options: {', '.join(unknown)} (ScanOptions fields)")
    config = changes.get("config")
    if config is not None and not isinstance(config, ScanConfig):
        changes["config"] = load_config(config)
    opts = replace(options or ScanOptions(), **changes)
    sources = [Path(source)] if isinstance(source, (str, Path)) else [Path(s) for s in source]
    if not sources:
        raise ValueError("scan() needs at least one capture")
    return run_scan(sources, Path(output), opts, progress=progress)
