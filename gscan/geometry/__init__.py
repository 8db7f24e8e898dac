"""Geometry: rigid transforms, Kabsch alignment, ICP, point sets, planes and the mesh record.

- transforms: `make_T`, `inv_T`, `transform_points`, `rotvec_to_R`, `rotation_angle_deg`, `pose_error`, `look_at`,
  `mean_pose`, `is_rigid` ([4 x 4] float64 transforms named by frames: `T_a_b` maps frame-b points into frame a)
- kabsch: `umeyama`, `kabsch`, `leave_one_out_residuals`, `kabsch_trimmed` (outlier-trimmed, numba consensus)
- icp: `icp` (open3d, target normals), `icp_point_to_plane` (numpy, source normals, deterministic), `ICPResult`
- pointset: `pca_normals`, `voxel_mean`, `voxel_down_indices`, `coincident_groups`
- plane: `Plane`, `ransac_plane`
- mesh: `MeshData` (vertex-coloured triangle mesh), `to_u8_colors`
- coverage: `CoverageMap`, `coverage_map`, `template_coverage` (which viewing directions of an object were seen;
  imported from `gscan.geometry.coverage`)
"""
from __future__ import annotations

from gscan.geometry.icp import ICPResult, icp, icp_point_to_plane
from gscan.geometry.kabsch import kabsch, kabsch_trimmed, leave_one_out_residuals, umeyama
from gscan.geometry.mesh import MeshData, to_u8_colors
from gscan.geometry.plane import Plane, ransac_plane
from gscan.geometry.pointset import coincident_groups, pca_normals, voxel_down_indices, voxel_mean
from gscan.geometry.transforms import (
                                       MAX_TRANSLATION_M,
                                       RIGID_ATOL,
                                       inv_T,
                                       is_rigid,
                                       look_at,
                                       make_T,
                                       mean_pose,
                                       pose_error,
                                       rotation_angle_deg,
                                       rotvec_to_R,
                                       transform_points,
)

__all__ = [
    "MAX_TRANSLATION_M", "RIGID_ATOL", "ICPResult", "MeshData", "Plane", "coincident_groups", "icp",
    "icp_point_to_plane", "inv_T", "is_rigid", "kabsch", "kabsch_trimmed", "leave_one_out_residuals", "look_at",
    "make_T", "mean_pose", "pca_normals", "pose_error", "ransac_plane", "rotation_angle_deg", "rotvec_to_R",
    "to_u8_colors", "transform_points", "umeyama", "voxel_down_indices", "voxel_mean",
]
