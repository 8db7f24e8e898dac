"""`scan(source, output, ...)`: the scan stage's Python entry point, what `gscan scan` runs."""
from __future__ import annotations

from pathlib import Path

from gscan.io.layouts import FORMATS
from gscan.progress import Progress
from gscan.scan.capture_mode import MOVING_OBJECT, STATIC_OBJECT
from gscan.scan.config import ScanConfig, load_config
from gscan.scan.pipeline import ScanOptions, ScanResult, run_scan

MODES = ("auto", STATIC_OBJECT, MOVING_OBJECT)


def scan(source: str | Path, output: str | Path, *, config: ScanConfig | str | Path | None = None,
         format: str = "auto", intrinsics: str | Path | None = None, depth_scale: float | None = None,
         mode: str = "auto", segment: bool = True, resume: bool = False, force: bool = False,
         obj_id: int | None = None, color_topic: str | None = None, depth_topic: str | None = None,
         depth_intrinsics: str | Path | None = None, depth_to_color: str | Path | None = None,
         progress: Progress | None = None, meta: dict | None = None) -> ScanResult:
    """Register every view of an RGB-D capture into one object frame and write a template database.

    Args:
        source: the capture folder (capture, Open3D, TUM or BOP layout), or a recording (a RealSense or ROS 1
            .bag, a rosbag2 .db3 / .mcap or its folder).
        output: the template database to write (`OBJ.gscan`).
        config: the scan configuration: a ScanConfig, a YAML file (`gscan config dump` shows the keys), or None
            for the defaults.
        format: "auto" (detected) or "capture" | "open3d" | "tum" | "bop".
        intrinsics: a cam_K.txt or Open3D intrinsics JSON overriding the layout's own.
        depth_scale: metres per raw depth unit overriding the layout's.
        mode: "auto" | "static-object" | "moving-object".
        segment: fuse the object alone (False: the whole scene).
        resume: continue an interrupted scan into `output`.
        force: replace an existing `output`.
        obj_id: BOP folder: the object to scan (default: the first in scene_gt.json).
        color_topic, depth_topic: a recording's image topics (default: detected when unambiguous).
        depth_intrinsics, depth_to_color: for depth images not registered to the colour images (a Kinect v1):
            the depth camera's intrinsics (cam_K.txt / Open3D JSON) and its pose in the colour camera
            (T_color_depth, a 4 x 4 text or JSON matrix in metres; None: the same centre and axes); the depth
            is reprojected into the colour camera.
        progress: stage progress reporting (`gscan.progress.Progress`), none by default.
        meta: more keys for the database's meta table (JSON values), e.g. a mark of the tool that wrote it.

    Returns:
        ScanResult: frames read and registered, the unregistered and skipped frames by name, edges accepted and
        rejected, the capture mode, mesh size, keyframes and seconds per stage. The poses T_obj_cam [4 x 4] of
        the views are in the database (`TemplateDB.poses`).

    Raises:
        InputError: bad input, naming the file (an unreadable capture, an existing output without `force`, a
            configuration that does not validate).
        ValueError: an unknown `format` or `mode`.
    """
    if format not in ("auto", *FORMATS):
        raise ValueError(f"format must be one of {', '.join(('auto', *FORMATS))}, not {format!r}")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, not {mode!r}")
    cfg = config if isinstance(config, ScanConfig) else load_config(config)
    opts = ScanOptions(input_dir=Path(source), output=Path(output), fmt=format,
                       intrinsics=None if intrinsics is None else Path(intrinsics), depth_scale=depth_scale,
                       mode=mode, segment=segment, resume=resume, force=force, config=cfg, obj_id=obj_id,
                       color_topic=color_topic, depth_topic=depth_topic, meta=dict(meta or {}),
                       depth_intrinsics=None if depth_intrinsics is None else Path(depth_intrinsics),
                       depth_to_color=None if depth_to_color is None else Path(depth_to_color))
    return run_scan(opts, progress=progress)
