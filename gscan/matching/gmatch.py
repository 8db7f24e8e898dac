"""GMatch: geometry-constrained keypoint matching (Method and Algorithm 1 of M. Yang and H. Li, "GMatch: A
Lightweight, Geometry-Constrained Keypoint Matcher for Zero-Shot 6DoF Pose Estimation in Robotic Grasp Tasks",
arXiv:2505.16144).

Inputs per side: 3D keypoints [N x 3] (metres, in that side's camera frame), a descriptor
distance matrix [Ns x Nt] and the viewing direction of each side in the frame of its points.

Definitions (GMatch as gscan implements it):

* candidates: all pairs (i, j) with descriptor distance d_f(i, j) < eps_f, ordered by
  (key ascending, row-major index) -- this order is the "descriptor order" below (seeds, levels 2
  and 3) and the tie-break of every argmin, which makes the search deterministic. `order` picks the
  key: "ratio" (default) d_f(i, j) / d_2(i), d_2(i) the second-smallest distance of source i's row
  (Lowe's ratio: the most distinctive pairs first), or "distance" d_f itself (the paper's "top-T
  most similar"). On repetitive textures (newspaper glyphs, wood grain) the most similar pairs are
  copies of one pattern, so the first T candidates by distance may hold no true pair; by ratio the
  true pairs come first (see BENCHMARKS.md, section Parameter studies).
* delta(p, q) for two pairs p = (i1, j1), q = (i2, j2): with l_s = |ps_i1 - ps_i2| and
  l_t = |pt_j1 - pt_j2|, delta = |l_s - l_t| / l_s if |l_s - l_t| < eta_pq, else 1.
  eta_pq = eta * max(f(p), f(q)) with f(i, j) = max(1, (z / eta_ref_depth)^2) over the
  depths z of the pair's two keypoints when `eta_depth` (depth noise grows with z^2),
  else 1. Pairs sharing a source or a target keypoint are never combined (one-to-one).
* g(matches, q) = max over p in matches of delta(p, q); a pair is consistent if g <= eps_c.
* flip-over test of a pair q against the last two matches m1 = matches[-1], m2 = matches[-2]:
  n_s = (ps_m1 - ps_m2) x (ps_m1 - ps_q), likewise n_t; with z_s = n_s . view_s / |n_s| and
  z_t = n_t . view_t / |n_t|, q flips over iff z_s * z_t < 0 (the paper's sign test) and
  |z_s - z_t| > flip_margin. The margin is for triples that are not on one surface: the camera may
  cross such a triangle's plane, and a view change of theta flips the sign of triangles with
  |z_s| + |z_t| up to about 2 sin(theta / 2) (0.62 at 36 deg): without a margin a scan with 36 deg
  between views registers wrong edges (see BENCHMARKS.md, section Parameter studies). The cost:
  a plane seen from behind at more than ~66 deg from the view, and a mirror image of a deep 3D
  layout, are not rejected by it (the "triple" set rejects mirror images). Near-collinear triples
  (sine of the angle at the first vertex, |n| / (|e1| |e2|), below collinear_sin on either side)
  are not tested.
* "triple" constraint set (instead of flip-over): the hypothesis' start triangle (a, b, c)
  fixes a plane on each side (unit normals from the same ordered triangle, so a mirror image
  has the opposite sign); a pair q gets the extra cost |h_s - h_t| / |ps_q - ps_a| if
  |h_s - h_t| < eta_aq else 1, h = signed off-plane distance (the triple product
  (b - a) x (c - a) . (q - a) divided by |(b - a) x (c - a)|); like delta, a cost above eps_c
  rejects the pair.
  With pairwise distances this is the paper's complete characterisation up to rigid motion.
* "distance": pairwise distances only (ablation; cannot tell a mirror image apart).

Search (bounded; every bound is a parameter):

1. seeds: the first T candidates in descriptor order.
2. per seed s: A_s = candidates consistent with s (delta <= eps), kept in descriptor order.
   Level 2: the first K2 members b of A_s; A_b = members of A_s consistent with b.
   Level 3: per b, the first K3 members c of A_b (one-to-one, g({s, b}, c) <= eps) whose triangle
   (s, b, c) is non-degenerate (sine of the angle at s >= collinear_sin on both sides) and, in flip
   mode, does not flip over (tested at the same corner s, so every start triangle is flip-tested). At most
   T * K2 * K3 hypotheses of length 3; start cost = max of the three deltas. Each hypothesis is grown as
   soon as it is generated (seed, b, c order).
3. growth (Algorithm 1 `Step`, up to length L): the hypothesis keeps its survivors (members of
   A_b consistent with every match so far) with their running max cost g, updated with the newest
   match only, so a Step is O(#survivors). Each Step removes survivors with g > eps or sharing a
   keypoint with the newest match, skips flip-overs w.r.t. the last two matches (flip mode; skipped
   pairs stay survivors) and appends the argmin of g (ties: descriptor order).
4. the longest list wins, ties by lower cost, then by search order (every hypothesis' list is kept in
   the trace: `gscan.registration.pairwise` checks the support of the runners-up). Bound: g never decreases as
   a list grows, so once a full-length (L) list of cost c* exists nothing containing a pair with
   g >= c* can win; eps tightens from eps_c to min(eps_c, c*) for everything generated afterwards
   (A_s is compacted, so from then on the first K2 / K3 members of levels 2 and 3 are counted among
   the pairs left: the hypotheses tried depend on the tightening, deterministically and still at
   most T * K2 * K3), and a hypothesis is abandoned ("pruned") once its cost reaches c* or its
   length + #survivors falls below the best length; its trace entry keeps the shorter list.

The search runs in a numba kernel (`gscan.matching.kernel`, compiled with `cache=True`); candidate
extraction is a separate function.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from gscan.matching.kernel import flips, search, second_smallest_per_row

# the settings live in a light module (read with the configuration); their names stay importable from here
from gscan.matching.params import CONSTRAINTS, ORDERS, GMatchParams, default_eps_f  # noqa: F401

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HypothesisTrace:
    seed: tuple[int, int]  # (source, target) keypoint indices of the seed pair
    start: np.ndarray  # [3 x 2] int32 the length-3 hypothesis
    matches: np.ndarray  # [length x 2] int32 its list as grown (up to where it was pruned)
    length: int  # final length (when pruned: length reached before pruning)
    cost: float  # max pairwise cost of the list
    pruned: bool  # abandoned because it could no longer beat the best list


@dataclass
class GMatchResult:
    matches: np.ndarray  # [M x 2] int32 (source index, target index), in match order
    cost: float  # max pairwise delta over the final list (1.0 when empty)
    n_candidates: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)  # "candidates", "search"
    # per hypothesis: start [H x 3 x 2] int32, length [H], cost [H], pruned [H], list [H x L x 2] (see `trace`)
    hyp_start: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 2), np.int32))
    hyp_length: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    hyp_cost: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hyp_pruned: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    # [H x L x 2], -1 past length
    hyp_matches: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 2), np.int32))
    candidates: Candidates | None = None  # the candidate pairs searched (set by `gmatch`)

    @property
    def trace(self) -> list[HypothesisTrace]:
        """Per hypothesis, in search order: seed pair, 3-pair start, its list, final length, cost, pruned."""
        return [HypothesisTrace((int(h[0, 0]), int(h[0, 1])), h, m[:n], int(n), float(c), bool(p))
                for h, m, n, c, p in zip(self.hyp_start, self.hyp_matches, self.hyp_length, self.hyp_cost,
                                         self.hyp_pruned, strict=True)]


@dataclass(frozen=True)
class Candidates:
    src: np.ndarray  # [C] int32 source keypoint index, descriptor order
    tgt: np.ndarray  # [C] int32 target keypoint index
    dist: np.ndarray  # [C] float32 descriptor distance, in search order


def extract_candidates(dist: np.ndarray, eps_f: float, order: str) -> Candidates:
    """Pairs with dist [Ns x Nt] < eps_f in search order (module docstring): by (key, row-major index)
    with key = the distance ("distance") or the distance over the second-smallest distance of its row
    ("ratio"; rows with fewer than two targets use eps_f)."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    dist = np.asarray(dist)
    if dist.ndim != 2:
        raise ValueError(f"distance matrix must be [Ns x Nt], got shape {dist.shape}")
    flat = np.flatnonzero(dist < eps_f)
    d = dist.reshape(-1)[flat].astype(np.float32)
    d2 = None
    if order == "ratio" and len(d) and dist.shape[1] >= 2:
        d2 = second_smallest_per_row(np.ascontiguousarray(dist, dtype=np.float32))
    return order_candidates(flat, d, d2, dist.shape, eps_f, order)


def order_candidates(flat: np.ndarray, d: np.ndarray, d2: np.ndarray | None, shape: tuple[int, int], eps_f: float,
                     order: str) -> Candidates:
    """The candidates of `extract_candidates` from their pairs: flat [C] row-major indices into the
    [Ns x Nt] distance matrix `shape` (any order), d [C] float32 their distances, d2 [Ns] float32 every row's
    second-smallest distance (None: Nt < 2, eps_f is used; needed for "ratio" only)."""
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    nt = shape[1]
    key = d.astype(np.float32) + np.float32(0.0)  # (-0 -> +0)
    if order == "ratio" and len(key):
        d2 = np.full(shape[0], eps_f, np.float32) if d2 is None else d2
        key = (key / np.maximum(d2[flat // nt], np.float32(1e-30))).astype(np.float32)
    if shape[0] * nt < 2**32 and (len(key) == 0 or key.min() >= 0):
        # one sort of unique 64-bit keys (float32 bits, monotone for non-negative values | flat index): faster
        # than sorting by two keys, same order
        o = np.argsort((key.view(np.uint32).astype(np.uint64) << np.uint64(32)) | flat.astype(np.uint64))
    else:
        o = np.lexsort((flat, key))
    flat = flat[o]
    return Candidates((flat // nt).astype(np.int32), (flat % nt).astype(np.int32), d[o].astype(np.float32))


# ----------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------


def _as_points(p: np.ndarray, name: str) -> np.ndarray:
    p = np.ascontiguousarray(p, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must be [N x 3], got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} holds non-finite values")
    return p


def _unit(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    nv = np.linalg.norm(v)
    if not np.isfinite(nv) or nv == 0:
        raise ValueError(f"{name} must be a non-zero 3-vector")
    return v / nv


def _depth_factor(pts: np.ndarray, view: np.ndarray, params: GMatchParams, depth: np.ndarray | None) -> np.ndarray:
    if not params.eta_depth:
        return np.ones(len(pts))
    z = pts @ view if depth is None else np.asarray(depth, dtype=np.float64).reshape(len(pts))
    return np.maximum(1.0, (z / params.eta_ref_depth) ** 2)


def search_candidates(pts_s: np.ndarray, pts_t: np.ndarray, cand: Candidates, params: GMatchParams = GMatchParams(),
                      view_s: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.0),
                      view_t: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.0),
                      depth_s: np.ndarray | None = None, depth_t: np.ndarray | None = None) -> GMatchResult:
    """GMatch search over precomputed candidates (see module docstring).

    pts_s [Ns x 3], pts_t [Nt x 3] metres; view_* [3] viewing direction in the frame of the points;
    depth_* [N] optional depths for the eta growth (default: pts @ view, right for camera-frame points).
    """
    pts_s = _as_points(pts_s, "pts_s")
    pts_t = _as_points(pts_t, "pts_t")
    vs, vt = _unit(view_s, "view_s"), _unit(view_t, "view_t")
    t0 = time.perf_counter()
    C = len(cand.src)
    if C == 0:
        return GMatchResult(np.zeros((0, 2), np.int32), 1.0, 0, {"search": 0.0})
    ci = np.ascontiguousarray(cand.src, dtype=np.int32)
    cj = np.ascontiguousarray(cand.tgt, dtype=np.int32)
    if ci.min() < 0 or ci.max() >= len(pts_s) or cj.min() < 0 or cj.max() >= len(pts_t):
        raise ValueError("candidate indices out of range")
    fs = _depth_factor(pts_s, vs, params, depth_s)
    ft = _depth_factor(pts_t, vt, params, depth_t)
    cf = np.maximum(fs[ci], ft[cj]).astype(np.float32)
    best, n, cost, hyp, hlen, hcost, hpruned, hlist = search(
        pts_s, pts_t, ci, cj, cf, fs, float(ft.max()), vs, vt, int(params.T), int(params.L), int(params.K2),
        int(params.K3),
        float(params.eps_c), float(params.eta), CONSTRAINTS[params.constraint], float(params.flip_margin),
        float(params.collinear_sin))
    matches = np.stack([ci[best[:n]], cj[best[:n]]], 1).astype(np.int32) if n else np.zeros((0, 2), np.int32)
    hmatches = np.where(hlist[..., None] >= 0, np.stack([ci[hlist], cj[hlist]], -1), -1).astype(np.int32)
    ms = (time.perf_counter() - t0) * 1e3
    return GMatchResult(matches, float(cost) if n else 1.0, C, {"search": ms},
                        np.stack([ci[hyp], cj[hyp]], -1).astype(np.int32), hlen, hcost, hpruned, hmatches)


def step(pts_s: np.ndarray, pts_t: np.ndarray, cand: Candidates, matches: np.ndarray,
         params: GMatchParams = GMatchParams(), view_s=(0.0, 0.0, 1.0), view_t=(0.0, 0.0, 1.0)) -> int | None:
    """Algorithm 1 (`Step`) written out in numpy: the readable reference of the kernel's growth.

    matches [M x 2] (M >= 2; M >= 3 for "triple") source/target indices. Returns the index (into the
    candidate arrays) of the pair to append -- argmin of g over the candidates that are one-to-one
    with the matches, have g <= eps_c and do not flip over w.r.t. the last two matches (ties: the
    first in descriptor order) -- or None. O(#candidates * M); the kernel does the same in
    O(#survivors) per Step.
    """
    pts_s = _as_points(pts_s, "pts_s")
    pts_t = _as_points(pts_t, "pts_t")
    vs, vt = _unit(view_s, "view_s"), _unit(view_t, "view_t")
    m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    ci, cj = cand.src.astype(np.int64), cand.tgt.astype(np.int64)
    fs = _depth_factor(pts_s, vs, params, None)
    ft = _depth_factor(pts_t, vt, params, None)
    cf = np.maximum(fs[ci], ft[cj])
    ok = ~np.isin(ci, m[:, 0]) & ~np.isin(cj, m[:, 1])
    g = np.zeros(len(ci))
    for i, j in m:
        ls = np.linalg.norm(pts_s[ci] - pts_s[i], axis=1)
        lt = np.linalg.norm(pts_t[cj] - pts_t[j], axis=1)
        err = np.abs(ls - lt)
        eta = params.eta * np.maximum(cf, max(fs[i], ft[j]))
        d = np.where((err < eta) & (ls > 0), err / np.maximum(ls, 1e-12), 1.0)
        g = np.maximum(g, d)
    if params.constraint == "triple" and len(m) >= 3:
        a, b, c = m[:3]
        ns = np.cross(pts_s[b[0]] - pts_s[a[0]], pts_s[c[0]] - pts_s[a[0]])
        nt = np.cross(pts_t[b[1]] - pts_t[a[1]], pts_t[c[1]] - pts_t[a[1]])
        hs = (pts_s[ci] - pts_s[a[0]]) @ (ns / np.linalg.norm(ns))
        ht = (pts_t[cj] - pts_t[a[1]]) @ (nt / np.linalg.norm(nt))
        la = np.linalg.norm(pts_s[ci] - pts_s[a[0]], axis=1)
        err = np.abs(hs - ht)
        eta = params.eta * np.maximum(cf, max(fs[a[0]], ft[a[1]]))
        g = np.maximum(g, np.where((err < eta) & (la > 0), err / np.maximum(la, 1e-12), 1.0))
    ok &= g <= params.eps_c
    if params.constraint == "flip" and len(m) >= 2:
        (i1, j1), (i2, j2) = m[-1], m[-2]
        for k in np.flatnonzero(ok):
            if flips(pts_s, pts_t, i1, i2, ci[k], j1, j2, cj[k], vs, vt, params.flip_margin, params.collinear_sin):
                ok[k] = False
    if not ok.any():
        return None
    idx = np.flatnonzero(ok)
    return int(idx[np.argmin(g[idx])])


def gmatch(pts_s: np.ndarray, pts_t: np.ndarray, dist: np.ndarray, eps_f: float, params: GMatchParams = GMatchParams(),
           view_s: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.0),
           view_t: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.0), depth_s: np.ndarray | None = None,
           depth_t: np.ndarray | None = None) -> GMatchResult:
    """GMatch: the longest geometrically consistent list of keypoint pairs (module docstring).

    Args:
        pts_s, pts_t: source [Ns x 3] and target [Nt x 3] keypoints, metres, each in its own camera (or view) frame.
        dist: [Ns x Nt] descriptor distances (`gscan.features.descriptor_distances`).
        eps_f: feature threshold: pairs closer than it are candidates (`default_eps_f(kind)`).
        params: the search's bounds and tolerances.
        view_s, view_t: [3] viewing direction of each side in the frame of its points (+z for camera frames).
        depth_s, depth_t: optional [N] depths for the depth-grown eta (default: the points along the view).

    Returns:
        GMatchResult: matches [M x 2] int32 (source, target index; M <= params.L, empty when nothing is
        consistent), its cost, the number of candidates, timings, and every hypothesis' list (`trace`).
    """
    dist = np.asarray(dist)
    if dist.shape != (len(pts_s), len(pts_t)):
        raise ValueError(f"distance matrix shape {dist.shape} != ({len(pts_s)}, {len(pts_t)})")
    t0 = time.perf_counter()
    cand = extract_candidates(dist, eps_f, params.order)
    t_cand = (time.perf_counter() - t0) * 1e3
    res = search_candidates(pts_s, pts_t, cand, params, view_s, view_t, depth_s, depth_t)
    res.timings_ms["candidates"] = t_cand
    res.candidates = cand
    log.debug("gmatch: %d candidates, %d matches, cost %.4f, %s", res.n_candidates, len(res.matches), res.cost,
              res.timings_ms)
    return res
