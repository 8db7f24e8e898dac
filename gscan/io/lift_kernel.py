"""The window statistics of `gscan.io.camera.lift_keypoints` (numba): per keypoint, the median and the 10th and
90th percentiles of the valid depths in the window around its pixel, and their count.

Percentiles interpolate linearly between the two nearest ranks of the sorted valid values (numpy's default
method, to rounding); one pass per keypoint over its window, instead of a padded copy of the depth, a gathered
[N x window^2] block and a row sort. Compiled with `cache=True`, `nogil=True`; imported on first use, so that
importing `gscan.io` does not load numba.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _percentile(s, k, q):
    """The q-th percentile (q in [0, 100]) of the k sorted values s[:k] (k >= 1): linear between the two nearest
    ranks (a non-finite upper one counts as the lower)."""
    last = k - 1
    pos = q / 100.0 * last
    i0 = int(np.floor(pos))
    i1 = min(i0 + 1, last)
    a = s[i0]
    if i1 == i0:
        return a
    b = s[i1]
    if not np.isfinite(b):
        b = a
    return a + (b - a) * (pos - i0)


@njit(cache=True, nogil=True)
def window_stats(depth, u, v, r, med, lo, hi, count):
    """For keypoint k at integer pixel (u[k], v[k]) of depth [H x W]: count[k] the depths > 0 in the
    (2r+1)^2 window around it (pixels outside the image count as invalid), med / lo / hi [k] their 50th, 10th
    and 90th percentiles in float64 (NaN when none)."""
    H, W = depth.shape
    buf = np.empty((2 * r + 1) ** 2)
    for k in range(u.shape[0]):
        n = 0
        for y in range(v[k] - r, v[k] + r + 1):
            for x in range(u[k] - r, u[k] + r + 1):
                if y < 0 or y >= H or x < 0 or x >= W:
                    continue
                z = np.float64(depth[y, x])
                if z > 0:  # insertion into the sorted buf[:n]
                    i = n
                    while i > 0 and buf[i - 1] > z:
                        buf[i] = buf[i - 1]
                        i -= 1
                    buf[i] = z
                    n += 1
        count[k] = n
        if n == 0:
            med[k] = lo[k] = hi[k] = np.nan
        else:
            med[k] = _percentile(buf, n, 50.0)
            lo[k] = _percentile(buf, n, 10.0)
            hi[k] = _percentile(buf, n, 90.0)
