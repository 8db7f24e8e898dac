"""Scanning: an RGB-D capture (or a CAD mesh) into a template database. `gscan.scan(source, output, ...)` calls
`scan` (the package is callable, see gscan/__init__.py).

- api: `scan(source, output, *, config=..., ...) -> ScanResult` (what `gscan scan` runs)
- pipeline: the stages (mode, load, features, register, posegraph, segment, fuse, database), `ScanResult`
- select: frame selection (`FrameSelector`: the frames a scan keeps, by motion and sharpness)
- store: `FrameStore` (the kept frames' images on disk while a scan runs)
- config: `ScanConfig` (the YAML configuration), `load_config`, `dump_defaults`
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
    "scan": "gscan.scan.api",
    "ScanResult": "gscan.scan.pipeline",
    "ScanConfig": "gscan.scan.config", "load_config": "gscan.scan.config", "dump_defaults": "gscan.scan.config",
    "detect_mode": "gscan.scan.capture_mode", "moving_object_masks": "gscan.scan.capture_mode",
    "STATIC_OBJECT": "gscan.scan.capture_mode", "MOVING_OBJECT": "gscan.scan.capture_mode",
    "select_keyframes": "gscan.scan.keyframes", "KeyframeParams": "gscan.scan.keyframes",
    "SegmentParams": "gscan.scan.segment", "segment_frame": "gscan.scan.segment",
    "segment_sequence": "gscan.scan.segment", "support_plane": "gscan.scan.segment",
    "FusedModel": "gscan.scan.fuse", "FusionParams": "gscan.scan.fuse", "fuse_tsdf": "gscan.scan.fuse",
    "template_frame": "gscan.scan.fuse",
    "TemplateResult": "gscan.scan.cad", "template_from_mesh": "gscan.scan.cad",
}

if TYPE_CHECKING:
    from gscan.scan.api import scan
    from gscan.scan.cad import TemplateResult, template_from_mesh
    from gscan.scan.capture_mode import MOVING_OBJECT, STATIC_OBJECT, detect_mode, moving_object_masks
    from gscan.scan.config import ScanConfig, dump_defaults, load_config
    from gscan.scan.fuse import FusedModel, FusionParams, fuse_tsdf, template_frame
    from gscan.scan.keyframes import KeyframeParams, select_keyframes
    from gscan.scan.pipeline import ScanResult
    from gscan.scan.segment import SegmentParams, segment_frame, segment_sequence, support_plane

__all__ = [
    "MOVING_OBJECT", "STATIC_OBJECT", "FusedModel", "FusionParams", "KeyframeParams", "ScanConfig", "ScanResult",
    "SegmentParams",
    "TemplateResult", "detect_mode", "dump_defaults", "fuse_tsdf", "load_config", "moving_object_masks", "scan",
    "segment_frame", "segment_sequence", "select_keyframes", "support_plane", "template_frame", "template_from_mesh",
]
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
