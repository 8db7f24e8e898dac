"""Numba kernels over the retrieval matrix S [M query keypoints x N template keypoints] (cosine similarities
of unit descriptors, or distances), which read the entries they need instead of copying blocks out of it.

- `neighbourhood_candidates`: GMatch candidates of one view neighbourhood. The estimator matches a
  neighbourhood's template keypoints against the query keypoints, each side grouped by location (SIFT
  orientations of one point share it; a group's value is the best of its members'). GMatch needs only the
  pairs under the feature threshold and, for its ratio order, every template row's second-smallest distance
  (`gscan.matching.gmatch.extract_candidates`). One pass over S's rows computes both without building the
  grouped [rows x groups] distance block: the same candidate list, in the same order, as `extract_candidates`
  on that block.
- `best_columns`: per chosen row, the best of chosen columns (first on ties) and its value, as np.argmax
  over S[np.ix_(rows, cols)] (the keypoint support of a pose, gscan.estimate.verify).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from gscan.matching.gmatch import Candidates, order_candidates


@njit(cache=True, nogil=True)
def _scan(S, sign, q_members, q_starts, t_first, x_row, x_col, lo, unit, eps32, flat, dist, top2):
    """One pass over the groups of S [M x N] float32 (module docstring).

    sign: 1 (similarities, larger is better) or -1 (distances, negated so that larger is better); query group
    g holds rows q_members[q_starts[g]:q_starts[g+1]]; template row r's first column is t_first[r], its further
    columns x_col[k] for the k with x_row[k] == r. A pair is a candidate when its group value w exceeds `lo`
    and its distance (unit: sqrt(max(2 - 2 w, 0)) in float32, else -w) is below eps32.
    Writes flat [C] int64 (row-major index r * G + g, in query-group order) and dist [C] float32 of the first
    len(flat) candidates and top2 [R] float32 (every template row's second-largest group value, ties counted);
    returns C (more than len(flat) when they did not fit: call again with room for C)."""
    G = q_starts.shape[0] - 1
    R = t_first.shape[0]
    cap = flat.shape[0]
    top1 = np.full(R, -np.inf, np.float32)
    top2[:] = -np.inf
    buf = np.empty(R, np.float32)
    n = 0
    two = np.float32(2.0)
    zero = np.float32(0.0)
    for g in range(G):
        for a in range(q_starts[g], q_starts[g + 1]):
            row = S[q_members[a]]
            if a == q_starts[g]:
                for r in range(R):
                    buf[r] = sign * row[t_first[r]]
            else:
                for r in range(R):
                    w = sign * row[t_first[r]]
                    buf[r] = max(buf[r], w)
            for k in range(x_row.shape[0]):
                w = sign * row[x_col[k]]
                r = x_row[k]
                buf[r] = max(buf[r], w)
        for r in range(R):  # the two largest values of every template row, ties counted
            w = buf[r]
            t1 = top1[r]
            m = min(t1, w)
            top2[r] = max(top2[r], m)
            top1[r] = max(t1, w)
        for r in range(R):
            w = buf[r]
            if w > lo:
                if unit:
                    x = two - two * w
                    d = np.sqrt(max(zero, x))
                else:
                    d = -w
                if d < eps32:
                    if n < cap:
                        flat[n] = r * G + g
                        dist[n] = d
                    n += 1
    return n


def _unit_distance(w: np.float32) -> np.float32:
    """The distance of unit descriptors with cosine similarity w, in float32 as the kernel computes it."""
    x = np.float32(2.0) - np.float32(2.0) * w
    return np.sqrt(max(x, np.float32(0.0)))


@lru_cache(maxsize=8)
def _unit_threshold(eps32: np.float32) -> np.float32:
    """The largest float32 similarity whose distance is not below eps32: the candidates are exactly the group
    values above it (the distance falls monotonically with the similarity), so the kernel computes a distance
    for those only (a cosine above the threshold is rare; one below it is common for RootSIFT)."""
    w = np.float32(1.0 - 0.5 * float(eps32) ** 2)
    while _unit_distance(w) < eps32:
        w = np.nextafter(w, np.float32(-np.inf))
    while _unit_distance(np.nextafter(w, np.float32(np.inf))) >= eps32:
        w = np.nextafter(w, np.float32(np.inf))
    return np.float32(w)


class TemplateGroups:
    """The template side of a neighbourhood for `neighbourhood_candidates`: global keypoint columns [n] in row
    order (`order`, `starts` from gscan.geometry.pointset.coincident_groups over the neighbourhood's keypoints
    `idx` [n])."""

    def __init__(self, idx: np.ndarray, order: np.ndarray, starts: np.ndarray):
        cols = np.asarray(idx, np.int64)[order]
        sizes = np.diff(np.r_[starts, len(cols)])
        self.first = np.ascontiguousarray(cols[starts])  # [R] each row's first column
        extra = np.setdiff1d(np.arange(len(cols)), starts)  # the other members, row by row
        self.extra_row = np.repeat(np.arange(len(starts)), sizes - 1).astype(np.int64)
        self.extra_col = np.ascontiguousarray(cols[extra])

    def __len__(self) -> int:
        return len(self.first)


def neighbourhood_candidates(S: np.ndarray, unit: bool, q_order: np.ndarray, q_starts: np.ndarray,
                             tg: TemplateGroups, eps_f: float, order: str, capacity: int = 1 << 16) -> Candidates:
    """GMatch candidates (`gscan.matching.gmatch.Candidates`) of template rows `tg` against the query groups
    (`q_order`, `q_starts` [G] from coincident_groups of the query keypoints; q_order holds their rows in S,
    which may be a subset of S's rows) under the feature threshold
    eps_f: those `extract_candidates(dist, eps_f, order)` gives on dist [R x G], dist[r, g] the distance of
    the best-agreeing member pair. S [M x N] float32: cosine similarities of unit descriptors (`unit`;
    distance sqrt(2 - 2 s)) or distances. capacity: candidates the first pass has room for (a second pass
    follows when there are more)."""
    return neighbourhoods_candidates(S, unit, q_order, q_starts, [tg], eps_f, order, capacity)[0]


def neighbourhoods_candidates(S: np.ndarray, unit: bool, q_order: np.ndarray, q_starts: np.ndarray,
                              tgs: list[TemplateGroups], eps_f: float, order: str,
                              capacity: int = 1 << 16) -> list[Candidates]:
    """`neighbourhood_candidates` of several neighbourhoods in one pass over S's rows (each row is read once
    for all of them)."""
    G = len(q_starts)
    off = np.cumsum([0] + [len(tg) for tg in tgs])
    if G == 0 or off[-1] == 0:
        return [order_candidates(np.zeros(0, np.int64), np.zeros(0, np.float32), None, (len(tg), G), eps_f, order)
                for tg in tgs]
    eps32 = np.float32(eps_f)
    lo = _unit_threshold(eps32) if unit else -eps32
    qs = np.r_[q_starts, len(q_order)].astype(np.int64)
    first = np.concatenate([tg.first for tg in tgs])
    extra_row = np.concatenate([tg.extra_row + o for tg, o in zip(tgs, off[:-1], strict=True)])
    extra_col = np.concatenate([tg.extra_col for tg in tgs])
    args = (S, np.float32(1.0 if unit else -1.0), np.asarray(q_order, np.int64), qs, first, extra_row, extra_col,
            lo, unit, eps32)
    top2 = np.empty(off[-1], np.float32)
    cap = max(1, capacity)
    while True:
        flat, d = np.empty(cap, np.int64), np.empty(cap, np.float32)
        n = _scan(*args, flat, d, top2)
        if n <= cap:
            break
        cap = n
    row = flat[:n] // G  # rows of all the neighbourhoods, one after the other
    which = np.searchsorted(off, row, side="right") - 1
    d2 = np.sqrt(np.maximum(2.0 - 2.0 * top2, 0.0)) if unit else -top2
    out = []
    for k, tg in enumerate(tgs):
        sel = np.flatnonzero(which == k)
        out.append(order_candidates(flat[sel] - off[k] * G, d[sel], d2[off[k]:off[k + 1]] if G >= 2 else None,
                                    (len(tg), G), eps_f, order))
    return out


@njit(cache=True, nogil=True)
def _best_columns(S, sign, rows, cols, idx, val):
    for i in range(rows.shape[0]):
        row = S[rows[i]]
        best = sign * row[cols[0]]
        arg = 0
        for j in range(1, cols.shape[0]):
            w = sign * row[cols[j]]
            if w > best:
                best = w
                arg = j
        idx[i] = arg
        val[i] = best


def best_columns(S: np.ndarray, rows: np.ndarray, cols: np.ndarray, sign: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(j [R] int64, value [R]) for rows [R] and cols [K] (K >= 1) of S [M x N]: j the first position in cols of
    the largest sign * S[row, col] (sign -1: the smallest distance), value = sign * S[row, cols[j]] (S's dtype).
    Equal to np.argmax over (sign * S)[np.ix_(rows, cols)] along axis 1, without copying the block."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    if len(cols) == 0:
        raise ValueError("best_columns needs at least one column")
    S = np.ascontiguousarray(S)
    idx = np.empty(len(rows), np.int64)
    val = np.empty(len(rows), S.dtype)
    _best_columns(S, S.dtype.type(sign), rows, cols, idx, val)
    return idx, val
