"""Pose estimation: the object's pose T_cam_obj in a new RGB-D frame against a template (CPU).

- estimator: `Estimator` (`from_path`, `estimate(frame) -> EstimateResult`), `EstimateParams`
"""
from __future__ import annotations

from gscan.estimate.estimator import EstimateParams, EstimateResult, Estimator

__all__ = ["EstimateParams", "EstimateResult", "Estimator"]
