"""ICP refinement of a rigid transform between two point clouds, in two variants:

- `icp`: open3d's ICP (point-to-plane with normals estimated on the target, or point-to-point), with
  voxel downsampling, fitness and inlier RMSE; registration's optional refinement of an edge.
- `icp_point_to_plane`: point-to-plane ICP on the SOURCE's normals in numpy, deterministic
  (bit-identical output for identical input); pose estimation's refinement on the template's normals.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gscan.geometry.transforms import make_T, rotvec_to_R


@dataclass
class ICPResult:
    T: np.ndarray  # [4 x 4] refined transform (target <- source)
    fitness: float  # fraction of source points with a correspondence within max_dist
    rmse: float  # inlier RMSE (m)


def icp(src_pts: np.ndarray, tgt_pts: np.ndarray, T_init: np.ndarray, max_dist: float,
        voxel: float = 0.0, iterations: int = 30, point_to_plane: bool = True) -> ICPResult:
    """Refine T (tgt <- src) by open3d ICP (point-to-plane by default) on [N x 3] / [M x 3] clouds.

    `voxel` > 0 downsamples both clouds first. Normals of the target are estimated with a
    radius of 3 voxels (or 3 * max_dist when voxel is 0).
    """
    import open3d as o3d

    def cloud(p: np.ndarray) -> o3d.geometry.PointCloud:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(p, dtype=np.float64)))
        return pc.voxel_down_sample(voxel) if voxel > 0 else pc

    src, tgt = cloud(src_pts), cloud(tgt_pts)
    if len(src.points) < 10 or len(tgt.points) < 10:
        return ICPResult(np.asarray(T_init, dtype=float).copy(), 0.0, float("inf"))
    radius = 3 * (voxel if voxel > 0 else max_dist)
    est: o3d.pipelines.registration.TransformationEstimation
    if point_to_plane:
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    else:
        est = o3d.pipelines.registration.TransformationEstimationPointToPoint()
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations)
    res = o3d.pipelines.registration.registration_icp(src, tgt, max_dist, np.asarray(T_init, dtype=float), est, crit)
    return ICPResult(np.asarray(res.transformation).copy(), float(res.fitness), float(res.inlier_rmse))


def icp_point_to_plane(src: np.ndarray, src_normals: np.ndarray, tgt: np.ndarray, T_init: np.ndarray,
                       max_dist: float, iterations: int = 20) -> tuple[np.ndarray, float]:
    """Point-to-plane ICP of src [N x 3] (normals src_normals [N x 3]) onto tgt [M x 3] from T_init
    (tgt <- src) -> (T [4 x 4], fitness).

    The planes are the SOURCE's (the template's clean surface), not normals estimated on the noisy query
    depth, which drag the pose (see BENCHMARKS.md, section Masks, ICP, the first call and frames without
    depth). Each iteration pairs every moved source point with its nearest target point within `max_dist` and
    solves the linearised 6-DoF step. Deterministic (bit-identical output for identical input), unlike open3d's threaded
    reductions; fitness = fraction of source points paired in the last iteration.
    """
    from scipy.spatial import cKDTree

    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    T = np.asarray(T_init, dtype=np.float64).copy()
    if len(src) < 10 or len(tgt) < 10:
        return T, 0.0
    tree = cKDTree(tgt)
    fitness = 0.0
    for _ in range(iterations):
        p = src @ T[:3, :3].T + T[:3, 3]
        d, j = tree.query(p, distance_upper_bound=max_dist, workers=-1)  # per-query results: thread-safe
        ok = np.isfinite(d)
        fitness = float(ok.mean())
        if ok.sum() < 10:
            break
        p, q, n = p[ok], tgt[j[ok]], src_normals[ok] @ T[:3, :3].T
        r = np.einsum("ij,ij->i", p - q, n)
        A = np.hstack([np.cross(p, n), n])  # [K x 6]: d(residual) / d(rotvec, translation)
        x = np.linalg.solve(np.einsum("ki,kj->ij", A, A) + 1e-9 * np.eye(6), -np.einsum("ki,k->i", A, r))
        T = make_T(rotvec_to_R(x[:3]), x[3:]) @ T
        if np.linalg.norm(x[:3]) < 1e-5 and np.linalg.norm(x[3:]) < 1e-5:  # 0.6 mdeg, 10 um
            break
    return T, fitness
