"""Pose estimation of a templated object in RGB-D frames, and tracking through sequences.

    Estimator.from_path(template) -> Estimator;  Estimator.estimate(frame, mask=None) -> EstimateResult
    Tracker(estimator).step(frame) -> TrackStep;  track_sequence(estimator, sequence) -> TrackRun
    write_poses(run, out_dir, force=False): one `ob_in_cam` 4x4 text file per frame with a pose

Modules: `estimator` (features, retrieval, joint matching, solve), `query` (the frame's full-image work, once),
`verify` (the evidence a pose is accepted on), `refine` (anchored ICP), `pnp` (2D-3D fallback without depth),
`track` (the previous pose as a prior), `result` (EstimateResult, the `estimate --json` object).
"""
from gscan.estimate.estimator import EstimateParams, Estimator
from gscan.estimate.result import STAGES, EstimateResult
from gscan.estimate.track import STATUSES, Tracker, TrackParams, TrackRun, TrackStep, track_sequence, write_poses
from gscan.estimate.verify import AcceptParams, Evidence

__all__ = ["STAGES", "STATUSES", "AcceptParams", "EstimateParams", "EstimateResult", "Estimator", "Evidence",
           "TrackParams", "TrackRun", "TrackStep", "Tracker", "track_sequence", "write_poses"]
