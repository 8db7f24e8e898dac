"""Kabsch / Umeyama alignment of matched point sets, and the outlier-trimmed Kabsch of registration and
pose estimation (its consensus step is the numba kernel `gscan.geometry.consensus_kernel`, imported on first
use so that importing gscan.geometry does not load numba).
"""
from __future__ import annotations

import numpy as np

from gscan.geometry.transforms import make_T, transform_points


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
            with_scale: bool = False) -> np.ndarray:
    """Least-squares rigid (or similarity) transform T with dst ~= T @ src.

    src, dst: [N x 3], N >= 3 (weights [N] optional). A reflection is never returned
    (the reflection guard flips the smallest singular direction). Returns [4 x 4];
    with_scale puts the scale into the rotation block.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need two [N x 3] arrays with N >= 3, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    C = (xd * w[:, None]).T @ xs
    U, S, Vt = np.linalg.svd(C)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    s = 1.0
    if with_scale:
        var_s = (w * (xs ** 2).sum(1)).sum()
        s = float(np.trace(np.diag(S) @ D) / var_s)
    return make_T(s * R, mu_d - s * R @ mu_s)


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Rigid T (proper rotation) minimising sum |T @ src_i - dst_i|^2. src, dst: [N x 3]."""
    return umeyama(src, dst, weights, with_scale=False)


def leave_one_out_residuals(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """[N] residual |T_k src_k - dst_k| of each pair under T_k = kabsch of the other N - 1 pairs (src, dst
    [N x 3], N >= 4): the N fits in one batched SVD, each from the totals less the pair left out."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 4:
        raise ValueError(f"need two [N x 3] arrays with N >= 4, got {src.shape} and {dst.shape}")
    m = len(src) - 1
    mu_s = (src.sum(0) - src) / m  # [N x 3] centroids without pair k
    mu_d = (dst.sum(0) - dst) / m
    C = dst.T @ src - dst[:, :, None] * src[:, None, :] - m * mu_d[:, :, None] * mu_s[:, None, :]  # [N x 3 x 3]
    U, _, Vt = np.linalg.svd(C)
    U[:, :, 2] *= np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)[:, None]  # reflection guard (umeyama)
    R = U @ Vt
    pred = np.einsum("kij,kj->ki", R, src - mu_s) + mu_d
    return np.linalg.norm(pred - dst, axis=1)


CONSENSUS_MAX_PAIRS = 32  # kabsch_trimmed enumerates the triples of at most this many pairs (4960)


def kabsch_trimmed(src: np.ndarray, dst: np.ndarray, tau: float | np.ndarray, min_sin: float = 0.1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch on matched points src, dst [N x 3] (N >= 3) with gross outliers trimmed: (T, keep [N] bool).
    tau: the distance (m) beyond which a pair is off, one for all pairs or one per pair [N] (a pair's own
    noise, `gscan.registration.noise`); residuals below are compared with it, scores sum them in its units.

    1. Plain Kabsch; when every pair lies within tau of its target under it, all pairs are kept.
    2. Otherwise consensus: every triple of pairs (of the first CONSENSUS_MAX_PAIRS, in list order) whose
       triangles have a sine above min_sin in both clouds is posed by its triad (the two triangles' frames)
       and scored by the sum over all pairs of their residuals truncated at tau (MSAC; lowest wins, first
       on ties: `gscan.geometry.consensus_kernel`). The winner's pairs within tau are re-solved by Kabsch and
       re-selected until the selection is stable (at most 3 times). A pair off by a few centimetres drags
       plain Kabsch so far that trimming the worst residual first drops true pairs: on a whole frame
       (rendered, plain table, 60 deg) one pair 36 cm off among 14 true ones gave 19 deg that way.
       When every triple is degenerate, plain Kabsch on all pairs is returned.
    3. Then the worst pair by leave-one-out residual (against the pose solved without it) is dropped while
       it lies more than tau off, at least 5 pairs are kept and no fewer than half of the list: it catches
       a far-off pair that tilts the fit towards itself (a clustered list plus one distant point).
    Without outliers this is plain Kabsch. The kept pairs may be a minority of the list.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    n = len(src)
    taus = np.broadcast_to(np.asarray(tau, dtype=np.float64), (n,)).copy()  # [N]
    keep = np.ones(n, bool)
    T = kabsch(src, dst)
    if n > 3 and (np.linalg.norm(transform_points(T, src) - dst, axis=1) > taus).any():  # 2. consensus
        from gscan.geometry.consensus_kernel import best_triple  # numba, on first use

        i, j, k, T_tri = best_triple(np.ascontiguousarray(src), np.ascontiguousarray(dst),
                                     min(n, CONSENSUS_MAX_PAIRS), taus, float(min_sin))
        if i >= 0:
            keep = np.linalg.norm(transform_points(T_tri, src) - dst, axis=1) < taus
            keep[[i, j, k]] = True
            for _ in range(3):
                T = kabsch(src[keep], dst[keep])
                again = np.linalg.norm(transform_points(T, src) - dst, axis=1) < taus
                if again.sum() < 3 or (again == keep).all():
                    break  # T is the selection's pose
                keep = again
            else:  # the third re-selection changed it
                T = kabsch(src[keep], dst[keep])
    floor = max(3, (n + 1) // 2)
    while keep.sum() >= 5 and keep.sum() - 1 >= floor:  # 3. leave-one-out residuals
        idx = np.flatnonzero(keep)
        r = leave_one_out_residuals(src[idx], dst[idx]) / taus[idx]
        worst = int(np.argmax(r))
        if r[worst] <= 1.0:
            break
        keep[idx[worst]] = False
        T = kabsch(src[keep], dst[keep])
    return T, keep
