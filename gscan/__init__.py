"""gscan: RGB-D object scanning into GMatch templates, and CPU 6DoF pose estimation.

The public API (details in each name's docstring; frames in names: `T_cam_obj` maps object-frame points into
the camera frame, [4 x 4] float64, metres):

- input: `open_sequence(path) -> Sequence`, `load_frame(color, depth, intrinsics) -> RGBDFrame`, `Intrinsics`
- keypoints and matching: `extract_features(frame) -> Features`, `gmatch(pts_s, pts_t, dist, eps_f)`,
  `register_frames(frame_s, frame_t) -> PairResult`
- templates: `scan(source, output) -> ScanResult`, `template_from_mesh(mesh, output) -> TemplateResult`,
  `TemplateDB`, `export(db, format, out) -> ExportResult`
- pose estimation: `Estimator.from_path(db).estimate(frame) -> EstimateResult`; `serve(templates)` (the HTTP
  service of `gscan serve`)
- parameters: `FeatureParams`, `GMatchParams`, `RegisterParams`, `ScanConfig`, `EstimateParams`
- errors: `GscanError`, `InputError` (bad input, naming the file)

Names are imported on first use (PEP 562), so `import gscan` and the command line stay fast.

`scan` and `export` are also the names of the stage subpackages `gscan.scan` and `gscan.export`; Python binds a
subpackage to its name in `gscan` when it is first imported, so those two names are the subpackages, made
callable: `gscan.scan(...)` runs `gscan.scan.api.scan`, `gscan.export(...)` runs `gscan.export.export`, and
`gscan.scan.pipeline` stays a module path. `serve` is the subpackage `gscan.serve` too, which makes itself callable
(`gscan.serve(...)` starts the service). Type checkers see the functions.
"""
from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING, Any

from gscan._lazy import lazy_exports
from gscan._version import __version__

_EXPORTS = {
    "open_sequence": "gscan.io.sequence",
    "load_frame": "gscan.io.images",
    "Intrinsics": "gscan.io.camera",
    "RGBDFrame": "gscan.io.camera",
    "extract_features": "gscan.features",
    "Features": "gscan.features",
    "FeatureParams": "gscan.features",
    "gmatch": "gscan.matching.gmatch",
    "GMatchParams": "gscan.matching.gmatch",
    "register_frames": "gscan.registration.pairwise",
    "RegisterParams": "gscan.registration.pairwise",
    "PairResult": "gscan.registration.pairwise",
    "ScanConfig": "gscan.scan.config",
    "ScanResult": "gscan.scan.pipeline",
    "template_from_mesh": "gscan.scan.cad",
    "TemplateResult": "gscan.scan.cad",
    "TemplateDB": "gscan.template.db",
    "Estimator": "gscan.estimate.estimator",
    "EstimateParams": "gscan.estimate.estimator",
    "EstimateResult": "gscan.estimate.estimator",
    "GscanError": "gscan.errors",
    "InputError": "gscan.errors",
    "serve": "gscan.serve",
}
# public names that are also subpackages: (the function's module, its name)
_CALLABLE_PACKAGES = {"scan": ("gscan.scan.api", "scan"), "export": ("gscan.export", "export")}

if TYPE_CHECKING:
    from gscan.errors import GscanError, InputError
    from gscan.estimate.estimator import EstimateParams, EstimateResult, Estimator
    from gscan.export import export as export
    from gscan.features import FeatureParams, Features, extract_features
    from gscan.io.camera import Intrinsics, RGBDFrame
    from gscan.io.images import load_frame
    from gscan.io.sequence import open_sequence
    from gscan.matching.gmatch import GMatchParams, gmatch
    from gscan.registration.pairwise import PairResult, RegisterParams, register_frames
    from gscan.scan.api import scan as scan
    from gscan.scan.cad import TemplateResult, template_from_mesh
    from gscan.scan.config import ScanConfig
    from gscan.scan.pipeline import ScanResult
    from gscan.serve.server import serve as serve
    from gscan.template.db import TemplateDB

__all__ = [
    "EstimateParams", "EstimateResult", "Estimator", "FeatureParams", "Features", "GMatchParams", "GscanError",
    "InputError", "Intrinsics", "PairResult", "RGBDFrame", "RegisterParams", "ScanConfig", "ScanResult", "TemplateDB",
    "TemplateResult", "__version__", "export", "extract_features", "gmatch", "load_frame", "open_sequence",
    "register_frames", "scan", "serve", "template_from_mesh",
]

_lazy_getattr, _lazy_dir = lazy_exports(__name__, _EXPORTS)


class _CallablePackage(types.ModuleType):
    """A stage subpackage that is also a public function of gscan (`_CALLABLE_PACKAGES`)."""

    def _function(self) -> Any:
        module, name = _CALLABLE_PACKAGES[self.__name__.rpartition(".")[2]]
        return getattr(importlib.import_module(module), name)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._function()(*args, **kwargs)

    @property
    def __signature__(self) -> Any:  # inspect.signature / help show the function's
        import inspect  # only when asked: `import gscan` stays light

        return inspect.signature(self._function())


class _Gscan(types.ModuleType):
    def __getattribute__(self, name: str) -> Any:
        value = super().__getattribute__(name)
        if name in _CALLABLE_PACKAGES and type(value) is types.ModuleType:
            value.__class__ = _CallablePackage
        return value


def __getattr__(name: str) -> Any:
    if name in _CALLABLE_PACKAGES:  # not imported yet: importing binds the subpackage to the name
        return importlib.import_module(f"{__name__}.{name}")
    return _lazy_getattr(name)


def __dir__() -> list[str]:
    return __all__


sys.modules[__name__].__class__ = _Gscan
