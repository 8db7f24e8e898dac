"""`Edge`: a registration between two frames of a sequence, as registration makes it and the template database
stores it (a light module: the template reads edges without loading registration's kernels)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PRUNED = "pruned by the pose graph: "  # reason prefix of edges registration accepted and the pose graph rejected


@dataclass
class Edge:
    """A registration between frames src and tgt: T_tgt_src [4 x 4] (None if none was found), matches [M x 2]
    int32 (src keypoint index, tgt keypoint index), quality numbers, kind "sequential" | "loop", the verdict."""

    src: str
    tgt: str
    T_tgt_src: np.ndarray | None
    matches: np.ndarray
    cost: float | None = None
    rmse: float | None = None
    fitness: float | None = None
    kind: str = "sequential"
    accepted: bool = True
    reason: str | None = None
    depth_only: bool = False  # accepted on depth keypoints that the texture could not judge (not stored)

    @property
    def pruned(self) -> bool:
        """Accepted by registration, rejected by the pose graph."""
        return bool(self.reason and self.reason.startswith(PRUNED))
