"""The records a template database stores and returns: views, their keypoints, registration edges, the
mesh, and the in-memory `Template` the estimator loads (numpy arrays; shapes in each docstring).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from gscan.io.camera import Intrinsics


@dataclass
class View:
    """One input view. color [H x W x 3] uint8 RGB, depth [H x W] float32 m (0 invalid), mask [H x W]
    bool; images may be None (not stored, or not loaded). T_obj_cam [4 x 4] or None = unregistered."""

    name: str
    intrinsics: Intrinsics
    T_obj_cam: np.ndarray | None = None
    color: np.ndarray | None = None
    depth: np.ndarray | None = None
    mask: np.ndarray | None = None
    keyframe: bool = True
    quality: float | None = None
    input_index: int | None = None


@dataclass
class ViewFeatures:
    """Keypoints of one view: pixels [N x 2] float32 (u, v), points_obj [N x 3] float32 (object frame,
    camera frame while the view is unregistered), descriptors [N x D] (float32 or uint8), kind, scales [N]."""

    pixels: np.ndarray
    points_obj: np.ndarray
    descriptors: np.ndarray
    kind: str
    scales: np.ndarray | None = None

    def __iter__(self) -> Iterator[Any]:  # `pixels, points_obj, descriptors, kind = db.features(name)`
        return iter((self.pixels, self.points_obj, self.descriptors, self.kind))


@dataclass
class Edge:
    """A registration between two views: T_tgt_src [4 x 4] (None if none was found), matches [M x 2]
    int32 (src keypoint index, tgt keypoint index), quality numbers, kind "sequential" | "loop"."""

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


@dataclass
class MeshData:
    """vertices [V x 3] float (m, object frame), triangles [F x 3] int, vertex_colors [V x 3] uint8 | None."""

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray | None

    def __iter__(self) -> Iterator[Any]:  # `V, F, C = db.mesh()`
        return iter((self.vertices, self.triangles, self.vertex_colors))


@dataclass
class Template:
    """In-memory template for the estimator: the registered (key)frame views and their stacked keypoints.

    T_obj_cam [V x 4 x 4]; kp_view [N] int32 index into `view_names`; pixels [N x 2] float32;
    points_obj [N x 3] float32; descriptors [N x D]; view_offsets [V + 1] (keypoints of view i are
    rows view_offsets[i]:view_offsets[i+1]); cloud points [P x 3] / colors [P x 3] uint8; extent_m [3].
    """

    path: Path
    meta: dict
    kind: str | None
    view_names: list[str]
    intrinsics: list[Intrinsics]
    T_obj_cam: np.ndarray
    kp_view: np.ndarray
    pixels: np.ndarray
    points_obj: np.ndarray
    descriptors: np.ndarray
    view_offsets: np.ndarray
    cloud_points: np.ndarray | None
    cloud_colors: np.ndarray | None
    mesh: MeshData | None
    grasps: dict[str, np.ndarray] = field(default_factory=dict)
    extent_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
