"""Every instance of one or more templates in one frame (`Estimator.estimate_all`, `estimate_templates`).

A frame's features and retrieval are computed once (a later search reads its keypoints' rows of the retrieval
matrix in place, `Retrieval.rows`); the search of `Estimator.estimate` (stages 3-7) is then repeated on what the
instances found so far do not explain:

- a found pose explains the pixels whose point lies within `instances.explain_dist` of its surface, inside its
  silhouette (`explained_pixels`, grown by `instances.dilate_px`); their keypoints leave the next search's
  lists and retrieval votes, and their depth leaves its ICP target and its depth evidence (a pose there finds
  no depth to confirm it). Every pose returned passes the same verification as the single estimate's.
- a rival of an accepted pose (stage 7) that is accepted on pixels of its own, and whose centre lies farther
  than the object's thinnest extent from the accepted one's (two poses closer than that interpenetrate), is
  another instance, left to the next search; a rival on the same pixels (more than `instances.max_overlap` of
  the smaller's in common: a twin face, a symmetric view) is weighed as in the single estimate, and a tie
  still refuses the pose.
- a pose that shares more than `max_overlap` of its pixels with an instance already found, or lies closer
  than the thinnest extent to one, is a duplicate: never returned.
- a refused search is tried again `instances.retries` times in a row, the keypoints of the lists it refused
  left out (another instance may lie beyond them); the search stops after that (the last refusal is the
  list's reason when nothing was found), or after `instances.max_instances` instances. Instances are returned
  best score first (depth agreement, then keypoint support).

The single estimate runs one such search after it accepts a pose (`elsewhere`): a second place accepted there
refuses the view as ambiguous (one pose cannot say which of two objects the template fits is meant).

Several templates (`estimate_templates`): the frame's search region and features are shared by the templates
that read the frame alike (the same descriptor kind and keypoint settings, no camera correction of their own);
where two templates' instances claim the same pixels (more than `max_overlap` of the smaller's), the one with
more supporting keypoints keeps them and the other is refused there, with that reason.
"""
from __future__ import annotations

import logging
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
from scipy.spatial import cKDTree

from gscan.estimate.hypotheses import Matcher, MatchList, QueryKeypoints, hypothesise, prescore, query_keypoints
from gscan.estimate.model import ObjectModel
from gscan.estimate.params import EstimateParams
from gscan.estimate.pnp import pnp_without_depth
from gscan.estimate.query import QueryDepth, QueryFrame, query_features
from gscan.estimate.result import STAGES, EstimateResult, matrix_json, ms_since, not_found
from gscan.estimate.retrieval import Retrieval, TemplateIndex
from gscan.estimate.rivals import AMBIGUOUS, ListVerifier
from gscan.estimate.verify import support_radius, visible
from gscan.features import Features
from gscan.geometry.grid_kernel import NearestGrid
from gscan.geometry.transforms import transform_points
from gscan.io.camera import Intrinsics, RGBDFrame
from gscan.progress import StageTimer


class Searcher(Protocol):
    """What the instance search uses of `gscan.estimate.estimator.Estimator` (which calls it: this module does not
    import it)."""

    name: str
    params: EstimateParams
    index: TemplateIndex
    model: ObjectModel
    verifier: ListVerifier
    matcher: Matcher
    camera_fix: tuple[Intrinsics, Intrinsics] | None
    query_depth: QueryDepth | None

    def prepare(self, frame: RGBDFrame, mask: np.ndarray | None = None) -> QueryFrame: ...

    def limit_threads(self) -> AbstractContextManager[None]: ...

    def estimate(self, frame: RGBDFrame, mask: np.ndarray | None = None, refine: bool = True,
                 near: np.ndarray | None = None) -> EstimateResult: ...

    def result(self, res: EstimateResult, timer: StageTimer, t0: float,
               near: np.ndarray | None = None) -> EstimateResult: ...

log = logging.getLogger(__name__)


@dataclass
class Instances:
    """Every instance of one template found in a frame. results: found poses (`EstimateResult`, `pixels` set),
    best score first; reason: why no instance was found (None when some were); stopped: why the search
    stopped (the last search's refusal, or the cap); refused: the poses found and then
    given to another template claiming their pixels (not found, each with its reason); timings_ms: the frame's
    stages in milliseconds for this template (`STAGES`)."""

    template: str
    results: list[EstimateResult]
    reason: str | None = None
    stopped: str | None = None
    refused: list[EstimateResult] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict:
        """The `gscan estimate --all --json` object of one template: "template", "instances" (each one as the
        single estimate's object, plus "pixels": their count and box [x0, y0, x1, y1]), "reason", "refused"
        (the same objects, T_cam_obj null, the reason given), "stopped" and "timings_ms"."""
        return {"template": self.template, "instances": [instance_json(r) for r in self.results],
                "reason": self.reason, "stopped": self.stopped, "refused": [instance_json(r) for r in self.refused],
                "timings_ms": {k: float(self.timings_ms.get(k, 0.0)) for k in STAGES}}


def instance_json(res: EstimateResult) -> dict:
    """`res.to_json()` plus "pixels": {"count", "box" [x0, y0, x1, y1] or null} of the pixels it explains."""
    out = res.to_json()
    pix = res.pixels
    if pix is None or not pix.any():
        out["pixels"] = {"count": 0, "box": None}
    else:
        rows, cols = np.flatnonzero(pix.any(axis=1)), np.flatnonzero(pix.any(axis=0))
        out["pixels"] = {"count": int(pix.sum()), "box": [int(cols[0]), int(rows[0]), int(cols[-1]) + 1,
                                                          int(rows[-1]) + 1]}
    if res.T_cam_obj is None:
        out["T_cam_obj"] = matrix_json(None)
    return out


def thinnest_extent(samples: np.ndarray) -> float:
    """The object's extent (m) along its thinnest principal axis (samples [S x 3]): two poses whose centres lie
    closer than this make the object interpenetrate itself."""
    c = samples - samples.mean(axis=0)
    _, vecs = np.linalg.eigh(c.T @ c)
    return float(np.ptp(c @ vecs[:, 0]))


def explained_pixels(q: QueryFrame, samples: np.ndarray, T_cam_obj: np.ndarray, dist: float,
                     dilate_px: int) -> np.ndarray:
    """[H x W] bool the pixels a pose explains: inside the convex silhouette of the template surface samples
    [S x 3] visible at T_cam_obj [4 x 4], with a point within `dist` (m) of those samples; decided on every
    second pixel of every second row (each standing for its 2 x 2 block) and grown by dilate_px. Computed in
    the silhouette's bounding box (from even pixel coordinates, grown by dilate_px): the same pixels as over
    the whole frame."""
    H, W = q.frame.depth.shape
    out = np.zeros((H, W), bool)
    _, pc, uv = visible(T_cam_obj, q.frame.intrinsics, samples)
    if len(uv) < 3:
        return out
    hull = cv2.convexHull(uv.astype(np.int32))
    x0, y0 = (int(hull[..., 0].min()) - dilate_px) // 2 * 2, (int(hull[..., 1].min()) - dilate_px) // 2 * 2
    x0, y0 = max(0, x0), max(0, y0)
    x1, y1 = min(W, int(hull[..., 0].max()) + 2 + dilate_px), min(H, int(hull[..., 1].max()) + 2 + dilate_px)
    sil = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(sil, hull - np.array([x0, y0], np.int32), 1)
    box = (slice(y0, y1), slice(x0, x1))
    ys, xs = np.nonzero(sil[::2, ::2].astype(bool) & (q.frame.depth[box][::2, ::2] > 0))
    if len(ys) == 0:
        return out
    pts = q.cloud[y0 + 2 * ys, x0 + 2 * xs].astype(np.float64)
    grid = NearestGrid.build(pc, dist)  # the pairs of a kd-tree with distance_upper_bound, without its build
    if grid is not None:
        ok, _ = grid.query(pts)
    else:
        d, _ = cKDTree(pc, balanced_tree=False, compact_nodes=False).query(pts, distance_upper_bound=dist)
        ok = np.isfinite(d)
    h, w = y1 - y0, x1 - x0
    half = np.zeros(((h + 1) // 2, (w + 1) // 2), bool)
    half[ys[ok], xs[ok]] = True
    crop = np.repeat(np.repeat(half, 2, axis=0), 2, axis=1)[:h, :w]
    if dilate_px > 0:
        k = 2 * dilate_px + 1
        crop = cv2.dilate(crop.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    out[box] = crop
    return out


def without(q: QueryFrame, removed: np.ndarray) -> QueryFrame:
    """The query frame with the pixels `removed` ([H x W] bool) taken out: no depth, no point, not in the
    search region or off the plane (the support plane and the caller's mask otherwise kept)."""
    f = q.frame
    depth = f.depth.copy()
    depth[removed] = 0
    cloud = q.cloud.copy()
    cloud.reshape(-1, 3)[np.flatnonzero(removed)] = 0.0  # (by pixel index: a boolean mask over 3 channels is slower)
    mask = None if q.mask is None else q.mask & ~removed
    off = None if q.off_plane is None else q.off_plane & ~removed
    return QueryFrame(RGBDFrame(f.name, f.color, depth, f.intrinsics, f.mask), mask, q.depth_frac, q.plane, off,
                      _cloud=cloud, _heights=q.heights)


def keypoint_cells(feats: Features, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(rows [N], columns [N]) of the pixel each keypoint of feats lies on, in an image of `shape` (H, W, ...)."""
    H, W = shape[:2]
    return (np.clip(np.rint(feats.pixels[:, 1]).astype(np.int64), 0, H - 1),
            np.clip(np.rint(feats.pixels[:, 0]).astype(np.int64), 0, W - 1))


def agreeing(est: Searcher, r: Retrieval) -> np.ndarray:
    """[M] bool the query keypoints whose nearest template descriptor agrees (`verifier.support_sim`)."""
    return (r.best if est.index.unit else -r.best) >= est.verifier.support_sim


def subset(feats: Features, keep: np.ndarray) -> Features:
    """The keypoints `keep` ([N] bool) of `feats`."""
    return Features(feats.pixels[keep], feats.points[keep], feats.descriptors[keep], feats.kind,
                    None if feats.scales is None else feats.scales[keep])


class InstanceSearch:
    """The repeated search of one template in one prepared frame (module docstring)."""

    def __init__(self, est: Searcher, q: QueryFrame, feats: Features, refine: bool,
                 explained: np.ndarray | None = None, max_instances: int | None = None):
        self.est, self.q, self.feats, self.refine = est, q, feats, refine
        self.p = est.params.instances
        self.explained = explained  # [H x W] bool pixels already explained (the tracker's held instances)
        self.cap = self.p.max_instances if max_instances is None else max_instances
        self.thin = thinnest_extent(est.model.samples)
        self.timer = StageTimer()
        # the pixels computed in the frame last asked about, per pose (T_cam_obj's bytes): a pose weighed against
        # several rivals (`separate`), or weighed and then found, asks for the same ones
        self._pixels_q: QueryFrame | None = None
        self._pixels: dict[bytes, np.ndarray] = {}

    def pixels(self, q: QueryFrame, T_cam_obj: np.ndarray) -> np.ndarray:
        """[H x W] bool the pixels the pose explains in q (`explained_pixels`; read only: shared by the calls
        with the same q and pose)."""
        if q is not self._pixels_q:
            self._pixels_q, self._pixels = q, {}
        key = np.ascontiguousarray(T_cam_obj, dtype=np.float64).tobytes()
        pix = self._pixels.get(key)
        if pix is None:
            pix = explained_pixels(q, self.est.model.samples, T_cam_obj, self.p.explain_dist, self.p.dilate_px)
            pix.flags.writeable = False
            self._pixels[key] = pix
        return pix

    def same(self, T_a: np.ndarray, pix_a: np.ndarray, T_b: np.ndarray, pix_b: np.ndarray) -> bool:
        """Two poses are one instance: centres closer than the thinnest extent, or more than `max_overlap` of the
        smaller one's pixels in common."""
        c = self.est.model.center[None]
        if np.linalg.norm(transform_points(T_a, c)[0] - transform_points(T_b, c)[0]) < self.thin:
            return True
        return overlapping(pix_a, pix_b, self.p.max_overlap)

    def run(self) -> Instances:
        """The instances found (not yet completed by `Estimator.result`: poses as verified). Each search first
        verifies the previous search's lists on the keypoints left (pre-scored again: another instance's lists
        are often there already), and matches afresh only when none of them is accepted."""
        est, p = self.est, self.est.params
        found: list[EstimateResult] = []
        shape = self.q.frame.depth.shape[:2]
        removed = np.zeros(shape, bool) if self.explained is None else self.explained.copy()
        with self.timer.stage("retrieval"):
            r_all = est.index.retrieve(self.feats.descriptors)
        agree = agreeing(est, r_all)
        v, u = keypoint_cells(self.feats, shape)
        reason: str | None = f"the cap of {self.cap} instances reached"
        prev: tuple[list[MatchList], np.ndarray] | None = None  # the last search's lists, its keypoints' ids
        dropped = np.zeros(len(self.feats), bool)  # keypoints of refused lists
        refusals = 0  # refusals in a row
        for _ in range(2 * self.cap + self.p.retries):  # (an instance, an ambiguous one, a refusal)
            if len(found) >= self.cap:
                break
            keep = ~removed[v, u] & ~dropped
            if int((keep & agree).sum()) < p.accept.min_matches:
                reason = "too few keypoints left that agree with the template"
                break
            q = without(self.q, removed) if removed.any() else self.q
            ids = np.flatnonzero(keep)
            if len(ids) == len(keep):
                feats, r = self.feats, r_all
            else:
                feats = subset(self.feats, keep)
                with self.timer.stage("retrieval"):
                    r = est.index.subset(r_all, keep)
            qk = query_keypoints(feats, r.S, r.rows)
            tie: list[EstimateResult] = []

            def separate(res: EstimateResult, alt: EstimateResult, q: QueryFrame = q,
                         tie: list[EstimateResult] = tie) -> bool:
                assert res.T_cam_obj is not None and alt.T_cam_obj is not None
                a, b = self.pixels(q, res.T_cam_obj), self.pixels(q, alt.T_cam_obj)
                apart = not self.same(res.T_cam_obj, a, alt.T_cam_obj, b)
                if not apart:  # weighed against each other next: a tie refuses this pose
                    tie[:] = [res]
                return apart

            res = None
            if prev is not None:
                with self.timer.stage("match"):
                    lists = carried(prev[0], prev[1], ids, est, qk, r)
                res = est.verifier.verify_lists(q, qk, lists, self.refine, self.timer, separate) if lists else None
                if res is not None and res.T_cam_obj is None:
                    res, tie[:] = None, []
            if res is None:
                with self.timer.stage("match"):
                    lists = hypothesise(est.index, qk, r, est.matcher, p.gmatch.order, p.hypotheses,
                                        est.verifier.support_sim, p.verify.support_radius)
                res = est.verifier.verify_lists(q, qk, lists, self.refine, self.timer, separate)
            prev = (lists, ids)
            log.debug("search (%d keypoints left, %d lists): %s", len(ids), len(lists),
                      res.reason or f"found, score {res.score:.3f}")
            if res.T_cam_obj is None:
                reason = res.reason
                if (reason or "").startswith(AMBIGUOUS) and tie and tie[0].T_cam_obj is not None:
                    removed |= self.pixels(self.q, tie[0].T_cam_obj)  # no pose there, but others may lie beyond
                    continue
                refusals += 1
                tried = [c for c in lists if c.n >= p.accept.min_matches][: max(1, p.verify.lists)]
                if refusals > self.p.retries or not tried:
                    break
                # the refused lists' keypoints leave the next search (their pixels may hold another instance)
                dropped[ids[np.concatenate([c.matches[:, 1] for c in tried])]] = True
                prev = None
                continue
            refusals = 0
            pix = self.pixels(self.q, res.T_cam_obj).copy()  # the caller's to keep
            res.pixels = pix
            if any(self.same(res.T_cam_obj, pix, f.T_cam_obj, f.pixels) for f in found
                   if f.T_cam_obj is not None and f.pixels is not None):
                log.debug("a pose on an instance already found: not returned")
            else:
                found.append(res)
            if not (pix & ~removed).any():
                reason = "the last pose explains no pixel left"
                break
            removed |= pix
        found.sort(key=lambda r: (-r.score, -(r.evidence.support if r.evidence is not None else 0)))
        return Instances(est.name, found, None if found else reason, reason)


def elsewhere(est: Searcher, q: QueryFrame, feats: Features, r: Retrieval, res: EstimateResult, refine: bool,
              timer: StageTimer) -> EstimateResult:
    """The single estimate's accepted `res` (3D-3D), or the ambiguous view's not-found result when another place
    of the frame fits the template too (`rivals.elsewhere`): a second copy, or a look-alike whose faces in view
    carry the object's print (a pose of either passes every check; one pose cannot say which object is meant).

    The search is `estimate_all`'s next one: the keypoints and depth outside the pixels `res` explains, matched
    and verified as the first search was (not weighed against rivals: two poses tying there still put
    something the template fits there); then, when nothing is accepted there, 2D-3D PnP on
    the depth's holes outside those pixels (`pnp_without_depth`: an object in a stereo shadow; its pose refused
    when it sinks into the support plane, as the single estimate's is). A pose found there
    whose centre lies within the object's thinnest extent of the accepted one's is the same place; so is a pose
    of the depth search that shares more than `instances.max_overlap` of its pixels with it (PnP is then tried; a
    PnP pose in a hole explains few pixels of depth, so only its centre is compared). The depth search runs only
    when the keypoints left that agree with the template could carry an accepted pose (`could_hold`): a pose needs
    `accept.min_matches` inliers and, short of `accept.strong_matches` of them, `accept.min_support` supporting
    keypoints, all on one object (an inlier's descriptor agrees unless `verify.support_dist` is set below
    GMatch's eps_f). feats, r: the frame's keypoints and their retrieval; timer: the estimate's stages."""
    p = est.params
    if not p.rivals.elsewhere or res.T_cam_obj is None:
        return res
    T = res.T_cam_obj
    pix = explained_pixels(q, est.model.samples, T, p.instances.explain_dist, p.instances.dilate_px)
    keep = ~pix[keypoint_cells(feats, pix.shape)]
    inliers_agree = p.verify.support_dist is None or p.verify.support_dist >= est.index.eps_f
    need = min(p.accept.min_support, p.accept.strong_matches) if inliers_agree else p.accept.min_matches
    alt: EstimateResult | None = None
    if could_hold(feats.points[keep & agreeing(est, r)], max(need, p.accept.min_matches),
                  2.0 * (est.model.radius + support_radius(p.verify, float(feats.points[:, 2].max(initial=0.0))))):
        q_out = without(q, pix)
        with timer.stage("retrieval"):
            r_out = est.index.subset(r, keep)
        qk = query_keypoints(subset(feats, keep), r_out.S, r_out.rows)
        with timer.stage("match"):
            lists = hypothesise(est.index, qk, r_out, est.matcher, p.gmatch.order, p.hypotheses,
                                est.verifier.support_sim, p.verify.support_radius)
        # the first of the `verify.lists` best lists accepted, not weighed against its rivals: a place where
        # two poses tie still holds something the template fits
        alt = next((a for c in [c for c in lists if c.n >= p.accept.min_matches][: max(1, p.verify.lists)]
                    if (a := est.verifier.verify_list(q_out, qk, c, refine, timer, best=c is lists[0],
                                                      explain=False)).found),
                   not_found("none"))
        if alt.T_cam_obj is not None and overlapping(
                pix, explained_pixels(q, est.model.samples, alt.T_cam_obj, p.instances.explain_dist,
                                      p.instances.dilate_px), p.instances.max_overlap):
            alt = None
    if alt is None or alt.T_cam_obj is None:
        alt = pnp_without_depth(est.index, est.model.samples, q, not_found("none"), p, timer, exclude=pix)
        if alt.T_cam_obj is not None and est.verifier.sinks(q, alt.T_cam_obj) is not None:
            return res  # refused as the single estimate's 2D-3D pose is (`Estimator._above`)
    if alt.T_cam_obj is None:
        return res
    centre = transform_points(T, est.model.center[None])[0]
    other = transform_points(alt.T_cam_obj, est.model.center[None])[0]
    if np.linalg.norm(other - centre) < thinnest_extent(est.model.samples):
        return res
    how = (f"{alt.evidence.support} keypoints agree with it" if alt.method == "gmatch" and alt.evidence is not None
           else f"{alt.n_matches} 2D-3D matches agree with it where the depth has a hole")
    here = ", ".join(f"{x:.2f}" for x in centre)
    there = ", ".join(f"{x:.2f}" for x in other)
    log.info("a second place fits the template: (%s) and (%s) m", here, there)
    return not_found(f"{AMBIGUOUS}: two places in the frame fit the template, centred at ({here}) m and at ({there}) "
                     f"m in the camera frame ({res.evidence.support if res.evidence else 0} keypoints agree with the "
                     f"first; {how}): a second copy, or a look-alike printed alike on the faces in view; a mask "
                     f"on one of them picks it", res.n_matches, res.view, res.score,
                     evidence=res.evidence)


def could_hold(points: np.ndarray, need: int, span: float) -> bool:
    """Whether `need` of the keypoints points [K x 3] (camera frame) lie within `span` (m) of one of them: the
    keypoints supporting one pose lie on one object, within its diameter plus the support radius of each other
    (a cheap necessary condition for a pose there)."""
    if len(points) < need:
        return False
    tree = cKDTree(np.asarray(points, dtype=np.float64))
    counts = tree.query_ball_point(tree.data, span, return_length=True)
    return bool(np.max(counts) >= need)


def carried(lists: list[MatchList], ids: np.ndarray, now: np.ndarray, est: Searcher, qk: QueryKeypoints,
            r: Retrieval) -> list[MatchList]:
    """The match lists of a previous search on the keypoints left: each list's pairs whose query keypoint
    (ids [M]: the previous search's keypoints' ids) is still there (now [M']: this search's ids), lists of at
    least `accept.min_matches` pairs, pre-scored again on this search's keypoints (qk, r), best first."""
    local = np.full(int(max(ids.max(initial=-1), now.max(initial=-1))) + 1, -1, np.int64)
    local[now] = np.arange(len(now))
    out: list[MatchList] = []
    for c in lists:
        q_new = local[ids[c.matches[:, 1]]]
        ok = q_new >= 0
        n = int(ok.sum())
        if n >= est.params.accept.min_matches:
            m = np.stack([c.matches[ok, 0], q_new[ok]], 1)
            out.append(MatchList(n, c.cost, c.view, m, longest=min(c.longest, n)))
    prescore(out, est.index, qk.feats, r, est.verifier.support_sim, est.params.verify.support_radius)
    return sorted(out, key=lambda c: (-c.support, -c.n, c.cost))


def overlapping(pix_a: np.ndarray, pix_b: np.ndarray, max_overlap: float) -> bool:
    """More than max_overlap of the smaller pixel set ([H x W] bool each) lies in the other."""
    n = min(int(pix_a.sum()), int(pix_b.sum()))
    return n > 0 and int((pix_a & pix_b).sum()) > max_overlap * n


def estimate_all(est: Searcher, frame: RGBDFrame, mask: np.ndarray | None = None, refine: bool = True,
                 shared: tuple[QueryFrame, Features] | None = None, explained: np.ndarray | None = None,
                 max_instances: int | None = None) -> Instances:
    """Every instance of `est`'s object in `frame` (module docstring); shared: the frame prepared and its
    features when another template already computed them (`estimate_templates`); explained: [H x W] bool pixels
    taken as explained before the first search (instances known otherwise: the tracker's); max_instances: the
    cap for this call (default `instances.max_instances`)."""
    t0 = time.perf_counter()
    timer = StageTimer()
    with est.limit_threads():
        if shared is None:
            q = est.prepare(frame, mask)
            use_depth = q.depth_frac >= est.params.query.min_depth_frac
            with timer.stage("features"):
                feats = query_features(q.frame, q.search, est.params.features, est.params.query,
                                       depth=est.query_depth) if use_depth else None
        else:
            q, feats = shared
        if feats is None:  # no usable depth: the single estimate's 2D-3D pose is the one instance it can give
            res = est.estimate(frame, mask, refine)
            out = Instances(est.name, [res] if res.found else [], None if res.found else res.reason)
            out.timings_ms = dict(res.timings_ms)
            return out
        if len(feats) < 3:
            where = "the query frame" + (" mask" if q.mask is not None else "")
            out = Instances(est.name, [], f"too few keypoints in {where}")
        else:
            search = InstanceSearch(est, q, feats, refine, explained, max_instances)
            out = search.run()
            for k, t in search.timer.timings.items():
                timer.timings[k] = timer.timings.get(k, 0.0) + t
        out.results = [est.result(r, timer, t0) for r in out.results]
    out.timings_ms = {k: 1e3 * timer.timings.get(k, 0.0) for k in STAGES if k != "total"}
    out.timings_ms["total"] = ms_since(t0)
    return out


def estimate_templates(estimators: list[Searcher], frame: RGBDFrame, mask: np.ndarray | None = None,
                       refine: bool = True) -> list[Instances]:
    """Every instance of every template in `frame` (module docstring), one `Instances` per estimator in order.
    The frame is prepared and its features computed once for the templates that read it alike."""
    cache: dict[tuple, tuple[QueryFrame, Features | None]] = {}
    outs: list[Instances] = []
    for est in estimators:
        key = (est.params.features, est.params.query, est.query_depth) if est.camera_fix is None else None
        shared = cache.get(key) if key is not None else None
        prepared_ms = 0.0
        if shared is None:
            t0 = time.perf_counter()
            with est.limit_threads():
                q = est.prepare(frame, mask)
                use_depth = q.depth_frac >= est.params.query.min_depth_frac
                feats = query_features(q.frame, q.search, est.params.features, est.params.query,
                                       depth=est.query_depth) if use_depth else None
            shared = (q, feats)
            if key is not None:
                cache[key] = shared
            prepared_ms = ms_since(t0)
        q, feats = shared
        out = estimate_all(est, frame, mask, refine, None if feats is None else (q, feats))
        if feats is not None:  # the frame's preparation and features counted where they were computed
            out.timings_ms["features"] += prepared_ms
            out.timings_ms["total"] += prepared_ms
        outs.append(out)
    resolve_claims(outs, [e.params.instances.max_overlap for e in estimators])
    return outs


def resolve_claims(outs: list[Instances], max_overlap: list[float]) -> None:
    """Instances of different templates claiming the same pixels (more than the smaller template's
    `max_overlap` of the smaller's in common): the one with more supporting keypoints (then the higher score)
    keeps them, the other moves to its template's `refused`, not found, with the reason."""
    entries = [(i, r) for i, o in enumerate(outs) for r in o.results]

    def strength(r: EstimateResult) -> tuple[int, float]:
        return (r.evidence.support if r.evidence is not None else 0, r.score)

    entries.sort(key=lambda e: strength(e[1]), reverse=True)
    kept: list[tuple[int, EstimateResult]] = []
    for i, r in entries:
        assert r.pixels is not None
        rival = next(((j, k) for j, k in kept if j != i and k.pixels is not None
                      and overlapping(r.pixels, k.pixels, min(max_overlap[i], max_overlap[j]))), None)
        if rival is None:
            kept.append((i, r))
            continue
        j, k = rival
        lost = not_found(f"its pixels are claimed by template {outs[j].template}, better supported "
                         f"({strength(k)[0]} keypoints agree, {strength(r)[0]} with this one)", r.n_matches, r.view,
                         r.score, r.method, r.evidence)
        lost.pixels = r.pixels
        outs[i].refused.append(lost)
    for i, o in enumerate(outs):
        o.results = [r for j, r in kept if j == i]
        o.results.sort(key=lambda r: (-r.score, -(r.evidence.support if r.evidence is not None else 0)))
        if not o.results and o.reason is None:
            o.reason = o.refused[0].reason if o.refused else "not found"
