"""Pairing colour and depth frames by timestamp."""
from __future__ import annotations

import numpy as np

DEFAULT_PERIOD_S = 1.0 / 30.0  # frame period assumed for a stream of a single frame


def frame_period(stamps_ns: np.ndarray) -> float | None:
    """Median interval (s) between consecutive distinct timestamps; None for fewer than two."""
    t = np.unique(np.asarray(stamps_ns, dtype=np.int64))
    if len(t) < 2:
        return None
    return float(np.median(np.diff(t))) * 1e-9


def pair_tolerance(color_ns: np.ndarray, depth_ns: np.ndarray) -> float:
    """Largest colour-depth time difference (s) accepted as one frame: half the frame period of the
    faster stream (its median interval), so that each frame is paired with at most its nearest partner."""
    periods = [p for p in (frame_period(color_ns), frame_period(depth_ns)) if p is not None and p > 0]
    return 0.5 * (min(periods) if periods else DEFAULT_PERIOD_S)


def pair_frames(color_ns: np.ndarray, depth_ns: np.ndarray, max_dt_s: float) -> dict[int, int]:
    """One-to-one pairs {colour index: depth index} with |t_colour - t_depth| <= max_dt_s, closest first
    (ties: earlier colour, then earlier depth), as TUM's associate.py but in O(N log N).

    color_ns: [Nc], depth_ns: [Nd] int64 nanoseconds (any order).
    """
    c = np.asarray(color_ns, dtype=np.int64)
    d = np.asarray(depth_ns, dtype=np.int64)
    if len(c) == 0 or len(d) == 0:
        return {}
    tol = round(max_dt_s * 1e9)
    order = np.argsort(d, kind="stable")
    ds = d[order]
    lo = np.searchsorted(ds, c - tol, side="left")
    hi = np.searchsorted(ds, c + tol, side="right")
    ci, dj, dt = [], [], []
    for i in range(len(c)):  # each colour frame has few candidates: the tolerance is half a frame period
        for k in range(lo[i], hi[i]):
            ci.append(i)
            dj.append(int(order[k]))
            dt.append(abs(int(c[i]) - int(ds[k])))
    if not ci:
        return {}
    ci_a, dj_a, dt_a = np.array(ci), np.array(dj), np.array(dt)
    pairs: dict[int, int] = {}
    used: set[int] = set()
    for k in np.lexsort((dj_a, ci_a, dt_a)):
        i, j = int(ci_a[k]), int(dj_a[k])
        if i not in pairs and j not in used:
            pairs[i] = j
            used.add(j)
    return pairs
