"""Point-set helpers of pose estimation, deterministic (bit-identical output for identical input): PCA
normals, voxel grids, groups of coincident points. Points are [N x 3] float metres.
"""
from __future__ import annotations

import numpy as np


def _row_codes(keys: np.ndarray) -> np.ndarray:
    """Integer keys [N x K] -> [N] int64 codes ordered as the rows are lexicographically (equal rows, equal
    codes), so that np.unique over the codes orders, indexes and counts as np.unique(keys, axis=0) does,
    without sorting rows; the keys themselves when their ranges do not fit in 62 bits."""
    if len(keys) == 0 or keys.ndim != 2:
        return keys
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0 ** 62:
        return keys
    code = np.zeros(len(keys), np.int64)
    for c in range(keys.shape[1]):
        code = code * span[c] + (keys[:, c] - lo[c])
    return code


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
    _, first, inv = np.unique(_row_codes(keys), axis=0, return_index=True, return_inverse=True)
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
    _, inv, cnt = np.unique(_row_codes(keys), axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    # per-voxel sums in input order (bincount adds like np.add.at, one column at a time)
    out = np.stack([np.bincount(inv, weights=pts[:, c], minlength=len(cnt)) for c in range(pts.shape[1])], 1)
    return out / cnt[:, None]


def voxel_down_indices(pts: np.ndarray, voxel: float) -> np.ndarray:
    """[N x 3] -> [M] indices of one point (the first, in input order) per occupied voxel; deterministic."""
    if voxel <= 0 or len(pts) == 0:
        return np.arange(len(pts))
    keys = np.floor(np.asarray(pts, dtype=np.float64) / voxel).astype(np.int64)
    _, first = np.unique(_row_codes(keys), axis=0, return_index=True)
    return np.sort(first)
