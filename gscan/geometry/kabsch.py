"""Kabsch / Umeyama alignment of matched point sets, and the outlier-trimmed Kabsch of registration and
pose estimation: the specifications and the checks of the input. Each is computed by a numba kernel
(`gscan.geometry.kabsch_kernel`, the consensus step `gscan.geometry.consensus_kernel`), imported on first use so
that importing gscan.geometry does not load numba.
"""
from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
            with_scale: bool = False) -> np.ndarray:
    """Least-squares rigid (or similarity) transform T with dst ~= T @ src.

    src, dst: [N x 3], N >= 3 (weights [N] optional). A reflection is never returned
    (the reflection guard flips the smallest singular direction). Returns [4 x 4];
    with_scale puts the scale into the rotation block.
    """
    from gscan.geometry.kabsch_kernel import umeyama as kernel  # numba, on first use

    src, dst = _pairs(src, dst, 3)
    w = np.ones(len(src)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64).reshape(len(src))
    return kernel(src, dst, w, with_scale)


def _pairs(src: np.ndarray, dst: np.ndarray, n_min: int) -> tuple[np.ndarray, np.ndarray]:
    """src, dst as C-contiguous float64 [N x 3] arrays of one shape, N >= n_min (ValueError otherwise)."""
    src = np.ascontiguousarray(src, dtype=np.float64)
    dst = np.ascontiguousarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < n_min:
        raise ValueError(f"need two [N x 3] arrays with N >= {n_min}, got {src.shape} and {dst.shape}")
    return src, dst


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Rigid T (proper rotation) minimising sum |T @ src_i - dst_i|^2. src, dst: [N x 3]."""
    return umeyama(src, dst, weights, with_scale=False)


def leave_one_out_residuals(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """[N] residual |T_k src_k - dst_k| of each pair under T_k = kabsch of the other N - 1 pairs (src, dst
    [N x 3], N >= 4): the N fits each from the totals less the pair left out."""
    from gscan.geometry.kabsch_kernel import leave_one_out_residuals as kernel  # numba, on first use

    return kernel(*_pairs(src, dst, 4))


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
    from gscan.geometry.kabsch_kernel import kabsch_trimmed as kernel  # numba, on first use

    src, dst = _pairs(src, dst, 3)
    n = len(src)
    taus = np.ascontiguousarray(np.broadcast_to(np.asarray(tau, dtype=np.float64), (n,)))  # [N]
    return kernel(src, dst, taus, float(min_sin), min(n, CONSENSUS_MAX_PAIRS))
