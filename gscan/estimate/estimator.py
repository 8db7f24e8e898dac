"""Pose of a templated object in a new RGB-D frame (`gscan estimate`).

Pipeline of `Estimator.estimate`, a façade over the stages' modules (every stage timed by a
`gscan.progress.StageTimer`, `EstimateResult.timings_ms`); the frame's full-image work (back-projection, the
support-plane fit, the search region) is done once (`gscan.estimate.query`):

1. features: RootSIFT keypoints of the query, lifted with the query depth into the camera frame, inside `mask` when
   given; without a mask inside the pixels standing off the dominant plane (the table top, whose texture would
   otherwise take most of the keypoints), or the whole frame when there is no such plane. Detection runs on the
   bounding boxes of the search region's blobs only (`gscan.estimate.query`).
2. retrieval (`gscan.estimate.retrieval.TemplateIndex`): one GEMM of the query descriptors against the template's
   stacked descriptors (normalised once at load); every query keypoint whose nearest template descriptor is closer
   than `retrieval.max_dist` votes for that descriptor's view. A view's neighbourhood is itself and the
   `retrieval.joint_views` - 1 views whose optical axes are nearest to its own, within `retrieval.joint_deg`; the
   views with most votes are taken as centres (a view inside a neighbourhood already taken is skipped), up to
   `retrieval.top_k`. When no list of these gives an accepted pose (and the view is not ambiguous), the next
   `top_k` neighbourhoods by votes are matched, solved and verified (stages 3-7, under the short lists' rule:
   `retrieval.next_round`): the clutter's keypoints vote too, and a sparsely printed object's right views can
   rank below the views they vote for.
3. match (`gscan.estimate.hypotheses`): GMatch (gscan.matching.gmatch) of each retrieved neighbourhood's keypoints
   jointly, all expressed in its central view's camera frame (view direction +z), against the query keypoints (+z): a
   pose between keyframes, or a face the scan saw from a steeper angle than the query, collects its matches from
   several views at once. GMatch's candidates are read from the retrieval GEMM's matrix by one kernel pass per
   neighbourhood (`gscan.estimate.similarity`), never recomputed or copied into a distance block.
4. solve: every neighbourhood's best list and its GMatch runners-up (at most `hypotheses.runner_up_margin` shorter: in
   clutter a hard view's correct list ties with the lists the background offers) are posed at once (batched Kabsch)
   and pre-scored by the query keypoints their nearest template descriptor lands on at that pose; lists whose poses
   agree are pooled; the best pre-scored list's pose is solved by Kabsch with gross outliers trimmed
   (`kabsch_trimmed`, object-frame template points -> query camera points).
5. refine (`gscan.estimate.rivals` runs stages 5-7 on each list): point-to-plane ICP (`gscan.estimate.refine`,
   template normals, the match list as weak anchors) of the template cloud's points visible from the predicted pose
   onto the query cloud cropped to a sphere of `refine.crop_radii` (1.2) object radii around the predicted centre and,
   without a mask, to the off-plane pixels. A given mask does not crop it: ICP pairs the template's whole visible
   surface with the query, and a mask that clips the silhouette (eroded, or cut by an occluder) would pull the pose
   toward the cut. A refinement that moves the pose by more than the object radius or `refine.max_turn_deg` (30)
   degrees is discarded.
6. verify (`gscan.estimate.verify`): the pose is accepted from the evidence (depth agreement, keypoint support
   relative to what the frame and the template show there, the list's geometry), never from the list length alone, and
   refused when it sinks the object into the support plane. When the best list's pose is refused, the next
   `verify.lists` - 1 lists are tried, under the short lists' stricter rule.
7. rivals: a box printed alike on two faces fits a pose turned onto its twin face as well as the right one, in shape
   and in most keypoints. The next `rivals.lists` lists whose pre-score support reaches `rivals.min_support` of the
   accepted list's, and whose poses lie beyond the refinement's reach of the accepted pose (a list within it is the
   same pose sharpened), are solved, refined and verified too. A rival accepted at another pose is compared with the
   accepted pose on the query keypoints that support one pose and not the other (a sign test at level `rivals.p`): the
   pose they significantly favour is returned; when neither is favoured the view is ambiguous and no pose is returned
   (nor sought by PnP in the depth's holes). Poses are compared up to the template's symmetries that hold in shape
   and texture: a rival that differs from the accepted pose by one is the same answer (`gscan.estimate.symmetric`).
   Then the frame outside the accepted pose is searched as `estimate_all`'s next search would
   (`gscan.estimate.instances.elsewhere`, `rivals.elsewhere`): a pose accepted at another place (a second copy,
   or a look-alike printed alike on the faces in view) makes the view ambiguous, the reason naming both places.
8. symmetry: for such an object the returned pose is the equivalent a fixed rule picks (the one whose rotation lies
   nearest the object's +z up in the image, +x to the right; `gscan.estimate.symmetric`), the same for every
   equivalent the hypotheses found, marked `EstimateResult.symmetry`; with `near` (the tracker's previous pose), the
   equivalent nearest it. Each grasp is offered in every equivalent (`grasp_equivalents`, a continuous axis sampled
   every `symmetry.grasp_step_deg`).

A frame that comes with the intrinsics the template's scan found its capture's colour camera not to have
(gscan.scanning.calibration) is first read as the scan read the capture (`as_scanned`).

Without usable query depth (valid fraction of the search region < `query.min_depth_frac`) the pose is solved 2D-3D
(`gscan.estimate.pnp`), and the same 2D-3D solve is tried after a failed 3D-3D estimate on the search region's holes
in the depth (a dark, shiny or transparent object leaves a hole in otherwise good depth).

Settings: `EstimateParams` (gscan.estimate.params), a section per stage, read from a configuration file's `estimate:`
section by `gscan.estimate.settings.load_estimate_params`.

The estimator limits BLAS (threadpoolctl) and OpenCV to one thread each (`threads`) while it runs: its matrices and
detection boxes are small, and a thread pool spinning up per call costs more CPU than it saves.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np

from gscan.estimate.hypotheses import GMatchLists, Matcher, QueryKeypoints, hypothesise, query_keypoints
from gscan.estimate.instances import Instances, elsewhere, estimate_all
from gscan.estimate.model import ObjectModel
from gscan.estimate.params import DEFAULT_PARAMS, EstimateParams
from gscan.estimate.pnp import estimate_pnp, pnp_without_depth
from gscan.estimate.query import QueryDepth, QueryFrame, backproject32, prepare_query, query_features
from gscan.estimate.refine import normal_equations
from gscan.estimate.result import STAGES, EstimateResult, not_found, timed
from gscan.estimate.retrieval import Retrieval, TemplateIndex
from gscan.estimate.rivals import AMBIGUOUS, ListVerifier
from gscan.estimate.similarity import TemplateGroups, best_columns, neighbourhood_candidates
from gscan.estimate.texture import KeyframeTextures
from gscan.features import descriptor_distances
from gscan.features.keypoints import JOINT
from gscan.geometry.grid_kernel import NearestGrid
from gscan.geometry.kabsch import kabsch_trimmed
from gscan.geometry.plane import ransac_plane
from gscan.geometry.pointset import coincident_groups
from gscan.io.align import align_depth_to_color
from gscan.io.camera import DepthCamera, Intrinsics, RGBDFrame, lift_keypoints
from gscan.matching.gmatch import search_candidates
from gscan.progress import StageTimer
from gscan.registration.noise import DepthNoise
from gscan.template.db import Template, open_template

log = logging.getLogger(__name__)

__all__ = ["STAGES", "EstimateParams", "EstimateResult", "Estimator", "Instances"]


class Estimator:
    """A template loaded once for repeated pose estimation (`from_path`, then `estimate`). Its parts: `index`
    (the template's keypoints, retrieval), `model` (the object's surface), `verifier` (stages 4-7 on the match
    lists), `matcher` (stage 3, GMatch by default)."""

    def __init__(self, tpl: Template, params: EstimateParams = DEFAULT_PARAMS, matcher: Matcher | None = None):
        """tpl: a loaded template (TemplateDB.load_template: object keypoints in the object frame); matcher: the
        match lists of a view neighbourhood (default: `GMatchLists`, benchmarks put a baseline in its place)."""
        kind = tpl.require_keypoints()
        if kind == JOINT and not params.query.depth_keypoints:  # the template's image keypoints alone
            tpl = tpl.image_keypoints()
            kind = tpl.require_keypoints()
        image_kind = "rootsift" if kind == JOINT else kind  # a joint set's image keypoints are RootSIFT
        if image_kind != params.features.kind:
            params = replace(params, features=replace(params.features, kind=image_kind))
        self.params = params
        self.path = tpl.path
        self.name = Path(tpl.path).stem if tpl.path is not None else "template"
        self.kind = kind
        self.index = TemplateIndex(tpl, params.gmatch.eps_f, params.retrieval)
        self.model = ObjectModel.from_template(tpl, params.refine.voxel)
        self.verifier = ListVerifier(self.index, self.model, params)
        self.matcher: Matcher = matcher or GMatchLists(params.gmatch, params.accept.min_matches,
                                                       params.hypotheses.runner_up_margin)
        self.view_names = self.index.view_names
        self.query_depth = query_depth(tpl)
        if self.query_depth is not None:  # poses the depth alone decides meet the keyframes' texture (verifier)
            self.verifier.keyframes = KeyframeTextures(tpl.path, self.view_names, self.index.T_obj_cam,
                                                      params.accept.max_chroma_shift)
            self.verifier.depth_noise = self.query_depth.noise
        self.model_points = self.model.model_points  # for metrics: mesh vertices, else the cloud
        # the scan found the capture's depth off its colour at the given intrinsics (gscan.scanning.calibration): a
        # frame read with those same intrinsics is read as the scan read the capture
        cam = tpl.meta.get("camera") if isinstance(tpl.meta, dict) else None
        self.camera_fix: tuple[Intrinsics, Intrinsics] | None = None  # (given, the colour camera's)
        if isinstance(cam, dict) and cam.get("corrected"):
            given, colour = cam["given_intrinsics"], cam["colour_intrinsics"]
            self.camera_fix = Intrinsics.from_dict(given), Intrinsics.from_dict(colour)
        self._blas = None
        if params.threads.blas is not None:
            from threadpoolctl import ThreadpoolController

            self._blas = ThreadpoolController()
        self._warm_up()

    @classmethod
    def from_path(cls, path: str | Path, params: EstimateParams = DEFAULT_PARAMS,
                  matcher: Matcher | None = None) -> Estimator:
        """Open a complete template database (InputError for a missing / partial / foreign file)."""
        return cls(open_template(path), params, matcher)

    def _warm_up(self) -> None:
        """Load the compiled kernels (numba's cache) now, on a few of the first view's keypoints matched to
        themselves with the estimate's own array types: otherwise the first estimate paid it (the retrieval
        matrix's kernels, GMatch's, the neighbour grid of ICP and of the keypoint support, the plane RANSAC's
        scoring, the back-projection, kabsch_trimmed's consensus, run with one pair moved 1 m off, ICP's normal
        equations and the keypoint lift's window statistics)."""
        ix = self.index
        a, b = ix.offsets[0], min(ix.offsets[1], ix.offsets[0] + 8)
        if b - a < 4:
            return
        q = ix.descriptors[a:b]
        S = q.astype(np.float32) @ q.T.astype(np.float32) if ix.unit else descriptor_distances(q, q, ix.kind)
        pts = ix.neighbourhoods[0].points[:b - a]
        groups = coincident_groups(pts)
        cand = neighbourhood_candidates(S, ix.unit, *groups, TemplateGroups(np.arange(b - a), *groups), ix.eps_f,
                                        self.params.gmatch.order)
        search_candidates(pts, pts.astype(np.float32), cand, self.params.gmatch)
        best_columns(S, np.arange(b - a), np.arange(b - a), 1.0 if ix.unit else -1.0)
        grid = NearestGrid.build(pts, 0.005)
        if grid is not None:
            grid.query(pts)
        ransac_plane(pts, 20, np.random.default_rng(0), 0.01, np.zeros(3))  # (a plane found: both kernels)
        tiny = Intrinsics(1.0, 1.0, 0.5, 0.5, 2, 2)
        backproject32(RGBDFrame("warm-up", np.zeros((2, 2, 3), np.uint8), np.ones((2, 2), np.float32), tiny))
        moved = np.array(pts, dtype=np.float64)
        moved[0] += 1.0
        kabsch_trimmed(pts, moved, self.params.hypotheses.trim_tau)
        H, g = np.empty((6, 6)), np.empty(6)
        normal_equations(moved, np.arange(len(pts)), moved, moved, np.eye(4)[:3, :3], moved, moved, 0.1, H, g)
        lift_keypoints(np.zeros((1, 2)), np.ones((2, 2), np.float32), tiny)

    # ------------------------------------------------------------------------------------------------
    def estimate(self, frame: RGBDFrame, mask: np.ndarray | None = None, refine: bool = True,
                 near: np.ndarray | None = None) -> EstimateResult:
        """Pose T_cam_obj of the template's object in `frame` (mask: optional [H x W] bool search region; near: a
        pose [4 x 4] whose nearest symmetric equivalent is returned instead of the rule's, stage 8)."""
        t0 = time.perf_counter()
        q = self.prepare(frame, mask)
        with self.limit_threads():
            return self._estimate(q, refine, t0, near)

    def prepare(self, frame: RGBDFrame, mask: np.ndarray | None = None) -> QueryFrame:
        """The frame's full-image work (back-projection, support plane, search region), done once; several
        templates estimated in one frame share it (`estimate_prepared`)."""
        with self.limit_threads():
            return prepare_query(self.as_scanned(frame), mask, self.params.query)

    def estimate_all(self, frame: RGBDFrame, mask: np.ndarray | None = None, refine: bool = True,
                     explained: np.ndarray | None = None, max_instances: int | None = None) -> Instances:
        """Every instance of the template's object in `frame` (gscan.estimate.instances): found poses best score
        first, each verified as `estimate`'s pose is, never two on one instance; none with the reason. explained:
        [H x W] bool pixels of instances known already (left out of the search); max_instances: this call's cap
        (default `instances.max_instances`)."""
        return estimate_all(self, frame, mask, refine, explained=explained, max_instances=max_instances)

    def estimate_prepared(self, q: QueryFrame, refine: bool = True) -> EstimateResult:
        """`estimate` on a frame `prepare` made (several templates estimated in one frame share it)."""
        t0 = time.perf_counter()
        with self.limit_threads():
            return self._estimate(q, refine, t0)

    def as_scanned(self, frame: RGBDFrame) -> RGBDFrame:
        """`frame`, or, when it comes with the intrinsics the scan found its capture's colour camera not to have
        (`camera_fix`), its depth reprojected into the colour camera the scan used, with that camera's
        intrinsics."""
        if self.camera_fix is None or frame.intrinsics != self.camera_fix[0]:
            return frame
        given, colour = self.camera_fix
        log.debug("frame %s: read with the colour camera the scan found (focal length %.1f px)", frame.name, colour.fx)
        return RGBDFrame(frame.name, frame.color, align_depth_to_color(frame.depth, DepthCamera(given), colour), colour,
                         frame.mask)

    @contextmanager
    def limit_threads(self) -> Iterator[None]:
        """BLAS threads limited to `threads.blas` and OpenCV's to `threads.cv` while estimating (None: as they
        are)."""
        with ExitStack() as stack:
            if self._blas is not None:
                stack.enter_context(self._blas.limit(limits=self.params.threads.blas, user_api="blas"))
            if self.params.threads.cv is not None:
                import cv2

                n = cv2.getNumThreads()
                cv2.setNumThreads(self.params.threads.cv)
                stack.callback(cv2.setNumThreads, n)
            yield

    def result(self, res: EstimateResult, timer: StageTimer, t0: float,
               near: np.ndarray | None = None) -> EstimateResult:
        """`res` completed: its pose the symmetric equivalent stage 8 picks (nearest `near` [4 x 4] when given), its
        grasps at the pose and in every equivalent, and its timings (`timed`, total since t0)."""
        return timed(self.settle(res, near), timer, t0)

    def settle(self, res: EstimateResult, near: np.ndarray | None = None) -> EstimateResult:
        """`res` with its pose the symmetric equivalent stage 8 picks (nearest `near` [4 x 4] when given) and its
        grasps at that pose and in every equivalent (a settled pose may be settled again nearer another pose)."""
        group = self.verifier.group
        if res.T_cam_obj is not None:
            T = res.T_cam_obj
            if group:
                T = res.T_cam_obj = group.canonical(T) if near is None else group.nearest(T, near)
                res.symmetry = group.label
            res.grasps = self.model.grasps_at(T)
            poses = group.equivalents(T, self.params.symmetry.grasp_step_deg) if group else [T]
            res.grasp_equivalents = {k: [E @ G for E in poses] for k, G in self.model.grasps.items()}
        else:
            log.info("not found: %s", res.reason)
        return res

    # ------------------------------------------------------------------------------------------------
    def _estimate(self, q: QueryFrame, refine: bool, t0: float, near: np.ndarray | None = None) -> EstimateResult:
        """Stages 1-7 (module docstring) on a prepared frame, threads as they are."""
        p = self.params
        timer = StageTimer()
        use_pnp = q.depth_frac < p.query.min_depth_frac
        with timer.stage("features"):
            feats = query_features(q.frame, q.search, p.features, p.query, lift=not use_pnp, depth=self.query_depth)
        if len(feats) < 3:
            where = "the query frame" + (" mask" if q.mask is not None else "")
            res = not_found(f"too few keypoints in {where}")
        else:
            with timer.stage("retrieval"):
                r = self.index.retrieve(feats.descriptors)
            if use_pnp:
                res = estimate_pnp(self.index, q.frame, feats, r.S, self.index.top_views(r.votes), p.pnp, timer)
                if not res.found:
                    res.reason = f"{res.reason} (query depth unusable)"
                return self.result(res, timer, t0, near)
            with timer.stage("match"):
                qk = query_keypoints(feats, r.S)
                lists = hypothesise(self.index, qk, r, self.matcher, p.gmatch.order, p.hypotheses,
                                    self.verifier.support_sim, p.verify.support_radius)
            res = self.verifier.verify_lists(q, qk, lists, refine, timer)
            if not res.found and p.retrieval.next_round and not (res.reason or "").startswith(AMBIGUOUS):
                res = self._next_round(q, qk, r, res, refine, timer)
            res = elsewhere(self, q, feats, r, res, refine, timer)
        if not res.found and not use_pnp and not (res.reason or "").startswith(AMBIGUOUS):
            # (an ambiguous view stays ambiguous to 2D-3D matching in its holes, on less evidence)
            res = pnp_without_depth(self.index, self.model.samples, q, res, p, timer)
        return self.result(self._above(q, res), timer, t0, near)

    def _next_round(self, q: QueryFrame, qk: QueryKeypoints, r: Retrieval, res: EstimateResult, refine: bool,
                    timer: StageTimer) -> EstimateResult:
        """The pose of the next `retrieval.top_k` neighbourhoods by votes when the first ones' lists gave none
        (`res`, returned when these give none either): clutter's keypoints vote for views too, and a sparsely
        printed object's right views can rank below them. Their lists are verified under the short lists' rule
        (the long lists' relaxed rule is the first round's best list's alone) and an accepted one is weighed
        against its rivals as in the first round."""
        k = self.params.retrieval.top_k
        views = self.index.top_neighbourhoods(r.votes, 2 * k)[k:]
        if not views:
            return res
        p = self.params
        with timer.stage("match"):
            lists = hypothesise(self.index, qk, r, self.matcher, p.gmatch.order, p.hypotheses,
                                self.verifier.support_sim, p.verify.support_radius, views)
        second = self.verifier.verify_lists(q, qk, lists, refine, timer, best=False, explain=False)
        return second if second.found or (second.reason or "").startswith(AMBIGUOUS) else res

    def _above(self, q: QueryFrame, res: EstimateResult) -> EstimateResult:
        """`res`, or not found when its pose sinks the object into the frame's support plane (verify). A 3D-3D
        pose was checked when it was verified; this checks the 2D-3D ones."""
        if res.T_cam_obj is None or q.plane is None or res.method == "gmatch":
            return res
        below = self.verifier.sinks(q, res.T_cam_obj)
        if below is None:
            return res
        return not_found(f"pose puts {below:.0%} of the object inside the support plane", res.n_matches, res.view,
                         res.score, res.method, res.evidence)


def query_depth(tpl: Template) -> QueryDepth | None:
    """How a query's keypoints are joined with its depth keypoints for `tpl` (`QueryDepth`): None unless its
    keypoints are joint (rootsift+fpfh); at the template's depth keypoints' object size and its capture's depth
    noise (its "keypoints" and "noise" meta; the default noise model without the latter), the size None (no depth
    keypoints) when unknown."""
    if tpl.kind != JOINT:
        return None
    meta = tpl.meta if isinstance(tpl.meta, dict) else {}
    kp, noise = meta.get("keypoints"), meta.get("noise")
    size = kp.get("object_depth_size") if isinstance(kp, dict) else None
    try:
        depth_noise = DepthNoise(**noise["depth"]) if isinstance(noise, dict) else DepthNoise()
    except (TypeError, KeyError, ValueError):
        depth_noise, size = DepthNoise(), None
    return QueryDepth(float(size) if size else None, depth_noise)
