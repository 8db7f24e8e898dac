"""Registration: pairs of frames (match, Kabsch, optional ICP, verdict), loop-closure candidates, and the
pose graph that turns the accepted edges into one camera pose per frame.

- pairwise: `register_frames(frame_s, frame_t) -> PairResult`, `register_features`, `RegisterParams`,
  `frame_cloud`, `relative_pose`
- loops: `select_loop_candidates`, `LoopParams`, `LoopCandidate`
- posegraph: `optimize_pose_graph -> PoseGraphResult`, `spanning_poses`, `GraphEdge`, `PoseGraphParams`,
  `information_from_points`
- sequence: a sequence of frames registered (`SequenceParams`, `capture_noise`, `register_edges`,
  `optimise_sequence -> SequenceResult`), its frames read through `edges.SequenceFrames` and its edges
  (`edges.PairEdge`, made by `edges.Registrar`) stored through an `edges.EdgeSink`; never sees the scan's
  configuration, options or database
"""
from __future__ import annotations

from gscan.registration.loops import LoopCandidate, LoopParams, select_loop_candidates
from gscan.registration.pairwise import (
                                         METHODS,
                                         PairResult,
                                         RegisterParams,
                                         frame_cloud,
                                         register_features,
                                         register_frames,
                                         relative_pose,
)
from gscan.registration.posegraph import (
                                         GraphEdge,
                                         PoseGraphParams,
                                         PoseGraphResult,
                                         information_from_points,
                                         optimize_pose_graph,
                                         spanning_poses,
)

__all__ = [
    "METHODS", "GraphEdge", "LoopCandidate", "LoopParams", "PairResult", "PoseGraphParams", "PoseGraphResult",
    "RegisterParams", "frame_cloud", "information_from_points", "optimize_pose_graph", "register_features",
    "register_frames", "relative_pose", "select_loop_candidates", "spanning_poses",
]
