"""Registration: pairs of frames (match, Kabsch, optional ICP, verdict), loop-closure candidates, and the
pose graph that turns the accepted edges into one camera pose per frame.

- frames: `register_frames(frame_s, frame_t) -> PairResult`
- pairwise: `register_features`, `RegisterParams`, `frame_cloud`, `relative_pose`
- loops: `select_loop_candidates`, `LoopParams`, `LoopCandidate`
- posegraph: `optimize_pose_graph -> PoseGraphResult`, `spanning_poses`, `GraphEdge`, `PoseGraphParams`,
  `information_from_points`
- sequence: a sequence of frames registered (`SequenceParams`, `capture_noise`, `register_edges`,
  `optimise_sequence -> SequenceResult`), its frames read through `edges.SequenceFrames` and its edges
  (`edges.Edge`, made by `edges.Registrar`) stored through an `edges.EdgeSink`; never sees the scan's
  configuration, options or database
- edge: `Edge` (a light module: the template database stores edges without loading the rest)

Names are imported on first use (PEP 562).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from gscan._lazy import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("METHODS", "PairResult", "RegisterParams", "frame_cloud", "register_features", "relative_pose"),
                    "gscan.registration.pairwise"),
    "register_frames": "gscan.registration.frames",
    **dict.fromkeys(("LoopCandidate", "LoopParams", "select_loop_candidates"), "gscan.registration.loops"),
    **dict.fromkeys(("GraphEdge", "PoseGraphParams", "PoseGraphResult", "information_from_points",
                     "optimize_pose_graph", "spanning_poses"), "gscan.registration.posegraph"),
    **dict.fromkeys(("SequenceParams", "SequenceResult", "capture_noise", "register_edges", "optimise_sequence"),
                    "gscan.registration.sequence"),
    "Edge": "gscan.registration.edge",
}

if TYPE_CHECKING:
    from gscan.registration.edge import Edge
    from gscan.registration.frames import register_frames
    from gscan.registration.loops import LoopCandidate, LoopParams, select_loop_candidates
    from gscan.registration.pairwise import (
        METHODS,
        PairResult,
        RegisterParams,
        frame_cloud,
        register_features,
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
    from gscan.registration.sequence import (
        SequenceParams,
        SequenceResult,
        capture_noise,
        optimise_sequence,
        register_edges,
    )

__all__ = [
    "METHODS",
    "Edge",
    "GraphEdge",
    "LoopCandidate",
    "LoopParams",
    "PairResult",
    "PoseGraphParams",
    "PoseGraphResult",
    "RegisterParams",
    "SequenceParams",
    "SequenceResult",
    "capture_noise",
    "frame_cloud",
    "information_from_points",
    "optimise_sequence",
    "optimize_pose_graph",
    "register_edges",
    "register_features",
    "register_frames",
    "relative_pose",
    "select_loop_candidates",
    "spanning_poses",
]
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
