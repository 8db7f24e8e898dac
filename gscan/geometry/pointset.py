"""Point-set helpers of pose estimation, deterministic (bit-identical output for identical input): PCA
normals, voxel grids, groups of coincident points. Points are [N x 3] float metres.
"""
from __future__ import annotations

import numpy as np


def pca_normals(pts: np.ndarray, k: int = 8) -> np.ndarray:
    """[N x 3] points -> [N x 3] unit normals (unoriented): smallest principal axis of the k nearest points."""
    from scipy.spatial import cKDTree

    pts = np.asarray(pts, dtype=np.float64)
    if len(pts) < k:
        return np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    _, nn = cKDTree(pts).query(pts, k=k, workers=-1)
    nb = pts[nn] - pts[nn].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("mki,mkj->mij", nb, nb))[1][:, :, 0]


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
