"""Stages 3-4, hypotheses: match lists of the retrieved neighbourhoods, pre-scored and pooled (`hypothesise`).

3. match: GMatch (gscan.matching.gmatch) of each retrieved neighbourhood's keypoints jointly, all expressed
   in its central view's camera frame (view direction +z), against the query keypoints (+z): a pose between
   keyframes, or a face the scan saw from a steeper angle than the query, collects its matches from several
   views at once. GMatch's candidates are read from the retrieval matrix by one kernel pass per
   neighbourhood (`gscan.estimate.similarity`), never recomputed or copied into a distance block.
4. every neighbourhood's best list and its GMatch runners-up (at most `runner_up_margin` shorter: in clutter a
   hard view's correct list ties with the lists the background offers) are posed at once (batched Kabsch) and
   pre-scored by the query keypoints their nearest template descriptor lands on at that pose; lists whose
   poses agree are pooled. The lists come back best pre-score first.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gscan.estimate.params import HypothesesParams
from gscan.estimate.retrieval import Retrieval, TemplateIndex
from gscan.estimate.similarity import neighbourhood_candidates, neighbourhoods_candidates
from gscan.estimate.verify import kabsch_batch, nn_support
from gscan.features import Features
from gscan.geometry.pointset import coincident_groups
from gscan.geometry.transforms import transform_points
from gscan.matching.gmatch import Candidates, GMatchParams, search_candidates


@dataclass
class MatchList:
    """One match list: matches [n x 2] (global template keypoint, query keypoint) found in the neighbourhood of
    `view`; cost: GMatch's; support: query keypoints whose nearest template descriptor lands on them at the
    list's plain Kabsch pose T [4 x 4] (T_cam_obj); longest: the longest single list pooled into this one."""

    n: int
    cost: float
    view: int
    matches: np.ndarray = field(repr=False)
    support: int = 0
    T: np.ndarray = field(default_factory=lambda: np.eye(4), repr=False)
    longest: int = 0


@dataclass
class QueryKeypoints:
    """The query's lifted keypoints and their similarity to the template. S: the retrieval matrix [M' x N];
    location [M]: a location id per keypoint (orientations of one point share it); order [M], starts [G]: the
    locations' keypoints (order[starts[g]:starts[g+1]], gscan.geometry.pointset.coincident_groups); group_kp
    [G]: a keypoint of each location; candidates: the GMatch candidates of the neighbourhoods to match, found
    together (central view -> its neighbourhood's); rows [M]: each keypoint's row in S (None: row i is
    keypoint i; `Retrieval.rows`)."""

    feats: Features
    S: np.ndarray = field(repr=False)
    location: np.ndarray = field(repr=False)
    order: np.ndarray = field(repr=False)
    starts: np.ndarray = field(repr=False)
    group_kp: np.ndarray = field(repr=False)
    candidates: dict[int, Candidates] = field(default_factory=dict, repr=False)
    rows: np.ndarray | None = field(default=None, repr=False)

    def row_of(self, kp: np.ndarray) -> np.ndarray:
        """The rows in S of the keypoints kp [K] (indices)."""
        return kp if self.rows is None else self.rows[kp]

    def similarity(self, cols: np.ndarray) -> np.ndarray:
        """S's columns cols [C] for every keypoint, in keypoint order [M x C] (a later instance search's
        keypoints are a subset of S's rows: read S through this or `row_of`, never row i as keypoint i)."""
        if self.rows is None:
            return self.S[:, cols]
        return self.S[self.rows[:, None], cols]


def query_keypoints(feats: Features, S: np.ndarray, rows: np.ndarray | None = None) -> QueryKeypoints:
    """The query keypoints grouped by location (S: the retrieval matrix, rows [M]: the keypoints' rows in it,
    None: row i is keypoint i)."""
    order, starts = coincident_groups(feats.points)
    location = np.empty(len(feats), np.int64)
    location[order] = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(feats)]))
    return QueryKeypoints(feats, S, location, order, starts, order[starts], rows=rows)


#: a neighbourhood's lists: (index, central view, query keypoints) -> [(matches [n x 2], cost)], best first
Matcher = Callable[[TemplateIndex, int, QueryKeypoints], list[tuple[np.ndarray, float]]]


@dataclass(frozen=True)
class GMatchLists:
    """The default `Matcher`: GMatch of the neighbourhood (its keypoints and its neighbours', in the central
    view's camera frame) against the query; its best list first, then the hypotheses at most
    `runner_up_margin` shorter (and at least `min_matches` long): a short correct list ties with the lists
    clutter offers, and the evidence decides between them. Keypoints sharing a 3D point (SIFT orientations of
    one location) are matched as one, by their closest descriptors."""

    gmatch: GMatchParams
    min_matches: int
    runner_up_margin: int

    def __call__(self, index: TemplateIndex, v: int, qk: QueryKeypoints) -> list[tuple[np.ndarray, float]]:
        nb = index.neighbourhoods[v]
        gs = nb.idx[nb.order[nb.starts]]  # source row -> global template keypoint
        gq = qk.group_kp  # target column -> query keypoint
        # the candidates of the [Ns x G] group distance block, read from S without building the block
        cand = qk.candidates.get(v)
        if cand is None:
            cand = neighbourhood_candidates(qk.S, index.unit, qk.row_of(qk.order), qk.starts, nb.groups,
                                            index.eps_f, self.gmatch.order)
        res = search_candidates(nb.points[nb.order[nb.starts]], qk.feats.points[gq], cand, self.gmatch)
        best = np.asarray(res.matches, dtype=np.int64).reshape(-1, 2)
        out = [(np.stack([gs[best[:, 0]], gq[best[:, 1]]], 1), float(res.cost))]
        n_min = max(self.min_matches, len(best) - self.runner_up_margin)
        hyps = np.flatnonzero(res.hyp_length >= n_min)
        if len(hyps):
            hm = res.hyp_matches[hyps].astype(np.int64)  # [H x L x 2], -1 past each length
            g = np.stack([gs[np.maximum(hm[..., 0], 0)], gq[np.maximum(hm[..., 1], 0)]], -1)
            out += [(g[i, :res.hyp_length[h]], float(res.hyp_cost[h])) for i, h in enumerate(hyps)]
        return out


def hypothesise(index: TemplateIndex, qk: QueryKeypoints, retrieval: Retrieval, matcher: Matcher,
                gmatch_order: str, params: HypothesesParams, support_sim: float,
                support_radius: float, views: list[int] | None = None) -> list[MatchList]:
    """Stages 3-4 (module docstring): the distinct lists of at least 3 pairs of the top neighbourhoods (or of the
    neighbourhoods of the central views `views`), pre-scored and pooled, best pre-score support first.
    support_sim: the similarity (negated distance) at which a query keypoint's nearest template descriptor
    agrees; support_radius: m at 0.5 m depth."""
    if views is None:
        views = index.top_neighbourhoods(retrieval.votes)
    qk.candidates = dict(zip(views, neighbourhoods_candidates(
        qk.S, index.unit, qk.row_of(qk.order), qk.starts, [index.neighbourhoods[v].groups for v in views],
        index.eps_f, gmatch_order), strict=True))
    lists: list[MatchList] = []
    seen: set[bytes] = set()
    for v in views:
        for m, cost in matcher(index, v, qk):
            key = np.ascontiguousarray(m[np.lexsort((m[:, 1], m[:, 0]))]).tobytes()
            if len(m) >= 3 and key not in seen:
                seen.add(key)
                lists.append(MatchList(len(m), cost, v, m))
    prescore(lists, index, qk.feats, retrieval, support_sim, support_radius)
    return merge_agreeing(lists, index.points_obj, qk.feats.points, params)


def prescore(lists: list[MatchList], index: TemplateIndex, feats: Features, retrieval: Retrieval,
             support_sim: float, support_radius: float) -> None:
    """Set every list's `T` (plain Kabsch, all lists at once) and `support`: the query keypoints whose nearest
    template keypoint by descriptor lands on them at that pose (`nn_support`)."""
    if not lists:
        return
    L = max(c.n for c in lists)
    src = np.zeros((len(lists), L, 3))
    dst = np.zeros((len(lists), L, 3))
    w = np.zeros((len(lists), L))
    for h, c in enumerate(lists):
        src[h, :c.n] = index.points_obj[c.matches[:, 0]]
        dst[h, :c.n] = feats.points[c.matches[:, 1]]
        w[h, :c.n] = 1.0
    T = kabsch_batch(src, dst, w)
    nn, best = retrieval.nn, retrieval.best
    agree = best >= support_sim if index.unit else best <= -support_sim
    q_pts = feats.points[agree].astype(np.float64)
    z = np.median(q_pts[:, 2]) if len(q_pts) else 0.5
    support = nn_support(T, index.points_obj[nn[agree]], q_pts, support_radius + 0.01 * max(float(z) - 0.5, 0.0))
    for c, n, T_h in zip(lists, support, T, strict=True):
        c.support, c.T = int(n), T_h


def merge_agreeing(lists: list[MatchList], points_obj: np.ndarray, q_points: np.ndarray,
                   params: HypothesesParams) -> list[MatchList]:
    """Lists whose poses agree (within merge_deg and merge_dist of the best-supported one's) are one list: their
    pairs are pooled (a pair once), so several short lists of one pose make one long one. points_obj [N x 3]:
    template keypoints, q_points [M x 3]: query keypoints. Returns the merged lists, best pre-score support
    first (ties: longer, then lower cost)."""
    order = sorted(lists, key=lambda c: (-c.support, -c.n, c.cost))
    merged: list[MatchList] = []
    members: list[list[np.ndarray]] = []
    if not order:
        return merged
    Ts = np.stack([c.T for c in order])
    trace_min = 1.0 + 2.0 * np.cos(np.radians(params.merge_deg))
    owner = np.full(len(order), -1)
    free = np.ones(len(order), bool)  # not yet owned by a representative
    for i, c in enumerate(order):  # each unowned list in order becomes a representative of those agreeing
        if not free[i]:
            members[owner[i]].append(c.matches)
            continue
        k = len(merged)
        merged.append(MatchList(c.n, c.cost, c.view, c.matches, c.support, c.T, c.n))
        members.append([c.matches])
        rest = np.flatnonzero(free[i + 1:]) + i + 1
        tr = np.einsum("ij,nij->n", c.T[:3, :3], Ts[rest, :3, :3])  # trace(R_c^T R_n)
        near = np.linalg.norm(Ts[rest, :3, 3] - c.T[:3, 3], axis=1) <= params.merge_dist
        joined = rest[(tr >= trace_min) & near]
        owner[joined] = k
        free[joined] = False
    width = int(q_points.shape[0]) + 1  # a pair's code: template keypoint * width + query keypoint
    for rep, ms in zip(merged, members, strict=True):
        rep.longest = max(len(m) for m in ms)
        if len(ms) > 1:
            m = np.concatenate(ms)
            _, first = np.unique(m[:, 0] * width + m[:, 1], return_index=True)  # (np.unique by rows is slower)
            m = m[np.sort(first)]  # the best list's pairs first, in order
            # pooled pairs off the representative's pose by more than twice the trim distance are left out
            r = np.linalg.norm(transform_points(rep.T, points_obj[m[:, 0]]) - q_points[m[:, 1]], axis=1)
            rep.matches = m[(r < 2 * params.trim_tau) | (np.arange(len(m)) < len(ms[0]))]
            rep.n = len(rep.matches)
    return merged
