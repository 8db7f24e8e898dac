"""Stage 2, retrieval: the template's keypoints indexed for the query (`TemplateIndex`).

The template's descriptors are stacked once ([N x D], unit RootSIFT vectors as float32); one GEMM of the
query descriptors against them gives the retrieval matrix S [M x N] (cosine similarity for unit descriptors,
else the descriptor distance). Every query keypoint whose nearest template descriptor is closer than
`retrieval.max_dist` votes for that descriptor's view. A view's neighbourhood is itself and the
`joint_views` - 1 views whose optical axes are nearest to its own, within `joint_deg`; the views with most
votes are taken as centres (a view inside a neighbourhood already taken is skipped), up to `top_k`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from gscan.estimate.params import RetrievalParams
from gscan.estimate.similarity import TemplateGroups
from gscan.features import descriptor_distances
from gscan.geometry.pointset import coincident_groups
from gscan.geometry.transforms import inv_T, transform_points
from gscan.matching.gmatch import default_eps_f
from gscan.template.db import Template

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Neighbourhood:
    """The views matched jointly around a central view v. views [K]: v first, then its nearest optical axes;
    idx [Nn]: their global template keypoint indices; points [Nn x 3]: those keypoints in v's camera frame;
    order [Nn], starts [G]: groups of coincident points (orientations of one location,
    gscan.geometry.pointset.coincident_groups); groups: the same for the similarity kernels."""

    views: np.ndarray = field(repr=False)
    idx: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)
    order: np.ndarray = field(repr=False)
    starts: np.ndarray = field(repr=False)
    groups: TemplateGroups = field(repr=False)


@dataclass(frozen=True)
class Retrieval:
    """The query against the index. S [M' x N]: similarity (unit descriptors) or distance of query keypoints to
    every template keypoint; votes [V]: query keypoints voting for each view; nn [M]: each query keypoint's
    nearest template keypoint (first on ties), best [M]: its value in S; rows [M]: each query keypoint's row in
    S (None: row i is keypoint i, M' = M). A subset of the keypoints (`TemplateIndex.subset`) reads its rows in
    its parent's S: the matrix is not copied."""

    S: np.ndarray = field(repr=False)
    votes: np.ndarray
    nn: np.ndarray = field(repr=False)
    best: np.ndarray = field(repr=False)
    rows: np.ndarray | None = field(default=None, repr=False)


class TemplateIndex:
    """The template's keypoints for retrieval and matching: descriptors [N x D] stacked (float32, uint8 for ORB),
    points_obj [N x 3] (object frame), kp_view [N] each keypoint's view, offsets [V + 1] (view v's keypoints:
    offsets[v]:offsets[v + 1]), T_obj_cam [V x 4 x 4] the views' poses, axes [V x 3] their optical axes (object
    frame), neighbourhoods [V] (`Neighbourhood`)."""

    def __init__(self, tpl: Template, eps_f: float | None, params: RetrievalParams):
        """eps_f: GMatch's descriptor threshold (None: the kind's default)."""
        assert tpl.kind is not None
        self.params = params
        self.kind: str = tpl.kind
        self.unit = self.kind == "rootsift"  # unit descriptors: S holds cosine similarities
        self.view_names = list(tpl.view_names)
        self.T_obj_cam = np.asarray(tpl.T_obj_cam, dtype=np.float64)
        self.points_obj = tpl.points_obj.astype(np.float64)
        self.descriptors = np.ascontiguousarray(tpl.descriptors, dtype=np.float32 if self.kind != "orb" else np.uint8)
        self.offsets = np.asarray(tpl.view_offsets, dtype=np.int64)
        self.kp_view = np.asarray(tpl.kp_view, dtype=np.int64)
        self.axes = self.T_obj_cam[:, :3, 2]
        self.eps_f = eps_f if eps_f is not None else default_eps_f(self.kind)
        cos = np.clip(self.axes @ self.axes.T, -1.0, 1.0)  # [V x V] between the views' optical axes
        self.neighbourhoods = [self._neighbourhood(v, cos[v]) for v in range(len(self.view_names))]
        log.debug("%d views, %d keypoints, neighbourhoods of %s views", len(self.view_names), len(self.points_obj),
                  [len(n.views) for n in self.neighbourhoods])

    def _neighbourhood(self, v: int, cos: np.ndarray) -> Neighbourhood:
        """View v and its nearest optical axes within joint_deg, at most joint_views in all (cos [V]: cosines
        of the angles between v's optical axis and every view's)."""
        V, p = len(self.view_names), self.params
        order = [u for u in np.lexsort((np.arange(V), -cos)) if u != v]
        near = [int(u) for u in order if cos[u] >= np.cos(np.radians(p.joint_deg))]
        nb = [v] + near[: max(0, p.joint_views - 1)]
        idx = np.concatenate([self.view_keypoints(u) for u in nb]).astype(np.int64)
        order_g, starts = coincident_groups(self.points_obj[idx])
        return Neighbourhood(np.asarray(nb, np.int64), idx, transform_points(inv_T(self.T_obj_cam[v]),
                             self.points_obj[idx]), order_g, starts, TemplateGroups(idx, order_g, starts))

    def view_keypoints(self, v: int) -> np.ndarray:
        """[Nv] global indices of view v's keypoints."""
        return np.arange(self.offsets[v], self.offsets[v + 1])

    def similarity(self, q_desc: np.ndarray) -> np.ndarray:
        """Query descriptors [M x D] -> S [M x N] (cosine similarity for unit descriptors, else distance)."""
        if self.unit:
            return np.matmul(q_desc.astype(np.float32), self.descriptors.T)
        return descriptor_distances(q_desc, self.descriptors, self.kind)

    def retrieve(self, q_desc: np.ndarray) -> Retrieval:
        """Query descriptors [M x D] -> the retrieval matrix, the view votes and each keypoint's nearest."""
        S = self.similarity(q_desc)
        nn, best = self.nearest(S)
        return Retrieval(S, self.votes(nn, best), nn, best)

    def votes(self, nn: np.ndarray, best: np.ndarray) -> np.ndarray:
        """[V] each view's votes: a query keypoint votes for the view holding its nearest template descriptor nn [M]
        when that one is close enough (best [M]: its value in S)."""
        ok = best >= 1.0 - 0.5 * self.params.max_dist ** 2 if self.unit else best < self.eps_f
        return np.bincount(self.kp_view[nn[ok]], minlength=len(self.view_names))

    def subset(self, r: Retrieval, keep: np.ndarray) -> Retrieval:
        """`r` of the query keypoints `keep` ([M] bool or indices) only, its votes counted again; the same S,
        their rows in it mapped (`Retrieval.rows`)."""
        nn, best = r.nn[keep], r.best[keep]
        rows = np.arange(len(r.nn))[keep] if r.rows is None else r.rows[keep]
        return Retrieval(r.S, self.votes(nn, best), nn, best, rows.astype(np.int64))

    def nearest(self, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each row's nearest template keypoint in S [M x N] (first on ties) and its value: ([M], [M])."""
        nn = np.argmax(S, axis=1) if self.unit else np.argmin(S, axis=1)
        return nn, S[np.arange(len(S)), nn]

    def distances(self, S: np.ndarray) -> np.ndarray:
        """A block of S -> L2 (unit descriptors) or Hamming distances."""
        if self.unit:
            return np.sqrt(np.maximum(2.0 - 2.0 * S, 0.0))
        return S

    def top_views(self, votes: np.ndarray) -> list[int]:
        """The top_k views by votes [V] (ties by view order), views without a vote left out."""
        order = np.lexsort((np.arange(len(votes)), -votes))
        return [int(v) for v in order[: self.params.top_k] if votes[v] > 0]

    def top_neighbourhoods(self, votes: np.ndarray, count: int | None = None) -> list[int]:
        """Central views of the neighbourhoods to match: views by their own votes [V] (ties by view order), each
        taken unless a neighbourhood already taken holds it, up to `count` (default top_k); views without a vote
        are left out. Clutter spreads votes over many views: taking a view's neighbours with it leaves room for a
        view of another side of the object."""
        count = self.params.top_k if count is None else count
        chosen: list[int] = []
        covered: set[int] = set()
        for v in np.lexsort((np.arange(len(votes)), -votes)):
            if votes[v] <= 0 or len(chosen) >= count:
                break
            if int(v) not in covered:
                chosen.append(int(v))
                covered.update(int(u) for u in self.neighbourhoods[v].views)
        return chosen

    def offered_keypoints(self, T_cam_obj: np.ndarray, max_deg: float) -> np.ndarray:
        """Global indices of the keypoints of the views within max_deg of the query camera's optical axis at the
        pose T_cam_obj (the nearest view when none is)."""
        axis = T_cam_obj[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the query camera's axis in the object frame
        views = np.flatnonzero(self.axes @ axis >= np.cos(np.radians(max_deg)))
        if len(views) == 0:
            views = np.array([int(np.argmax(self.axes @ axis))])
        return np.concatenate([self.view_keypoints(int(v)) for v in views]).astype(np.int64)
