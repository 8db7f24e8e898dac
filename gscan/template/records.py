"""The records a template database stores and returns: views, registration edges, a database's summary, and
the in-memory `Template` the estimator loads (numpy arrays; shapes in each docstring). A view's keypoints are
`gscan.features.Features`, the mesh `gscan.geometry.mesh.MeshData`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from gscan.errors import InputError
from gscan.features.keypoints import JOINT, depth_rows
from gscan.geometry.mesh import MeshData
from gscan.io.camera import Intrinsics, RGBDFrame

_FRAME_MASK: Any = object()  # View.from_frame: keep the frame's own mask


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

    @classmethod
    def from_frame(cls, frame: RGBDFrame, *, T_obj_cam: np.ndarray | None = None,
                   mask: np.ndarray | None = _FRAME_MASK, keyframe: bool = True, quality: float | None = None,
                   input_index: int | None = None) -> View:
        """The view of an RGB-D frame: its name, intrinsics and images; `mask` replaces the frame's own mask
        (None: no mask), T_obj_cam [4 x 4] or None (unregistered)."""
        return cls(name=frame.name, intrinsics=frame.intrinsics, T_obj_cam=T_obj_cam, color=frame.color,
                   depth=frame.depth, mask=frame.mask if mask is _FRAME_MASK else mask, keyframe=keyframe,
                   quality=quality, input_index=input_index)


@dataclass(frozen=True)
class TemplateSummary:
    """What a template database holds (`TemplateDB.summary`): schema version, status ("complete" | "partial"),
    number of views, registered views and keyframes, descriptor kind, source ("scan" | "mesh"), the object's
    extent [3] (m, object frame), the grasp names, why each unregistered frame is (name -> reason), the scan's
    frame selection: {"kept": int, "skipped": int, "reasons": {why: frames}} (empty for a template written
    before frames were selected, or from a mesh), and the frames of each part of the capture that no confident
    edge joins to the template's frames (largest first)."""

    schema: int
    status: str
    views: int
    registered: int
    keyframes: int
    descriptor: str | None
    source: str
    extent_m: tuple[float, float, float]
    grasps: tuple[str, ...]
    unregistered_reasons: dict[str, str] = field(default_factory=dict)
    selection: dict = field(default_factory=dict)
    parts: list[list[str]] = field(default_factory=list)


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

    def require_keypoints(self) -> str:
        """The keypoints' kind; InputError unless the template holds a registered view with keypoints (what an
        estimate needs)."""
        if self.kind is None or len(self.view_names) == 0 or len(self.descriptors) == 0:
            raise InputError(self.path, "template holds no registered view with keypoints")
        return self.kind

    def image_keypoints(self) -> Template:
        """This template with its image keypoints alone: a joint set (rootsift+fpfh, `gscan.features.depth`) loses
        its depth keypoints and its descriptors their FPFH part (kind rootsift, as a template scanned on the image's
        keypoints holds them); any other template unchanged."""
        if self.kind != JOINT:
            return self
        image = ~depth_rows(self.descriptors, self.kind)
        counts = np.bincount(self.kp_view[image], minlength=len(self.view_names))
        return replace(self, kind="rootsift", kp_view=self.kp_view[image], pixels=self.pixels[image],
                       points_obj=self.points_obj[image],
                       descriptors=np.ascontiguousarray(self.descriptors[image, :128]),
                       view_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))
