"""Pose refinement: point-to-plane ICP of the template's visible surface onto the query cloud, anchored by the
match list.

The template's normals give the planes (its clean surface, not the noisy query's). The matched keypoint pairs
enter the same least-squares step as weak point-to-point terms: where the surface alone leaves a direction
free (a can turning about its axis, a flat face sliding in its plane) they hold the pose where the matches put
it, and elsewhere the surface's many pairs outweigh them. Deterministic: bit-identical output for identical
input.
"""
from __future__ import annotations

import numpy as np

from gscan.geometry.transforms import make_T, rotvec_to_R


def _skew_rows(p: np.ndarray) -> np.ndarray:
    """[K x 3] points -> [K x 3 x 6] Jacobians of (omega x p + t) with respect to (omega, t)."""
    J = np.zeros((len(p), 3, 6))
    J[:, 0, 1], J[:, 0, 2] = p[:, 2], -p[:, 1]
    J[:, 1, 0], J[:, 1, 2] = -p[:, 2], p[:, 0]
    J[:, 2, 0], J[:, 2, 1] = p[:, 1], -p[:, 0]
    J[:, 0, 3] = J[:, 1, 4] = J[:, 2, 5] = 1.0
    return J


def icp_anchored(src: np.ndarray, src_normals: np.ndarray, tgt: np.ndarray, T_init: np.ndarray,
                 max_dists: tuple[float, ...], iterations: int, anchors: tuple[np.ndarray, np.ndarray] | None = None,
                 anchor_weight: float = 0.1) -> tuple[np.ndarray, float]:
    """ICP of src [N x 3] (object frame, normals src_normals [N x 3]) onto tgt [M x 3] (camera frame) from
    T_init (tgt <- src) -> (T [4 x 4], fitness: the fraction of src points paired in the last iteration).

    max_dists: correspondence distances, coarse to fine (m); each runs up to `iterations` steps (fewer once a
    step moves less than 0.6 mdeg and 10 um). anchors: (object-frame points [K x 3], camera-frame points
    [K x 3]) of the match list, each pair weighted `anchor_weight` against one surface pair."""
    from scipy.spatial import cKDTree

    from gscan.geometry.grid_kernel import NearestGrid

    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    T = np.asarray(T_init, dtype=np.float64).copy()
    if len(src) < 10 or len(tgt) < 10:
        return T, 0.0
    tree = None
    JtJ_a = Jtr_a = None
    fitness = 0.0
    for max_dist in max_dists:
        # the nearest target point within max_dist: a grid of that cell size (a kd-tree when the target is too
        # wide for one), the same pairs
        grid = NearestGrid.build(tgt, max_dist)
        if grid is None and tree is None:
            tree = cKDTree(tgt)
        for _ in range(iterations):
            p = src @ T[:3, :3].T + T[:3, 3]
            if grid is not None:
                ok, j = grid.query(p)
            else:
                assert tree is not None
                d, j = tree.query(p, distance_upper_bound=max_dist, workers=1)
                ok = np.isfinite(d)
            fitness = float(ok.mean())
            if ok.sum() < 10:
                return T, fitness
            p, q, n = p[ok], tgt[j[ok]], src_normals[ok] @ T[:3, :3].T
            r = np.einsum("ij,ij->i", p - q, n)
            A = np.empty((len(p), 6))  # d(residual) / d(rotvec, translation): [p x n, n]
            A[:, 0] = p[:, 1] * n[:, 2] - p[:, 2] * n[:, 1]
            A[:, 1] = p[:, 2] * n[:, 0] - p[:, 0] * n[:, 2]
            A[:, 2] = p[:, 0] * n[:, 1] - p[:, 1] * n[:, 0]
            A[:, 3:] = n
            H = A.T @ A + 1e-9 * np.eye(6)
            g = A.T @ r
            if anchors is not None and len(anchors[0]):
                pa = anchors[0] @ T[:3, :3].T + T[:3, 3]
                J = _skew_rows(pa)  # [K x 3 x 6]
                JtJ_a = np.einsum("kai,kaj->ij", J, J)
                Jtr_a = np.einsum("kai,ka->i", J, pa - anchors[1])
                H += anchor_weight * JtJ_a
                g += anchor_weight * Jtr_a
            x = np.linalg.solve(H, -g)
            T = make_T(rotvec_to_R(x[:3]), x[3:]) @ T
            if np.linalg.norm(x[:3]) < 1e-5 and np.linalg.norm(x[3:]) < 1e-5:
                break
    return T, fitness
