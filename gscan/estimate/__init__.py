"""Pose estimation of a templated object in RGB-D frames, and tracking through sequences.

    Estimator.from_path(template) -> Estimator;  Estimator.estimate(frame, mask=None) -> EstimateResult
    Estimator.estimate_all(frame) -> Instances (every instance); estimate_templates(estimators, frame) ->
    [Instances] (every instance of several templates, the frame's features computed once)
    Tracker(estimator).step(frame) -> TrackStep;  track_sequence(estimator, sequence) -> TrackRun
    InstanceTracker(estimator).step(frame) -> TrackStep with every instance and its identity (`track --all`;
    track_sequence(estimator, sequence, tracker=InstanceTracker(estimator)))
    write_poses(run, out_dir, force=False): one `ob_in_cam` 4x4 text file per frame with a pose

    load_estimate_params(config) -> EstimateParams: the `estimate:` section of a YAML configuration file;
    dump_estimate_defaults() -> str: its commented defaults

Modules, in the order of the stages: `query` (the frame's full-image work, once; the query keypoints),
`retrieval` (TemplateIndex: the template's stacked descriptors, view votes, neighbourhoods), `hypotheses`
(GMatch lists of the neighbourhoods, pre-scored and pooled), `rivals` (solve, refine and verify the lists; rival
poses), `symmetric` (poses that look alike under the object's symmetries, and the rule that picks one), `refine`
(anchored ICP), `verify` (the evidence a pose is accepted on), `pnp` (2D-3D fallback without depth), `estimator`
(Estimator, the façade composing them), `track` (the previous pose as a prior), `track_instances` (every
instance tracked, each with its identity), `model` (the object's surface),
`instances` (every instance of one or more templates: the search repeated on what found ones leave),
`params` (EstimateParams, a section per stage), `settings` (its YAML), `result` (EstimateResult, the `estimate
--json` object).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from gscan._lazy import lazy_exports

# names imported on first use (PEP 562): `settings` and `params` read the configuration without loading the
# estimator's stages (numba, scipy)
_EXPORTS = {
    "Estimator": "gscan.estimate.estimator", "Instances": "gscan.estimate.instances",
    "estimate_templates": "gscan.estimate.instances", "EstimateParams": "gscan.estimate.params",
    "AcceptParams": "gscan.estimate.params", "STAGES": "gscan.estimate.result",
    "EstimateResult": "gscan.estimate.result", "dump_estimate_defaults": "gscan.estimate.settings",
    "load_estimate_params": "gscan.estimate.settings", "STATUSES": "gscan.estimate.track",
    "Tracker": "gscan.estimate.track", "TrackParams": "gscan.estimate.track", "TrackRun": "gscan.estimate.track",
    "TrackStep": "gscan.estimate.track", "track_sequence": "gscan.estimate.track",
    "write_poses": "gscan.estimate.track", "InstanceTracker": "gscan.estimate.track_instances",
    "Evidence": "gscan.estimate.verify",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:
    from gscan.estimate.estimator import Estimator
    from gscan.estimate.instances import Instances, estimate_templates
    from gscan.estimate.params import AcceptParams, EstimateParams
    from gscan.estimate.result import STAGES, EstimateResult
    from gscan.estimate.settings import dump_estimate_defaults, load_estimate_params
    from gscan.estimate.track import STATUSES, Tracker, TrackParams, TrackRun, TrackStep, track_sequence, write_poses
    from gscan.estimate.track_instances import InstanceTracker
    from gscan.estimate.verify import Evidence

__all__ = ["STAGES", "STATUSES", "AcceptParams", "EstimateParams", "EstimateResult", "Estimator", "Evidence",
           "InstanceTracker", "Instances", "TrackParams", "TrackRun", "TrackStep", "Tracker", "dump_estimate_defaults",
           "estimate_templates", "load_estimate_params", "track_sequence", "write_poses"]
