"""The template's object surface as the estimator uses it: the cloud ICP pairs and the score projects, the
object's extent, its grasps and its symmetries."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gscan.errors import InputError
from gscan.geometry.pointset import pca_normals, voxel_down_indices
from gscan.geometry.symmetry import Symmetries
from gscan.template.db import Template


@dataclass(frozen=True)
class ObjectModel:
    """cloud [P x 3]: the template's cloud (its mesh's vertices, else its keypoints when it has none), object
    frame; model_points [Q x 3]: the points metrics use (mesh vertices when the template has a mesh, else the
    cloud); samples [S x 3] the cloud voxel-downsampled (ICP source, depth score, support-plane rule) with
    normals [S x 3]; center [3], radius: the cloud's bounding-box centre and its farthest point from it (m);
    grasps {name: T_obj_grasp [4 x 4]}; symmetries: the template's "symmetries" meta (`symmetries_of`)."""

    cloud: np.ndarray = field(repr=False)
    model_points: np.ndarray = field(repr=False)
    samples: np.ndarray = field(repr=False)
    normals: np.ndarray = field(repr=False)
    center: np.ndarray
    radius: float
    grasps: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    symmetries: Symmetries = field(default_factory=Symmetries)

    @classmethod
    def from_template(cls, tpl: Template, voxel: float) -> ObjectModel:
        """The model of a loaded template, its samples voxel-downsampled at `voxel` (m)."""
        cloud = tpl.cloud_points if tpl.cloud_points is not None and len(tpl.cloud_points) else None
        if cloud is None and tpl.mesh is not None and len(tpl.mesh.vertices):
            cloud = tpl.mesh.vertices
        if cloud is None:
            cloud = tpl.points_obj.astype(np.float64)
        cloud = np.asarray(cloud, dtype=np.float64)
        model_points = np.asarray(tpl.mesh.vertices if tpl.mesh is not None and len(tpl.mesh.vertices) else cloud,
                                  dtype=np.float64)
        samples = cloud[voxel_down_indices(cloud, voxel)]
        lo, hi = cloud.min(0), cloud.max(0)
        center = 0.5 * (lo + hi)
        radius = float(np.linalg.norm(cloud - center, axis=1).max())
        return cls(cloud, model_points, samples, pca_normals(samples), center, radius, dict(tpl.grasps),
                   symmetries_of(tpl))

    def grasps_at(self, T_cam_obj: np.ndarray) -> dict[str, np.ndarray]:
        """{name: T_cam_grasp [4 x 4]} = T_cam_obj @ T_obj_grasp."""
        return {k: T_cam_obj @ G for k, G in self.grasps.items()}


def symmetries_of(tpl: Template) -> Symmetries:
    """The object's symmetries, the template's "symmetries" meta (`Symmetries.to_json`); none when absent.
    InputError naming the template for a malformed value."""
    meta = tpl.meta if isinstance(tpl.meta, dict) else {}
    try:
        return Symmetries.from_json(meta.get("symmetries"))
    except ValueError as e:
        raise InputError(tpl.path or "template", f"its symmetries cannot be read: {e}") from None
