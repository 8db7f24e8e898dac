"""Numba kernel of the colour check's correlation (gscan.registration.colour): per image shift and tile, the sums
of the target texture sampled at the shifted positions, of its square and of its product with the source
texture, without the [shifts x samples] intermediates numpy needs.

Each tile's sum is numpy's `np.add.reduceat` of the same values, to the bit: the first value plus numpy's
pairwise sum of the rest (blocks of 8 accumulators up to 128 values, halves beyond), so the check's verdicts do
not depend on which of the two computed them.
"""
from __future__ import annotations

import numpy as np
from numba import njit

_BLOCK = 128  # numpy's PW_BLOCKSIZE


@njit(cache=True, nogil=True)
def _pairwise(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise sum of a[lo:lo + n] (float64)."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    if n <= _BLOCK:
        r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
        r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
        i = 8
        while i < n - n % 8:
            r0 += a[lo + i]
            r1 += a[lo + i + 1]
            r2 += a[lo + i + 2]
            r3 += a[lo + i + 3]
            r4 += a[lo + i + 4]
            r5 += a[lo + i + 5]
            r6 += a[lo + i + 6]
            r7 += a[lo + i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += a[lo + i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(a, lo, n2) + _pairwise(a, lo + n2, n - n2)


@njit(cache=True, nogil=True)
def _reduce(a, lo, n):  # pragma: no cover - compiled
    """np.add.reduceat's value of the segment a[lo:lo + n] (n >= 1)."""
    return a[lo] + _pairwise(a, lo + 1, n - 1)


@njit(cache=True, nogil=True)
def shifted_sums(Ia, starts, flat, width, at, fx, fy, offsets, sb, sbb, sab):  # pragma: no cover - compiled
    """For every offset k and tile g (samples starts[g]:starts[g + 1] of Ia [K], sorted by tile): the target
    texture flat (float32, rows of `width`) bilinearly interpolated at at + offsets[k] (top-left pixel, weights
    fx, fy [K]) as `colour._tile_zncc` computes it, and its tile sums into sb, sbb (its square) and sab (its
    product with Ia), each [len(offsets) x G] float64."""
    G = starts.shape[0] - 1
    b = np.empty(Ia.shape[0])
    bb = np.empty(Ia.shape[0])
    ab = np.empty(Ia.shape[0])
    for k in range(offsets.shape[0]):
        off = offsets[k]
        for i in range(Ia.shape[0]):
            p = at[i] + off
            x, y = fx[i], fy[i]
            v = (np.float64(flat[p]) * (1 - x) + np.float64(flat[p + 1]) * x) * (1 - y) \
                + (np.float64(flat[p + width]) * (1 - x) + np.float64(flat[p + width + 1]) * x) * y
            b[i] = v
            bb[i] = v * v
            ab[i] = v * Ia[i]
        for g in range(G):
            lo, n = starts[g], starts[g + 1] - starts[g]
            sb[k, g] = _reduce(b, lo, n)
            sbb[k, g] = _reduce(bb, lo, n)
            sab[k, g] = _reduce(ab, lo, n)
