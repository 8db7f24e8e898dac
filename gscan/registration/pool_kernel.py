"""Numba kernels of the guided pool's lookup (gscan.registration.pairwise.GuidedPool): the keypoint pairs whose
descriptors are close, held per source keypoint (compressed rows), and those of them whose two points lie within
a radius under a pose.

A pair is near when the squared distance, summed over x, y, z in that order, is at most the squared radius: the
test scipy's k-d tree makes, so the lookup returns the pairs a ball query over the target points followed by the
descriptor filter returned, in the same (source, target) order, without the lists of lists a ball query builds.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def pool_rows(dist, eps):  # pragma: no cover - compiled
    """(start [Ns + 1], targets [P]) int64: the targets j with dist[i, j] < eps of source i are
    targets[start[i]:start[i + 1]], ascending. dist [Ns x Nt]."""
    ns, nt = dist.shape
    start = np.zeros(ns + 1, np.int64)
    for i in range(ns):
        c = 0
        for j in range(nt):
            if dist[i, j] < eps:
                c += 1
        start[i + 1] = start[i] + c
    targets = np.empty(start[ns], np.int64)
    for i in range(ns):
        k = start[i]
        for j in range(nt):
            if dist[i, j] < eps:
                targets[k] = j
                k += 1
    return start, targets


@njit(cache=True, nogil=True)
def near_pairs(start, targets, q, pts_t, tau):  # pragma: no cover - compiled
    """(source indices [K], target indices [K]) int64 of the pool's pairs (start, targets of `pool_rows`) with
    |q[i] - pts_t[j]| <= tau[i]; q [Ns x 3] the source points in the target frame, pts_t [Nt x 3], tau [Ns];
    sorted by source, then target."""
    ii = np.empty(len(targets), np.int64)
    jj = np.empty(len(targets), np.int64)
    n = 0
    for i in range(q.shape[0]):
        r2 = tau[i] * tau[i]
        for k in range(start[i], start[i + 1]):
            j = targets[k]
            d = 0.0
            for a in range(3):
                e = pts_t[j, a] - q[i, a]
                d += e * e
            if d <= r2:
                ii[n] = i
                jj[n] = j
                n += 1
    return ii[:n], jj[:n]
