"""Point-set helpers of pose estimation, deterministic (bit-identical output for identical input): PCA
normals, point-to-plane ICP with the source's normals, voxel grids, groups of coincident points. Points are
[N x 3] float metres.
"""
from __future__ import annotations

import numpy as np

from gscan.geometry.transforms import make_T, rotvec_to_R


def pca_normals(pts: np.ndarray, k: int = 8) -> np.ndarray:
    """[N x 3] points -> [N x 3] unit normals (unoriented): smallest principal axis of the k nearest points."""
    from scipy.spatial import cKDTree

    pts = np.asarray(pts, dtype=np.float64)
    if len(pts) < k:
        return np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    _, nn = cKDTree(pts).query(pts, k=k, workers=-1)
    nb = pts[nn] - pts[nn].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("mki,mkj->mij", nb, nb))[1][:, :, 0]


def icp_point_to_plane(src: np.ndarray, src_normals: np.ndarray, tgt: np.ndarray, T_init: np.ndarray,
                       max_dist: float, iterations: int = 20) -> tuple[np.ndarray, float]:
    """Point-to-plane ICP of src [N x 3] (normals src_normals [N x 3]) onto tgt [M x 3] from T_init
    (tgt <- src) -> (T [4 x 4], fitness).

    The planes are the SOURCE's (the template's clean surface), not normals estimated on the noisy
    query depth, which measurably drag the pose (BENCHMARKS.md). Each iteration pairs every moved
    source point with its nearest target point within `max_dist` and solves the linearised 6-DoF
    step. Deterministic (bit-identical output for identical input), unlike open3d's threaded
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


def coincident_groups(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group [N x 3] points that coincide (to 0.1 mm): (order [N], starts [G]) such that
    pts[order[starts[g]:starts[g+1]]] is group g; groups in first-occurrence order, members in input order."""
    n = len(pts)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    keys = np.rint(np.asarray(pts, dtype=np.float64) * 1e4).astype(np.int64)
    _, first, inv = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first, kind="stable"), kind="stable")[inv.reshape(-1)]  # group id by first occurrence
    order = np.lexsort((np.arange(n), rank))
    starts = np.flatnonzero(np.r_[True, np.diff(rank[order]) != 0])
    return order.astype(np.int64), starts.astype(np.int64)


def voxel_mean(pts: np.ndarray, voxel: float) -> np.ndarray:
    """[N x D] rows, xyz first (then any per-point values, e.g. colours) -> [M x D] mean row of every voxel
    occupied by the xyz (ordered by voxel key); deterministic."""
    pts = np.asarray(pts, dtype=np.float64)
    if voxel <= 0 or len(pts) == 0:
        return pts
    keys = np.floor(pts[:, :3] / voxel).astype(np.int64)
    _, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    out = np.zeros((len(cnt), pts.shape[1]))
    np.add.at(out, inv.reshape(-1), pts)
    return out / cnt[:, None]


def voxel_down_indices(pts: np.ndarray, voxel: float) -> np.ndarray:
    """[N x 3] -> [M] indices of one point (the first, in input order) per occupied voxel; deterministic."""
    if voxel <= 0 or len(pts) == 0:
        return np.arange(len(pts))
    keys = np.floor(np.asarray(pts, dtype=np.float64) / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)
