"""Planes and a seeded RANSAC plane fit: the support plane of segmentation and of pose estimation.

Planes: `height(p) = normal . p + offset`; `ransac_plane` orients the normal towards a viewpoint.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Plane:
    """Plane {p : normal . p + offset = 0}; `height` is the signed distance along `normal`."""

    normal: np.ndarray  # [3] unit
    offset: float

    def height(self, pts: np.ndarray) -> np.ndarray:
        """[N x 3] (or [... x 3]) points -> [N] signed heights (m)."""
        return np.asarray(pts, dtype=np.float64) @ self.normal + self.offset

    def transformed(self, T_b_a: np.ndarray) -> Plane:
        """The same plane expressed in frame b, given this plane in frame a."""
        n = T_b_a[:3, :3] @ self.normal
        return Plane(n, float(self.offset - n @ T_b_a[:3, 3]))


def ransac_plane(S: np.ndarray, iterations: int, rng: np.random.Generator, dist: float | np.ndarray,
                 viewpoint: np.ndarray, max_behind: float | None = None) -> tuple[Plane, np.ndarray] | None:
    """Best of `iterations` random-triplet planes through [N x 3] points S, by inlier count.

    A point is an inlier when |height| < dist (a scalar, or one value per point [N]). Normals point
    towards `viewpoint` [3]. With `max_behind`, a plane with more than that fraction of S farther than
    dist behind it scores 0: a support plane has (almost) nothing behind it, a large object face seen
    head-on does. Triplets are drawn from `rng` in batches of 100; the first best plane wins. Returns
    (plane, inlier mask [N] bool), or None when every triplet is degenerate or disqualified.
    """
    from gscan.geometry.plane_kernel import HAS_FMA, plane_counts, plane_inliers  # numba, on first use

    vp = np.asarray(viewpoint, dtype=np.float64)
    S = np.ascontiguousarray(S, dtype=np.float64)
    # writable: the kernel is compiled for one array type
    d = np.array(np.broadcast_to(np.asarray(dist, dtype=np.float64).reshape(-1), (len(S),)))
    best, best_count, best_nrm, best_off, best_k = None, -1, None, None, -1
    for start in range(0, iterations, 100):
        m = min(100, iterations - start)
        tri = S[rng.integers(0, len(S), size=(m, 3))]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(nrm, axis=1)
        ok = length > 1e-12
        nrm = nrm[ok] / length[ok, None]
        off = -np.einsum("ij,ij->i", nrm, tri[ok, 0])
        flip = np.where(nrm @ vp + off < 0, -1.0, 1.0)
        nrm, off = nrm * flip[:, None], off * flip
        nrm, off = np.ascontiguousarray(nrm), np.ascontiguousarray(off)
        # signed heights (viewpoint side > 0) of every point above every plane, counted (plane_kernel)
        if HAS_FMA:
            counts, behind = plane_counts(S, nrm, off, d)
        else:
            h = S @ nrm.T + off  # [N x m]
            counts, behind = (np.abs(h) < d[:, None]).sum(0), (h < -d[:, None]).sum(0)
        if max_behind is not None:
            counts[behind > max_behind * len(S)] = 0
        if len(counts) and counts.max() > max(best_count, 0):  # a score of 0 (disqualified) never wins
            k = int(np.argmax(counts))
            best_count, best, best_nrm, best_off, best_k = int(counts[k]), Plane(nrm[k], float(off[k])), nrm, off, k
    if best is None or best_nrm is None or best_off is None:
        return None
    assert best_nrm is not None and best_off is not None
    if HAS_FMA:
        return best, plane_inliers(S, best_nrm, best_off, best_k, d)
    return best, np.abs(S @ best_nrm.T + best_off)[:, best_k] < d


def dominant_plane(cloud: np.ndarray, min_frac: float, iterations: int, stride: int = 6) -> Plane | None:
    """The dominant plane (a table top) of a camera-frame cloud [H x W x 3] (z = 0 where depth is missing), normal
    towards the camera, or None when no plane holds `min_frac` of the valid points: `ransac_plane` on every
    `stride`-th pixel (seeded; inliers within 6 mm + 0.5 % of the depth) over `iterations` hypotheses with at
    most 5 % of the points behind them (a large object face seen head-on is never taken for the table),
    least-squares refit on the inliers."""
    sub = np.asarray(cloud)[::stride, ::stride].reshape(-1, 3).astype(np.float64)
    sub = sub[sub[:, 2] > 0]
    if len(sub) < 100:
        return None
    found = ransac_plane(sub, iterations, np.random.default_rng(0), 0.006 + 0.005 * sub[:, 2], np.zeros(3),
                        max_behind=0.05)
    if found is None or found[1].sum() < min_frac * len(sub):
        return None
    inl = found[1]
    cen = sub[inl].mean(0)
    normal = np.linalg.svd(sub[inl] - cen, full_matrices=False)[2][2]
    if normal @ cen > 0:  # towards the camera (origin)
        normal = -normal
    return Plane(normal, float(-normal @ cen))
