"""Keypoint matching: GMatch (geometry-constrained search, its numba kernel in `kernel`) and the descriptor
baselines it is compared with.

- gmatch: `gmatch(pts_s, pts_t, dist, eps_f, params) -> GMatchResult`
- params: `GMatchParams`, `default_eps_f` (numpy and pydantic only)
- baselines: `run_baseline`, `BaselineParams`, `BaselineResult`, `BASELINES` (nearest neighbours, ratio test,
  mutual, RANSAC, LO-RANSAC, FGR)
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from gscan._lazy import lazy_exports

# names imported on first use (PEP 562): the settings (`params`) are read without loading the numba kernels
_EXPORTS = {
    "BASELINES": "gscan.matching.baselines", "BaselineParams": "gscan.matching.baselines",
    "BaselineResult": "gscan.matching.baselines", "run_baseline": "gscan.matching.baselines",
    "CONSTRAINTS": "gscan.matching.params", "ORDERS": "gscan.matching.params",
    "GMatchParams": "gscan.matching.params", "default_eps_f": "gscan.matching.params",
    "GMatchResult": "gscan.matching.gmatch", "gmatch": "gscan.matching.gmatch",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:
    from gscan.matching.baselines import BASELINES, BaselineParams, BaselineResult, run_baseline
    from gscan.matching.gmatch import GMatchResult, gmatch
    from gscan.matching.params import CONSTRAINTS, ORDERS, GMatchParams, default_eps_f

__all__ = ["BASELINES", "CONSTRAINTS", "ORDERS", "BaselineParams", "BaselineResult", "GMatchParams", "GMatchResult",
           "default_eps_f", "gmatch", "run_baseline"]
