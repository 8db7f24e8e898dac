"""Keypoint matching: GMatch (geometry-constrained search, its numba kernel in `kernel`) and the descriptor
baselines it is compared with.

- gmatch: `gmatch(pts_s, pts_t, dist, eps_f, params) -> GMatchResult`, `GMatchParams`, `default_eps_f`
- baselines: `run_baseline`, `BaselineParams`, `BaselineResult`, `BASELINES` (nearest neighbours, ratio test,
  mutual, RANSAC, LO-RANSAC, FGR)
"""
from __future__ import annotations

from gscan.matching.baselines import BASELINES, BaselineParams, BaselineResult, run_baseline
from gscan.matching.gmatch import CONSTRAINTS, ORDERS, GMatchParams, GMatchResult, default_eps_f, gmatch

__all__ = ["BASELINES", "CONSTRAINTS", "ORDERS", "BaselineParams", "BaselineResult", "GMatchParams", "GMatchResult",
           "default_eps_f", "gmatch", "run_baseline"]
