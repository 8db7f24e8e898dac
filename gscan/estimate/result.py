"""The outcome of one pose estimate, and its `gscan estimate --json` object (the command-line contract).

The stages are timed by a `gscan.progress.StageTimer` (seconds per stage name, the scan's timer); `timed`
writes its STAGES into `EstimateResult.timings_ms` (milliseconds, every key present, 0 for a stage not run).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from gscan.estimate.verify import Evidence
from gscan.progress import StageTimer

STAGES = ("features", "retrieval", "match", "solve", "refine", "total")


@dataclass
class EstimateResult:
    """Outcome of one estimate. T_cam_obj [4 x 4] or None (not found, see `reason`); grasps
    {name: T_cam_grasp [4 x 4]} = T_cam_obj @ T_obj_grasp (empty when not found); timings_ms per stage;
    evidence: what the accepted or refused pose rested on (None when no pose was solved).

    symmetry: for an object that looks the same under some turns (in shape and texture), the pose is the one of its
    equivalents the estimator's rule picks (gscan.estimate.symmetric) and this names the symmetries; None otherwise.
    grasp_equivalents {name: [T_cam_grasp [4 x 4], ...]}: each grasp in every equivalent pose, the reported pose's
    first (the grasp alone without symmetries). pixels: [H x W] bool the pixels the pose explains (set by
    `Estimator.estimate_all` only; not in `to_json`, whose instance object adds their count and box). T_refuted:
    a pose the rules for a pose the depth alone decided refused, that pose [4 x 4] (the verifier weighs later
    poses against it; not in `to_json`)."""

    T_cam_obj: np.ndarray | None
    score: float
    n_matches: int
    view: str | None
    reason: str | None
    grasps: dict[str, np.ndarray] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)
    method: str = "gmatch"  # "gmatch" (3D-3D) | "pnp" (2D-3D, no usable depth) | "track" (refined from a prior)
    evidence: Evidence | None = None
    symmetry: str | None = None
    grasp_equivalents: dict[str, list[np.ndarray]] = field(default_factory=dict)
    pixels: np.ndarray | None = field(default=None, repr=False)
    T_refuted: np.ndarray | None = field(default=None, repr=False)

    @property
    def found(self) -> bool:
        return self.T_cam_obj is not None

    def to_json(self) -> dict:
        """The `gscan estimate --json` object (the command-line contract's keys, plus "method", "symmetry",
        "grasp_equivalents" and "depth_only"); matrices as nested lists, metres."""
        return {"T_cam_obj": matrix_json(self.T_cam_obj), "score": float(self.score), "n_matches": int(self.n_matches),
                "view": self.view, "reason": self.reason, "grasps": {k: matrix_json(v) for k, v in self.grasps.items()},
                "timings_ms": {k: float(self.timings_ms.get(k, 0.0)) for k in STAGES}, "method": self.method,
                "symmetry": self.symmetry,
                "grasp_equivalents": {k: [matrix_json(T) for T in v] for k, v in self.grasp_equivalents.items()},
                "depth_only": self.depth_only}

    @property
    def depth_only(self) -> bool:
        """Whether the depth alone decided the found pose (a template with depth keypoints whose image keypoints
        could not judge it: `gscan.estimate.verify.decided_by_depth`)."""
        return self.found and self.evidence is not None and self.evidence.depth_only


def matrix_json(T: np.ndarray | None) -> list[list[float]] | None:
    """[4 x 4] -> nested lists of floats (None stays None)."""
    return None if T is None else [[float(x) for x in row] for row in np.asarray(T)]


def ms_since(t0: float) -> float:
    """Milliseconds of wall time since perf_counter() returned t0."""
    return (time.perf_counter() - t0) * 1e3


def found(T_cam_obj: np.ndarray, score: float, n: int, view: str | None, method: str,
          evidence: Evidence | None = None) -> EstimateResult:
    """A found pose T_cam_obj [4 x 4] (grasps and timings are the estimator's to add)."""
    return EstimateResult(T_cam_obj, float(score), int(n), view, None, method=method, evidence=evidence)


def not_found(reason: str, n: int = 0, view: str | None = None, score: float = 0.0, method: str = "gmatch",
              evidence: Evidence | None = None) -> EstimateResult:
    """No pose, for `reason` (one line)."""
    return EstimateResult(None, float(score), int(n), view, reason, method=method, evidence=evidence)


def timed(res: EstimateResult, timer: StageTimer, t0: float) -> EstimateResult:
    """`res` with its timings_ms: the timer's STAGES in milliseconds, and "total" since perf_counter() gave t0."""
    res.timings_ms = {k: 1e3 * timer.timings.get(k, 0.0) for k in STAGES if k != "total"}
    res.timings_ms["total"] = ms_since(t0)
    return res
