"""Numba kernels of `gscan.geometry.kabsch` (the specifications are there): Umeyama / Kabsch, the leave-one-out
residuals and the outlier-trimmed Kabsch, whose consensus step is `consensus_kernel.best_triple`.

Registration solves thousands of small alignments a scan (GMatch lists, their runner-ups, every refinement
round): in numpy each costs some twenty calls of a few microseconds, and holds the interpreter lock while it
does, so the scan's two registration threads wait on each other. Here one call does the whole alignment with
the lock released. The arithmetic follows the numpy formulation step by step, in its order (numpy's pairwise
summation, the same BLAS and LAPACK calls, einsum's order of a 3-term sum), so the results are those numpy
gives: scans are the same with either. Compiled with `cache=True`, `nogil=True`; imported on first use, so that
importing `gscan.geometry` does not load numba.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from gscan.geometry.consensus_kernel import best_triple


@njit(cache=True, nogil=True)
def _block_sum(a, lo, n):
    """Sum of a[lo:lo + n], n <= 128, as numpy sums a block: 8 partial sums, then the rest in order."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r = np.empty(8)
    for q in range(8):
        r[q] = a[lo + q]
    i = 8
    while i < n - n % 8:
        for q in range(8):
            r[q] += a[lo + i + q]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def _pairwise_sum(a):
    """Sum of a contiguous float64 vector as numpy's add.reduce sums it: blocks of up to 128 elements, halves
    beyond (each half's length a multiple of 8), the halves' sums added. Iterative: numba's cache cannot hold a
    recursive function."""
    lo_s = np.empty(64, np.int64)  # the halves still to sum (a vector of 2^64 elements is the limit)
    n_s = np.empty(64, np.int64)
    left = np.empty(64)  # the left half's sum of a split whose right half is being summed
    state = np.zeros(64, np.int64)  # 0: not split yet, 1: left half being summed, 2: right half
    top = 0
    lo_s[0], n_s[0] = 0, a.shape[0]
    value = 0.0
    while top >= 0:
        n = n_s[top]
        if n <= 128 or state[top] == 2:
            value = _block_sum(a, lo_s[top], n) if n <= 128 else left[top] + value
            state[top] = 0
            top -= 1
            if top >= 0 and state[top] == 1:  # the left half is done: the right one next
                left[top] = value
                state[top] = 2
                n2 = n_s[top] // 2
                n2 -= n2 % 8
                top += 1
                lo_s[top], n_s[top] = lo_s[top - 1] + n2, n_s[top - 1] - n2
            continue  # (a parent in state 2 adds its halves on the next pass)
        state[top] = 1
        n2 = n // 2
        n2 -= n2 % 8
        top += 1
        lo_s[top], n_s[top] = lo_s[top - 1], n2
    return value


@njit(cache=True, nogil=True)
def _det3(M):
    return (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]) - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
            + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]))


@njit(cache=True, nogil=True)
def umeyama(src, dst, w, with_scale):
    """[4 x 4] T with dst ~= T @ src: src, dst [N x 3] C-contiguous float64, N >= 3; w [N] float64 weights
    (not normalised); with_scale: the similarity's scale in the rotation block."""
    n = src.shape[0]
    w = w / _pairwise_sum(w)
    mu_s = np.dot(w, src)
    mu_d = np.dot(w, dst)
    xs = src - mu_s
    xd = dst - mu_d
    C = np.dot((xd * w.reshape(n, 1)).T, xs)
    U, S, Vt = np.linalg.svd(C)
    d = 1.0
    if _det3(U) * _det3(Vt) < 0:  # the reflection guard: the smallest singular direction flipped
        U[:, 2] = -U[:, 2]
        d = -1.0
    R = np.dot(U, Vt)
    s = 1.0
    if with_scale:
        sq = np.empty(n)
        for i in range(n):
            sq[i] = w[i] * ((xs[i, 0] * xs[i, 0] + xs[i, 1] * xs[i, 1]) + xs[i, 2] * xs[i, 2])
        s = ((S[0] + S[1]) + S[2] * d) / _pairwise_sum(sq)
    sR = s * R
    T = np.eye(4)
    T[:3, :3] = sR
    T[:3, 3] = mu_d - np.dot(sR, mu_s)
    return T


@njit(cache=True, nogil=True)
def leave_one_out_residuals(src, dst):
    """[N] |T_k src_k - dst_k|, T_k the Kabsch fit of the other N - 1 pairs: src, dst [N x 3] C-contiguous
    float64, N >= 4 (each fit from the totals less the pair left out)."""
    n = src.shape[0]
    m = n - 1
    tot_s = src[0].copy()  # column sums, row after row (numpy's axis-0 reduction)
    tot_d = dst[0].copy()
    for i in range(1, n):
        tot_s += src[i]
        tot_d += dst[i]
    G = np.dot(dst.T, src)
    out = np.empty(n)
    C = np.empty((3, 3))
    mu_s = np.empty(3)
    mu_d = np.empty(3)
    x = np.empty(3)
    for k in range(n):
        for a in range(3):
            mu_s[a] = (tot_s[a] - src[k, a]) / m
            mu_d[a] = (tot_d[a] - dst[k, a]) / m
        for a in range(3):
            for b in range(3):
                C[a, b] = G[a, b] - dst[k, a] * src[k, b] - m * mu_d[a] * mu_s[b]
        U, _, Vt = np.linalg.svd(C)
        if _det3(U) * _det3(Vt) < 0:
            U[:, 2] = -U[:, 2]
        R = np.dot(U, Vt)
        for a in range(3):
            x[a] = src[k, a] - mu_s[a]
        r = 0.0
        for a in range(3):
            e = ((R[a, 0] * x[0] + R[a, 2] * x[2]) + R[a, 1] * x[1]) + mu_d[a] - dst[k, a]  # einsum's order
            r += e * e
        out[k] = np.sqrt(r)
    return out


@njit(cache=True, nogil=True)
def _residuals(T, src, dst, out):
    """out [N] = |T src - dst| row by row (transform_points' product, then a norm's sum)."""
    P = np.dot(src, np.ascontiguousarray(T[:3, :3].T))
    for i in range(src.shape[0]):
        r = 0.0
        for a in range(3):
            e = P[i, a] + T[a, 3] - dst[i, a]
            r += e * e
        out[i] = np.sqrt(r)


@njit(cache=True, nogil=True)
def _fit_kept(src, dst, keep, ones):
    idx = np.flatnonzero(keep)
    return umeyama(np.ascontiguousarray(src[idx]), np.ascontiguousarray(dst[idx]), ones[:len(idx)], False)


@njit(cache=True, nogil=True)
def kabsch_trimmed(src, dst, taus, min_sin, n_enum):
    """(T [4 x 4], keep [N] bool): `gscan.geometry.kabsch.kabsch_trimmed` on src, dst [N x 3] C-contiguous
    float64, taus [N] float64 > 0; the consensus enumerates the triples of the first n_enum pairs."""
    n = src.shape[0]
    ones = np.ones(n)
    keep = np.ones(n, np.bool_)
    T = umeyama(src, dst, ones, False)
    r = np.empty(n)
    _residuals(T, src, dst, r)
    if n > 3 and (r > taus).any():  # 2. consensus
        i, j, k, T_tri = best_triple(src, dst, n_enum, taus, min_sin)
        if i >= 0:
            _residuals(T_tri, src, dst, r)
            keep = r < taus
            keep[i] = keep[j] = keep[k] = True
            stable = False
            for _ in range(3):
                T = _fit_kept(src, dst, keep, ones)
                _residuals(T, src, dst, r)
                again = r < taus
                if again.sum() < 3 or (again == keep).all():
                    stable = True  # T is the selection's pose
                    break
                keep = again
            if not stable:  # the third re-selection changed it
                T = _fit_kept(src, dst, keep, ones)
    floor = max(3, (n + 1) // 2)
    while keep.sum() >= 5 and keep.sum() - 1 >= floor:  # 3. leave-one-out residuals
        idx = np.flatnonzero(keep)
        loo = leave_one_out_residuals(np.ascontiguousarray(src[idx]), np.ascontiguousarray(dst[idx])) / taus[idx]
        worst = np.argmax(loo)
        if loo[worst] <= 1.0:
            break
        keep[idx[worst]] = False
        T = _fit_kept(src, dst, keep, ones)
    return T, keep
