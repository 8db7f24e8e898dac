"""Scanning: an RGB-D capture (or a CAD mesh) into a template database (`gscan.scan` is `scan` below).

- api: `scan(source, output, options) -> ScanResult` (what `gscan scan` runs)
- options: `ScanOptions` (every option of one scan, one typed value)
- pipeline: the stages (camera, mode, load, features, noise, register, posegraph, segment, fuse, symmetry, database),
  `ScanResult`; frames: the input's frames loaded and read back; output: the database, new or resumed; camera:
  the colour focal length checked before the scan
- select: frame selection (`FrameSelector`: the frames a scan keeps, by motion and sharpness)
- store: `FrameStore` (the kept frames' images on disk while a scan runs)
- config: `ScanConfig` (the YAML configuration: a section per stage, that stage's settings class), `for_capture`,
  `load_config`, `dump_defaults`
- capture_mode: `detect_mode` (static object or moving object), `moving_object_masks`
- keyframes: `select_keyframes`, `KeyframeParams`
- segment: `segment_frame`, `segment_sequence`, `support_plane`, `SegmentParams`
- fuse: `fuse_tsdf -> FusedModel`, `template_frame`, `FusionParams`
- cad: `template_from_mesh(mesh, output) -> TemplateResult` (rendered snapshots of a CAD mesh)

Names are imported on first use (PEP 562): `gscan config dump` reads the configuration without loading the
pipeline.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from gscan._lazy import lazy_exports

_EXPORTS = {
    "scan": "gscan.scanning.api", "ScanOptions": "gscan.scanning.options",
    "ScanResult": "gscan.scanning.pipeline",
    "ScanConfig": "gscan.scanning.config", "load_config": "gscan.scanning.config",
    "for_capture": "gscan.scanning.config", "dump_defaults": "gscan.scanning.config",
    "detect_mode": "gscan.scanning.capture_mode", "moving_object_masks": "gscan.scanning.capture_mode",
    "STATIC_OBJECT": "gscan.scanning.capture_mode", "MOVING_OBJECT": "gscan.scanning.capture_mode",
    "select_keyframes": "gscan.scanning.keyframes", "KeyframeParams": "gscan.scanning.keyframes",
    "SegmentParams": "gscan.scanning.segment", "segment_frame": "gscan.scanning.segment",
    "segment_sequence": "gscan.scanning.segment", "support_plane": "gscan.scanning.segment",
    "FusedModel": "gscan.scanning.fuse", "FusionParams": "gscan.scanning.fuse", "fuse_tsdf": "gscan.scanning.fuse",
    "template_frame": "gscan.scanning.fuse",
    "TemplateResult": "gscan.scanning.cad", "template_from_mesh": "gscan.scanning.cad",
}

if TYPE_CHECKING:
    from gscan.scanning.api import scan
    from gscan.scanning.cad import TemplateResult, template_from_mesh
    from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT, detect_mode, moving_object_masks
    from gscan.scanning.config import ScanConfig, dump_defaults, for_capture, load_config
    from gscan.scanning.fuse import FusedModel, FusionParams, fuse_tsdf, template_frame
    from gscan.scanning.keyframes import KeyframeParams, select_keyframes
    from gscan.scanning.options import ScanOptions
    from gscan.scanning.pipeline import ScanResult
    from gscan.scanning.segment import SegmentParams, segment_frame, segment_sequence, support_plane

__all__ = [
    "MOVING_OBJECT", "STATIC_OBJECT", "FusedModel", "FusionParams", "KeyframeParams", "ScanConfig", "ScanOptions",
    "ScanResult", "SegmentParams",
    "TemplateResult", "detect_mode", "dump_defaults", "for_capture", "fuse_tsdf", "load_config", "moving_object_masks",
    "scan", "segment_frame", "segment_sequence", "select_keyframes", "support_plane", "template_frame",
    "template_from_mesh",
]
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
