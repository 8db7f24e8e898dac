"""The numba kernel of `gscan.geometry.kabsch.kabsch_trimmed`'s consensus step (the specification is there).

`best_triple(src, dst, n_enum, tau, min_sin)` poses every non-degenerate triple of the first n_enum pairs by
its triad and scores every pair's residual under that pose in units of its tau, truncated at 1 (MSAC); the
lowest score wins,
the first in (i, j, k) order on ties. A triple's scoring stops once it can no longer win. Compiled with
`cache=True`, `nogil=True`; imported on first use, so that importing `gscan.geometry` does not load numba.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _frame(P, i, j, k, min_sin, F):
    """Fill F [3 x 3] with the orthonormal frame (columns) of triangle (P_i, P_j, P_k): e1 along P_j - P_i,
    e3 along the normal. False when the triangle's sine is at most min_sin (near-collinear)."""
    ax, ay, az = P[j, 0] - P[i, 0], P[j, 1] - P[i, 1], P[j, 2] - P[i, 2]
    bx, by, bz = P[k, 0] - P[i, 0], P[k, 1] - P[i, 1], P[k, 2] - P[i, 2]
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    la = np.sqrt(ax * ax + ay * ay + az * az)
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    if nn <= min_sin * la * np.sqrt(bx * bx + by * by + bz * bz) or nn == 0.0:
        return False
    ax, ay, az = ax / la, ay / la, az / la
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    F[0, 0], F[1, 0], F[2, 0] = ax, ay, az
    F[0, 1], F[1, 1], F[2, 1] = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax  # e3 x e1
    F[0, 2], F[1, 2], F[2, 2] = nx, ny, nz
    return True


@njit(cache=True, nogil=True)
def best_triple(src, dst, n_enum, tau, min_sin):
    """(i, j, k, T [4 x 4]) of the best-scoring triple (module docstring); i = -1 when every triple of the
    first n_enum pairs is degenerate in src or dst. src, dst [N x 3] float64, tau [N] float64 > 0."""
    n = src.shape[0]
    Fs = np.empty((3, 3))
    Fd = np.empty((3, 3))
    R = np.empty((3, 3))
    t = np.empty(3)
    best_score = np.inf
    best_i, best_j, best_k = -1, -1, -1
    T = np.eye(4)
    for i in range(n_enum):
        for j in range(i + 1, n_enum):
            for k in range(j + 1, n_enum):
                if not _frame(src, i, j, k, min_sin, Fs) or not _frame(dst, i, j, k, min_sin, Fd):
                    continue
                for a in range(3):
                    for b in range(3):
                        R[a, b] = Fd[a, 0] * Fs[b, 0] + Fd[a, 1] * Fs[b, 1] + Fd[a, 2] * Fs[b, 2]
                for a in range(3):  # t = centroid_dst - R centroid_src
                    t[a] = (dst[i, a] + dst[j, a] + dst[k, a]) / 3.0
                    for b in range(3):
                        t[a] -= R[a, b] * (src[i, b] + src[j, b] + src[k, b]) / 3.0
                score = 0.0
                for p in range(n):
                    dx = R[0, 0] * src[p, 0] + R[0, 1] * src[p, 1] + R[0, 2] * src[p, 2] + t[0] - dst[p, 0]
                    dy = R[1, 0] * src[p, 0] + R[1, 1] * src[p, 1] + R[1, 2] * src[p, 2] + t[1] - dst[p, 1]
                    dz = R[2, 0] * src[p, 0] + R[2, 1] * src[p, 1] + R[2, 2] * src[p, 2] + t[2] - dst[p, 2]
                    score += min(np.sqrt(dx * dx + dy * dy + dz * dz) / tau[p], 1.0)
                    if score >= best_score:
                        break
                if score < best_score:
                    best_score = score
                    best_i, best_j, best_k = i, j, k
                    T[:3, :3] = R
                    T[:3, 3] = t
    return best_i, best_j, best_k, T
