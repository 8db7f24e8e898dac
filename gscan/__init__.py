"""gscan: RGB-D object scanning into GMatch templates, and CPU 6DoF pose estimation.

The public API (details in each name's docstring; frames in names: `T_cam_obj` maps object-frame points into
the camera frame, [4 x 4] float64, metres):

- input: `open_sequence(path) -> Sequence`, `load_frame(color, depth, intrinsics) -> RGBDFrame`, `Intrinsics`,
  `DepthCamera`
- keypoints and matching: `extract_features(frame) -> Features`, `gmatch(pts_s, pts_t, dist, eps_f)`,
  `register_frames(frame_s, frame_t) -> PairResult`
- templates: `scan(source, output, options) -> ScanResult` with `ScanOptions`, `template_from_mesh(mesh, output)
  -> TemplateResult`, `TemplateDB`, `export(db, format, out) -> ExportResult`
- pose estimation: `Estimator.from_path(db).estimate(frame) -> EstimateResult`, `Tracker`; `serve(templates)`
  (the HTTP service of `gscan serve`)
- settings: `ScanConfig` (the scan's stages), `EstimateParams`, `FeatureParams`, `GMatchParams`, `RegisterParams`
- errors: `GscanError`, `InputError` (bad input, naming the file)

Names are imported on first use (PEP 562), so `import gscan` and the command line stay fast. The stages live in
subpackages named for them (`gscan.scanning`, `gscan.exporters`, `gscan.service`, ...).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from gscan._lazy import lazy_exports
from gscan._version import __version__

_EXPORTS = {
    "open_sequence": "gscan.io.sequence",
    "load_frame": "gscan.io.images",
    "Intrinsics": "gscan.io.camera",
    "DepthCamera": "gscan.io.camera",
    "RGBDFrame": "gscan.io.camera",
    "extract_features": "gscan.features",
    "Features": "gscan.features",
    "FeatureParams": "gscan.features",
    "gmatch": "gscan.matching.gmatch",
    "GMatchParams": "gscan.matching.gmatch",
    "register_frames": "gscan.registration.frames",
    "RegisterParams": "gscan.registration.pairwise",
    "PairResult": "gscan.registration.pairwise",
    "scan": "gscan.scanning.api",
    "ScanOptions": "gscan.scanning.options",
    "ScanConfig": "gscan.scanning.config",
    "ScanResult": "gscan.scanning.pipeline",
    "template_from_mesh": "gscan.scanning.cad",
    "TemplateResult": "gscan.scanning.cad",
    "TemplateDB": "gscan.template.db",
    "Estimator": "gscan.estimate.estimator",
    "EstimateParams": "gscan.estimate.estimator",
    "EstimateResult": "gscan.estimate.estimator",
    "Tracker": "gscan.estimate.track",
    "export": "gscan.exporters",
    "ExportResult": "gscan.exporters",
    "serve": "gscan.service.server",
    "GscanError": "gscan.errors",
    "InputError": "gscan.errors",
}

if TYPE_CHECKING:
    from gscan.errors import GscanError, InputError
    from gscan.estimate.estimator import EstimateParams, EstimateResult, Estimator
    from gscan.estimate.track import Tracker
    from gscan.exporters import ExportResult, export
    from gscan.features import FeatureParams, Features, extract_features
    from gscan.io.camera import DepthCamera, Intrinsics, RGBDFrame
    from gscan.io.images import load_frame
    from gscan.io.sequence import open_sequence
    from gscan.matching.gmatch import GMatchParams, gmatch
    from gscan.registration.frames import register_frames
    from gscan.registration.pairwise import PairResult, RegisterParams
    from gscan.scanning.api import scan
    from gscan.scanning.cad import TemplateResult, template_from_mesh
    from gscan.scanning.config import ScanConfig
    from gscan.scanning.options import ScanOptions
    from gscan.scanning.pipeline import ScanResult
    from gscan.service.server import serve
    from gscan.template.db import TemplateDB

__all__ = [
    "DepthCamera", "EstimateParams", "EstimateResult", "Estimator", "ExportResult", "FeatureParams", "Features",
    "GMatchParams", "GscanError", "InputError", "Intrinsics", "PairResult", "RGBDFrame", "RegisterParams",
    "ScanConfig", "ScanOptions", "ScanResult", "TemplateDB", "TemplateResult", "Tracker", "__version__", "export",
    "extract_features", "gmatch", "load_frame", "open_sequence", "register_frames", "scan", "serve",
    "template_from_mesh",
]

__getattr__, _dir = lazy_exports(__name__, _EXPORTS)


def __dir__() -> list[str]:
    return __all__
