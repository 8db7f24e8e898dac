"""gscan: RGB-D object scanning into GMatch templates, and CPU 6DoF pose estimation.

Names are imported on first use (PEP 562), so `import gscan` and the command line stay fast.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.2.0"

_EXPORTS = {
    "Intrinsics": "gscan.io.camera",
    "RGBDFrame": "gscan.io.camera",
    "GscanError": "gscan.errors",
    "InputError": "gscan.errors",
    "serve": "gscan.serve",
}

if TYPE_CHECKING:
    from gscan.errors import GscanError, InputError
    from gscan.io.camera import Intrinsics, RGBDFrame
    from gscan.serve.server import serve

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'gscan' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
