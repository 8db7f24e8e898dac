"""Pose of a templated object in a new RGB-D frame (`gscan estimate`).

Pipeline of `Estimator.estimate` (every stage timed, `EstimateResult.timings_ms`); the frame's full-image work
(back-projection, the support-plane fit, the search region) is done once (`gscan.estimate.query`):

1. features: RootSIFT keypoints of the query, lifted with the query depth into the camera frame, inside
   `mask` when given; without a mask inside the pixels standing off the dominant plane (the table top, whose
   texture would otherwise take most of the keypoints), or the whole frame when there is no such plane.
   Detection runs on the bounding boxes of the search region's blobs only (`region_boxes`).
2. retrieval: one GEMM of the query descriptors against the template's stacked descriptors (normalised
   once at load); every query keypoint whose nearest template descriptor is closer than `retrieval_dist`
   votes for that descriptor's view. A view's neighbourhood is itself and the `joint_views` - 1 views whose
   optical axes are nearest to its own, within `joint_deg`; the views with most votes are taken as centres
   (a view inside a neighbourhood already taken is skipped), up to `top_k`.
3. match: GMatch (gscan.matching.gmatch) of each retrieved neighbourhood's keypoints jointly, all expressed
   in its central view's camera frame (view direction +z), against the query keypoints (+z): a pose between
   keyframes, or a face the scan saw from a steeper angle than the query, collects its matches from several
   views at once. GMatch's candidates are read from the retrieval GEMM's matrix by one kernel pass per
   neighbourhood (`gscan.estimate.similarity`), never recomputed or copied into a distance block.
4. solve: every neighbourhood's best list and its GMatch runners-up (at most `runner_up_margin` shorter: in
   clutter a hard view's correct list ties with the lists the background offers) are posed at once (batched
   Kabsch) and pre-scored by the query keypoints their nearest template descriptor lands on at that pose;
   lists whose poses agree are pooled; the best pre-scored list's pose is solved by Kabsch with gross outliers
   trimmed (`kabsch_trimmed`, object-frame template points -> query camera points).
5. refine: point-to-plane ICP (`gscan.estimate.refine`, template normals, the match list as weak anchors) of
   the template cloud's points visible from the predicted pose onto the query cloud cropped to a sphere of
   1.2 object radii around the predicted centre and, without a mask, to the off-plane pixels. A given mask
   does not crop it: ICP pairs the template's whole visible surface with the query, and a mask that clips
   the silhouette (eroded, or cut by an occluder) would pull the pose toward the cut. A refinement that moves the
   pose by more than the object radius or 30 degrees is discarded.
6. verify (`gscan.estimate.verify`): the pose is accepted from the evidence (depth agreement, keypoint support
   relative to what the frame and the template show there, the list's geometry), never from the list length
   alone, and refused when it sinks the object into the support plane. When the best list's pose is refused,
   the next `verify_lists` - 1 lists are tried, under the short lists' stricter rule.
7. rivals: a box printed alike on two faces fits a pose turned onto its twin face as well as the right one,
   in shape and in most keypoints. The next `rivals` lists whose pre-score support reaches `rival_support` of
   the accepted list's, and whose poses lie beyond the refinement's reach of the accepted pose (a list within
   it is the same pose sharpened), are solved, refined and verified too. A rival accepted at another pose is
   compared with the accepted pose on the query keypoints that support one pose and not the other (a sign
   test at level `rival_p`): the pose they significantly favour is returned; when neither is favoured the
   view is ambiguous and no pose is returned (nor sought by PnP in the depth's holes).

A frame that comes with the intrinsics the template's scan found its capture's colour camera not to have
(gscan.scanning.calibration) is first read as the scan read the capture (`as_scanned`).

Without usable query depth (valid fraction of the search region < `min_depth_frac`) the pose is solved 2D-3D
(`gscan.estimate.pnp`), and the same 2D-3D solve is tried after a failed 3D-3D estimate on the search region's
holes in the depth (a dark, shiny or transparent object leaves a hole in otherwise good depth).

The estimator limits BLAS (threadpoolctl) and OpenCV to one thread each while it runs: its matrices and
detection boxes are small, and a thread pool spinning up per call costs more CPU than it saves.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.estimate.query import QueryFrame, backproject32, prepare_query
from gscan.estimate.refine import icp_anchored, normal_equations
from gscan.estimate.result import STAGES, EstimateResult, ms_since
from gscan.estimate.similarity import (
    TemplateGroups,
    best_columns,
    neighbourhood_candidates,
    neighbourhoods_candidates,
)
from gscan.estimate.verify import (
    AcceptParams,
    Evidence,
    accept,
    depth_votes,
    kabsch_batch,
    keypoint_support,
    list_spread,
    nn_support,
    sinks_into_plane,
    visible,
)
from gscan.features import (
    OBJECT_FEATURES,
    FeatureParams,
    Features,
    descriptor_distances,
    empty_features,
    extract_features,
    extract_features_in_mask,
)
from gscan.geometry.grid_kernel import NearestGrid
from gscan.geometry.kabsch import kabsch_trimmed
from gscan.geometry.plane import ransac_plane
from gscan.geometry.pointset import coincident_groups, pca_normals, voxel_down_indices, voxel_mean
from gscan.geometry.transforms import inv_T, pose_error, transform_points
from gscan.io.align import align_depth_to_color
from gscan.io.camera import DepthCamera, Intrinsics, RGBDFrame, lift_keypoints
from gscan.matching.gmatch import Candidates, GMatchParams, default_eps_f, search_candidates
from gscan.registration.noise import sign_test
from gscan.template.db import Template, open_template

log = logging.getLogger(__name__)

__all__ = ["STAGES", "EstimateParams", "EstimateResult", "Estimator"]

MAX_REFINE_DEG = 30.0  # a refinement turning the pose further is discarded (`Estimator.refine`)
AMBIGUOUS = "ambiguous view"  # the reason's start when two poses explain the frame alike (stage 7)


@dataclass(frozen=True)
class EstimateParams:
    # query keypoints (kind follows the template's), the same settings as the template's object keypoints
    features: FeatureParams = OBJECT_FEATURES
    gmatch: GMatchParams = field(default_factory=GMatchParams)  # matcher parameters (eps_f None -> default of the kind)
    top_k: int = 3  # view neighbourhoods retrieved and matched
    joint_views: int = 3  # views matched jointly per neighbourhood (1: every view alone)
    joint_deg: float = 60.0  # ... whose optical axes lie within this angle of the central view's
    verify_lists: int = 2  # match lists whose poses are verified, best pre-score first, until one is accepted
    rivals: int = 2  # lists after the accepted one verified as its rivals (module docstring, stage 7) ...
    rival_support: float = 0.4  # ... when their pre-score support reaches this fraction of the accepted list's
    rival_p: float = 0.05  # one-sided level of the sign test that lets one of two accepted poses win
    runner_up_margin: int = 2  # GMatch hypotheses this much shorter than a run's best list are pre-scored too
    merge_deg: float = 10.0  # lists whose poses agree within this angle ...
    merge_dist: float = 0.02  # ... and this distance (m) are pooled into one list
    retrieval_dist: float = 0.5  # descriptor distance under which a query keypoint votes for a view (RootSIFT L2)
    accept: AcceptParams = field(default_factory=AcceptParams)  # acceptance from the evidence (gscan.estimate.verify)
    support_dist: float | None = None  # descriptor distance at which a supporting keypoint agrees (None: eps_f)
    support_radius: float = 0.006  # m, query keypoint to template keypoint at the pose (grows 1 % of depth > 0.5 m)
    support_views_deg: float = 90.0  # template views within this angle of the query direction offer keypoints
    trim_tau: float = 0.008  # m, the match list's pose drops pairs off by more (geometry.transforms.kabsch_trimmed)
    icp_max_dist: float = 0.005  # m, ICP correspondence distance
    icp_voxel: float = 0.003  # m, template cloud downsampling (ICP source, score)
    icp_target_voxel: float = 0.004  # m, query cloud voxel averaging (ICP target)
    icp_iterations: int = 20
    icp_max_points: int = 1500  # source (template) points used by ICP, evenly subsampled
    icp_anchor_weight: float = 0.1  # weight of a matched keypoint pair against one surface pair in ICP
    crop_margin: int = 16  # px around the search region's bounding box kept for detection
    min_region_px: int = 150  # search-region blobs smaller than this are left out of the detection boxes
    depth_tol: float = 0.01  # m, depth agreement tolerance of the score (grows 2 % of depth beyond 0.5 m)
    min_depth_frac: float = 0.05  # valid-depth fraction of the search region below which PnP is used
    pnp_ratio: float = 0.8  # Lowe ratio of 2D-3D descriptor matches
    pnp_max_error_px: float = 4.0  # RANSAC reprojection threshold
    pnp_min_inliers: int = 12
    pnp_min_inlier_ratio: float = 0.25  # PnP inliers / 2D-3D matches below this -> not found
    pnp_in_holes: bool = True  # after a failed 3D-3D estimate, try PnP on the pixels without depth
    hole_min_frac: float = 0.01  # ... when at least this fraction of the search region lacks depth
    hole_open_px: int = 7  # ... counting holes that a (2r+1)-pixel square fits in (no speckle, no shadow band)
    hole_dilate_px: int = 4  # ... grown by this many pixels (keypoints at a hole's border)
    max_see_through: float = 0.2  # ... and its pose refused when the depth shows through more of the object
    remove_plane: bool = True  # without a mask: leave out the dominant plane (table) from the search region
    plane_min_frac: float = 0.3  # a plane counts as dominant when it holds this fraction of the valid depth
    plane_iterations: int = 64  # RANSAC plane hypotheses (seeded)
    below_tol: float = 0.015  # m: a template point this far behind the support plane is inside it ...
    max_below_frac: float = 0.2  # ... and a pose with more such points is not found
    blas_threads: int | None = 1  # BLAS threads while estimating (threadpoolctl; None leaves them as they are)
    cv_threads: int | None = 1  # OpenCV threads (SIFT) while estimating (None leaves them as they are)


@dataclass
class _Candidate:
    """One neighbourhood's match list: matches [M x 2] (global template keypoint, query keypoint)."""

    n: int
    cost: float
    view: int
    matches: np.ndarray = field(repr=False)
    support: int = 0  # query keypoints whose nearest template descriptor lands on them at the list's pose
    T: np.ndarray = field(default_factory=lambda: np.eye(4), repr=False)  # the list's plain Kabsch pose
    longest: int = 0  # the longest single GMatch list among the lists merged into this one


@dataclass
class _QueryKeypoints:
    """The query's lifted keypoints and their similarity to the template. S: the retrieval matrix
    [M x N_template] (cosine similarity for unit descriptors, else distance); location [M]: a location id per
    keypoint (orientations of one point share it); order [M], starts [G]: the locations' keypoints
    (order[starts[g]:starts[g+1]], gscan.geometry.pointset.coincident_groups); group_kp [G]: a keypoint of
    each location; candidates: the GMatch candidates of the neighbourhoods to match, found together."""

    feats: Features
    S: np.ndarray = field(repr=False)
    location: np.ndarray = field(repr=False)
    order: np.ndarray = field(repr=False)
    starts: np.ndarray = field(repr=False)
    group_kp: np.ndarray = field(repr=False)
    candidates: dict[int, Candidates] = field(default_factory=dict, repr=False)  # view -> its neighbourhood's


class Estimator:
    """A template loaded once for repeated pose estimation (`from_path`, then `estimate`)."""

    def __init__(self, tpl: Template, params: EstimateParams = EstimateParams()):
        """tpl: a loaded template (TemplateDB.load_template: object keypoints in the object frame)."""
        if tpl.kind is None or len(tpl.view_names) == 0 or len(tpl.descriptors) == 0:
            raise InputError(tpl.path, "template holds no registered view with keypoints")
        if tpl.kind != params.features.kind:
            params = replace(params, features=replace(params.features, kind=tpl.kind))
        self.params = params
        self.path = tpl.path
        self.name = Path(tpl.path).stem if tpl.path is not None else "template"
        self.kind = tpl.kind
        self.view_names = list(tpl.view_names)
        self.T_obj_cam = np.asarray(tpl.T_obj_cam, dtype=np.float64)  # [V x 4 x 4]
        self.points_obj = tpl.points_obj.astype(np.float64)
        desc = tpl.descriptors
        self.descriptors = np.ascontiguousarray(desc, dtype=np.float32 if self.kind != "orb" else np.uint8)
        self.unit = self.kind == "rootsift"
        V = len(self.view_names)
        self.offsets = np.asarray(tpl.view_offsets, dtype=np.int64)  # keypoints of view v: offsets[v]:offsets[v+1]
        self.kp_view = np.asarray(tpl.kp_view, dtype=np.int64)
        self.axes = self.T_obj_cam[:, :3, 2]  # [V x 3] optical axes in the object frame
        self._build_neighbourhoods()
        cloud = tpl.cloud_points if tpl.cloud_points is not None and len(tpl.cloud_points) else None
        if cloud is None and tpl.mesh is not None and len(tpl.mesh.vertices):
            cloud = tpl.mesh.vertices
        if cloud is None:
            cloud = self.points_obj
        self.cloud = np.asarray(cloud, dtype=np.float64)
        # model points for metrics: mesh vertices when the template has a mesh, else the cloud
        self.model_points = np.asarray(tpl.mesh.vertices if tpl.mesh is not None and len(tpl.mesh.vertices)
                                       else self.cloud, dtype=np.float64)
        sel = voxel_down_indices(self.cloud, params.icp_voxel)
        self.cloud_icp = self.cloud[sel]
        self.normals_icp = pca_normals(self.cloud_icp)
        lo, hi = self.cloud.min(0), self.cloud.max(0)
        self.center = 0.5 * (lo + hi)
        self.radius = float(np.linalg.norm(self.cloud - self.center, axis=1).max())
        self.grasps = dict(tpl.grasps)
        # the scan found the capture's depth off its colour at the given intrinsics (gscan.scanning.calibration): a
        # frame read with those same intrinsics is read as the scan read the capture
        cam = tpl.meta.get("camera") if isinstance(tpl.meta, dict) else None
        self.camera_fix: tuple[Intrinsics, Intrinsics] | None = None  # (given, the colour camera's)
        if isinstance(cam, dict) and cam.get("corrected"):
            given, colour = cam["given_intrinsics"], cam["colour_intrinsics"]
            self.camera_fix = Intrinsics.from_dict(given), Intrinsics.from_dict(colour)
        self.eps_f = params.gmatch.eps_f if params.gmatch.eps_f is not None else default_eps_f(self.kind)
        sd = params.support_dist if params.support_dist is not None else self.eps_f
        # similarity at which a supporting keypoint's descriptor agrees (cosine for unit descriptors)
        self.support_sim = 1.0 - 0.5 * sd ** 2 if self.unit else -sd
        self._blas = None
        if params.blas_threads is not None:
            from threadpoolctl import ThreadpoolController

            self._blas = ThreadpoolController()
        self._warm_up()
        if V:
            log.debug("%s: %d views, %d keypoints, neighbourhoods of %s views", self.path, V, len(self.points_obj),
                      [len(n) for n in self.neighbours])

    def _build_neighbourhoods(self) -> None:
        """Per view v: its neighbourhood (v first, then the nearest optical axes within joint_deg, at most
        joint_views), the neighbourhood's global keypoint indices, their points in v's camera frame and the
        groups of coincident points among them (keypoints of one location with several orientations)."""
        p = self.params
        V = len(self.view_names)
        cos = np.clip(self.axes @ self.axes.T, -1.0, 1.0)
        self.neighbours: list[np.ndarray] = []
        self.nb_idx: list[np.ndarray] = []
        self.nb_points: list[np.ndarray] = []
        self.nb_groups: list[tuple[np.ndarray, np.ndarray]] = []
        self.nb_tgroups: list[TemplateGroups] = []
        for v in range(V):
            order = [u for u in np.lexsort((np.arange(V), -cos[v])) if u != v]
            near = [int(u) for u in order if cos[v, u] >= np.cos(np.radians(p.joint_deg))]
            nb = [v] + near[: max(0, p.joint_views - 1)]
            idx = np.concatenate([np.arange(self.offsets[u], self.offsets[u + 1]) for u in nb]).astype(np.int64)
            self.neighbours.append(np.asarray(nb, np.int64))
            self.nb_idx.append(idx)
            self.nb_points.append(transform_points(inv_T(self.T_obj_cam[v]), self.points_obj[idx]))
            self.nb_groups.append(coincident_groups(self.points_obj[idx]))
            self.nb_tgroups.append(TemplateGroups(idx, *self.nb_groups[-1]))

    def _warm_up(self) -> None:
        """Load the compiled kernels (numba's cache) now, on a few of the first view's keypoints matched to
        themselves with the estimate's own array types: otherwise the first estimate paid it (the retrieval
        matrix's kernels, GMatch's, the neighbour grid of ICP and of the keypoint support, the plane RANSAC's
        scoring, the back-projection, kabsch_trimmed's consensus, run with one pair moved 1 m off, ICP's normal
        equations and the keypoint lift's window statistics)."""
        a, b = self.offsets[0], min(self.offsets[1], self.offsets[0] + 8)
        if b - a < 4:
            return
        q = self.descriptors[a:b]
        S = q.astype(np.float32) @ q.T.astype(np.float32) if self.unit else descriptor_distances(q, q, self.kind)
        pts = self.nb_points[0][:b - a]
        groups = coincident_groups(pts)
        cand = neighbourhood_candidates(S, self.unit, *groups, TemplateGroups(np.arange(b - a), *groups), self.eps_f,
                                        self.params.gmatch.order)
        search_candidates(pts, pts.astype(np.float32), cand, self.params.gmatch)
        best_columns(S, np.arange(b - a), np.arange(b - a), 1.0 if self.unit else -1.0)
        grid = NearestGrid.build(pts, 0.005)
        if grid is not None:
            grid.query(pts)
        ransac_plane(pts, 20, np.random.default_rng(0), 0.01, np.zeros(3))  # (a plane found: both kernels)
        tiny = Intrinsics(1.0, 1.0, 0.5, 0.5, 2, 2)
        backproject32(RGBDFrame("warm-up", np.zeros((2, 2, 3), np.uint8), np.ones((2, 2), np.float32), tiny))
        moved = np.array(pts, dtype=np.float64)
        moved[0] += 1.0
        kabsch_trimmed(pts, moved, self.params.trim_tau)
        H, g = np.empty((6, 6)), np.empty(6)
        normal_equations(moved, np.arange(len(pts)), moved, moved, np.eye(4)[:3, :3], moved, moved, 0.1, H, g)
        lift_keypoints(np.zeros((1, 2)), np.ones((2, 2), np.float32), tiny)

    @classmethod
    def from_path(cls, path: str | Path, params: EstimateParams = EstimateParams()) -> Estimator:
        """Open a complete template database (InputError for a missing / partial / foreign file)."""
        return cls(open_template(path), params)

    # ------------------------------------------------------------------------------------------------
    def estimate(self, frame: RGBDFrame, mask: np.ndarray | None = None, refine: bool = True) -> EstimateResult:
        """Pose T_cam_obj of the template's object in `frame` (mask: optional [H x W] bool search region)."""
        t_all = time.perf_counter()
        q = self.prepare(frame, mask)
        with self._blas_limit():
            return self.estimate_query(q, refine, t_all)

    def prepare(self, frame: RGBDFrame, mask: np.ndarray | None = None) -> QueryFrame:
        """The frame's full-image work (back-projection, support plane, search region), done once; several
        templates estimated in one frame share it (`estimate_query`)."""
        p = self.params
        with self._blas_limit():
            return prepare_query(self.as_scanned(frame), mask, p.remove_plane, p.min_depth_frac, p.plane_min_frac,
                                 p.plane_iterations)

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
    def _blas_limit(self) -> Iterator[None]:
        """BLAS threads limited to blas_threads and OpenCV's to cv_threads while estimating (None: as they are)."""
        with ExitStack() as stack:
            if self._blas is not None:
                stack.enter_context(self._blas.limit(limits=self.params.blas_threads, user_api="blas"))
            if self.params.cv_threads is not None:
                import cv2

                n = cv2.getNumThreads()
                cv2.setNumThreads(self.params.cv_threads)
                stack.callback(cv2.setNumThreads, n)
            yield

    def estimate_prepared(self, q: QueryFrame, refine: bool = True) -> EstimateResult:
        """`estimate` on a frame `prepare` made (several templates estimated in one frame share it)."""
        t_all = time.perf_counter()
        with self._blas_limit():
            return self.estimate_query(q, refine, t_all)

    def estimate_query(self, q: QueryFrame, refine: bool = True, t_all: float | None = None) -> EstimateResult:
        """`estimate` on a prepared frame (`prepare`), BLAS threads as they are."""
        t_all = time.perf_counter() if t_all is None else t_all
        tm: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        use_pnp = q.depth_frac < self.params.min_depth_frac
        t = time.perf_counter()
        feats = self._features(q.frame, q.search, lift=not use_pnp)
        tm["features"] = ms_since(t)
        if len(feats) < 3:
            where = "the query frame" + (" mask" if q.mask is not None else "")
            res = self._fail(tm, t_all, f"too few keypoints in {where}")
        else:
            t = time.perf_counter()
            S, votes, nearest = self._retrieve_nearest(feats.descriptors)
            tm["retrieval"] = ms_since(t)
            if use_pnp:
                from gscan.estimate.pnp import estimate_pnp

                res = estimate_pnp(self, q.frame, feats, S, self._top_views(votes), tm, t_all)
                if not res.found:
                    res.reason = f"{res.reason} (query depth unusable)"
                return res
            res = self._estimate_gmatch(q, feats, S, votes, refine, tm, t_all, nearest)
        if not res.found and not use_pnp and not (res.reason or "").startswith(AMBIGUOUS):
            # (an ambiguous view stays ambiguous to 2D-3D matching in its holes, on less evidence)
            from gscan.estimate.pnp import pnp_without_depth

            res = pnp_without_depth(self, q, res, tm, t_all)
        return self._above(q, res, tm, t_all)

    def _above(self, q: QueryFrame, res: EstimateResult, tm: dict[str, float], t_all: float) -> EstimateResult:
        """`res`, or not found when its pose sinks the object into the frame's support plane (verify). A 3D-3D
        pose was checked when it was verified; this checks the 2D-3D ones."""
        if res.T_cam_obj is None or q.plane is None or res.method == "gmatch":
            return res
        below = self._sinks(q, res.T_cam_obj)
        if below is None:
            return res
        return self._fail(tm, t_all, f"pose puts {below:.0%} of the object inside the support plane", res.n_matches,
                          res.view, res.score, res.method, res.evidence)

    def _sinks(self, q: QueryFrame, T_cam_obj: np.ndarray) -> float | None:
        if q.plane is None:
            return None
        assert q.heights is not None
        return sinks_into_plane(T_cam_obj, self.cloud_icp, q.plane, q.heights, q.frame.depth,
                                q.frame.intrinsics, self.params.below_tol, self.params.max_below_frac)

    def _estimate_gmatch(self, q: QueryFrame, feats: Features, S: np.ndarray, votes: np.ndarray, refine: bool,
                         tm: dict[str, float], t_all: float,
                         nearest: tuple[np.ndarray, np.ndarray] | None = None) -> EstimateResult:
        """Stages 3-6 (module docstring) on the lifted query keypoints (nearest: `_retrieve_nearest`'s)."""
        p = self.params
        t = time.perf_counter()
        qk = self._query_keypoints(feats, S)
        q_location = qk.location
        cands: list[_Candidate] = []
        seen: set[bytes] = set()
        views = self._top_neighbourhoods(votes)
        qk.candidates = dict(zip(views, neighbourhoods_candidates(
            S, self.unit, qk.order, qk.starts, [self.nb_tgroups[v] for v in views], self.eps_f,
            self.params.gmatch.order), strict=True))
        for v in views:
            for m, cost in self._match_hypotheses(v, qk):
                key = np.ascontiguousarray(m[np.lexsort((m[:, 1], m[:, 0]))]).tobytes()
                if len(m) >= 3 and key not in seen:
                    seen.add(key)
                    cands.append(_Candidate(len(m), cost, v, m))
        self._prescore(cands, feats, S, nearest)
        cands = self._merge_agreeing(cands, feats.points)
        tm["match"] = ms_since(t)
        if not cands:
            return self._fail(tm, t_all, "too few geometrically consistent matches (no list of 3)", 0)
        first: EstimateResult | None = None
        listed = [c for c in cands if c.n >= p.accept.min_matches]
        for i, c in enumerate(listed[: max(1, p.verify_lists)]):
            res = self._solve_verify(q, feats, S, q_location, c, refine, tm, t_all, best=c is cands[0])
            if res.found:
                rivals = [r for r in listed[i + 1:] if r.support >= p.rival_support * c.support]
                return self._against_rivals(q, feats, S, q_location, res, rivals, refine, tm, t_all)
            first = first or res
        if first is None:
            n = max(c.n for c in cands)
            return self._fail(tm, t_all, f"too few geometrically consistent matches ({n} < {p.accept.min_matches})", n,
                              self.view_names[cands[0].view])
        return first

    def _against_rivals(self, q: QueryFrame, feats: Features, S: np.ndarray, q_location: np.ndarray,
                        res: EstimateResult, rivals: list[_Candidate], refine: bool, tm: dict[str, float],
                        t_all: float) -> EstimateResult:
        """The accepted `res` against its rival lists (module docstring, stage 7): the pose the keypoints
        significantly favour, or not found when the view cannot tell them apart."""
        p = self.params
        checked = 0
        for r in rivals:
            assert res.T_cam_obj is not None and res.evidence is not None
            if checked >= p.rivals:
                break
            deg, dist = pose_error(r.T, res.T_cam_obj)
            if deg <= MAX_REFINE_DEG and dist <= self.radius:
                continue
            checked += 1
            alt = self._solve_verify(q, feats, S, q_location, r, refine, tm, t_all)
            if alt.T_cam_obj is None or alt.evidence is None:
                continue
            deg, dist = pose_error(alt.T_cam_obj, res.T_cam_obj)
            if deg <= p.merge_deg and dist <= p.merge_dist:  # the same pose: corroboration, not a rival
                continue
            a, b = res.evidence.supporters, alt.evidence.supporters
            only_res, only_alt = len(np.setdiff1d(a, b)), len(np.setdiff1d(b, a))
            if sign_test(only_res, only_alt) < p.rival_p:
                continue
            if sign_test(only_alt, only_res) < p.rival_p:
                log.debug("a rival pose wins (%d keypoints for it alone, %d against)", only_alt, only_res)
                res = alt
                continue
            return self._fail(tm, t_all, f"{AMBIGUOUS}: a pose {deg:.0f} deg / {dist * 1000:.0f} mm away explains it "
                              f"as well ({only_res} keypoints agree with one pose only, {only_alt} with the other)",
                              res.n_matches, res.view, res.score, evidence=res.evidence)
        tm["total"] = ms_since(t_all)
        return res

    def _prescore(self, cands: list[_Candidate], feats: Features, S: np.ndarray,
                  nearest: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Set every candidate's `support`: the query keypoints whose nearest template keypoint by descriptor
        lands on them under the list's plain Kabsch pose (`nn_support`), all lists at once. nearest: each query
        keypoint's nearest template keypoint and its value in S (`_retrieve_nearest`), else found in S."""
        if not cands:
            return
        L = max(c.n for c in cands)
        src = np.zeros((len(cands), L, 3))
        dst = np.zeros((len(cands), L, 3))
        w = np.zeros((len(cands), L))
        for h, c in enumerate(cands):
            src[h, :c.n] = self.points_obj[c.matches[:, 0]]
            dst[h, :c.n] = feats.points[c.matches[:, 1]]
            w[h, :c.n] = 1.0
        T = kabsch_batch(src, dst, w)
        nn, best = self._nearest(S) if nearest is None else nearest
        agree = best >= self.support_sim if self.unit else best <= -self.support_sim
        q_pts = feats.points[agree].astype(np.float64)
        z = np.median(q_pts[:, 2]) if len(q_pts) else 0.5
        support = nn_support(T, self.points_obj[nn[agree]], q_pts, self.params.support_radius
                             + 0.01 * max(float(z) - 0.5, 0.0))
        for c, n, T_h in zip(cands, support, T, strict=True):
            c.support, c.T = int(n), T_h

    def _merge_agreeing(self, cands: list[_Candidate], feats_points: np.ndarray) -> list[_Candidate]:
        """Lists whose poses agree (within merge_deg and merge_dist of the best-supported one's) are one list:
        their pairs are pooled (a pair once), so several short lists of one pose make one long one. Returns
        the merged lists, best pre-score support first (ties: longer, then lower cost)."""
        p = self.params
        order = sorted(cands, key=lambda c: (-c.support, -c.n, c.cost))
        merged: list[_Candidate] = []
        members: list[list[np.ndarray]] = []
        if not order:
            return merged
        Ts = np.stack([c.T for c in order])
        trace_min = 1.0 + 2.0 * np.cos(np.radians(p.merge_deg))
        owner = np.full(len(order), -1)
        for i, c in enumerate(order):  # each unowned list in order becomes a representative of those agreeing
            if owner[i] >= 0:
                members[owner[i]].append(c.matches)
                continue
            k = len(merged)
            merged.append(_Candidate(c.n, c.cost, c.view, c.matches, c.support, c.T, c.n))
            members.append([c.matches])
            rest = np.flatnonzero(owner[i + 1:] < 0) + i + 1
            tr = np.einsum("ij,nij->n", c.T[:3, :3], Ts[rest, :3, :3])  # trace(R_c^T R_n)
            agree = (tr >= trace_min) & (np.linalg.norm(Ts[rest, :3, 3] - c.T[:3, 3], axis=1) <= p.merge_dist)
            owner[rest[agree]] = k
        for rep, ms in zip(merged, members, strict=True):
            rep.longest = max(len(m) for m in ms)
            if len(ms) > 1:
                m = np.concatenate(ms)
                _, first = np.unique(m, axis=0, return_index=True)
                m = m[np.sort(first)]  # the best list's pairs first, in order
                # pooled pairs off the representative's pose by more than twice the trim distance are left out
                r = np.linalg.norm(transform_points(rep.T, self.points_obj[m[:, 0]]) - feats_points[m[:, 1]], axis=1)
                rep.matches = m[(r < 2 * p.trim_tau) | (np.arange(len(m)) < len(ms[0]))]
                rep.n = len(rep.matches)
        return merged

    def _solve_verify(self, q: QueryFrame, feats: Features, S: np.ndarray, q_location: np.ndarray, c: _Candidate,
                      refine: bool, tm: dict[str, float], t_all: float, best: bool = True) -> EstimateResult:
        """Solve, refine and verify one match list (best: the frame's best-supported list, gscan.estimate.verify)."""
        p = self.params
        t = time.perf_counter()
        src = self.points_obj[c.matches[:, 0]]
        dst = feats.points[c.matches[:, 1]].astype(np.float64)
        T_cam_obj, keep = kabsch_trimmed(src, dst, p.trim_tau)
        tm["solve"] += ms_since(t)
        t = time.perf_counter()
        if refine:  # the ICP target is not cut by a given mask: a mask that clips the silhouette pulls ICP to the cut
            T_cam_obj = self.refine(q, T_cam_obj, (src[keep], dst[keep]), q.off_plane)
        ev = self.evidence(q, T_cam_obj, feats, S, q_location)
        # inliers count query keypoint locations (pooled lists pair one keypoint with several template views)
        ev.n_matches, ev.n_inliers = c.longest, len(np.unique(q_location[c.matches[keep, 1]]))
        ev.spread_m = list_spread(src[keep])
        tm["refine"] += ms_since(t)
        view = self.view_names[c.view]
        below = self._sinks(q, T_cam_obj)
        why = accept(ev, self.radius, p.accept, best) if below is None else \
            f"pose puts {below:.0%} of the object inside the support plane"
        if why is not None:
            return self._fail(tm, t_all, why, c.longest, view, ev.score, evidence=ev)
        return self._found(T_cam_obj, ev.score, c.longest, view, tm, t_all, "gmatch", ev)

    def evidence(self, q: QueryFrame, T_cam_obj: np.ndarray, feats: Features, S: np.ndarray,
                 q_location: np.ndarray, kp_idx: np.ndarray | None = None,
                 sim_cols: np.ndarray | None = None) -> Evidence:
        """Depth agreement and keypoint support of a pose (gscan.estimate.verify); n_matches, n_inliers and
        spread_m are left to the caller. S [M x C]: the query keypoints' similarity (unit descriptors) or
        distance to template keypoints; kp_idx: the template keypoints offered (default: those of the views
        near the pose's viewing direction) and sim_cols their columns in S (default: S holds every keypoint)."""
        p = self.params
        frame = q.frame
        seen = visible(T_cam_obj, frame.intrinsics, self.cloud_icp)  # the template surface the pose shows
        n_c, n_b, n = depth_votes(frame.depth, frame.intrinsics, T_cam_obj, self.cloud_icp, p.depth_tol, q.off_plane,
                                  seen)
        ev = Evidence(score=n_c / max(1, n_c + n_b), confirmed=n_c / max(1, n))
        if kp_idx is None:
            kp_idx = self._offered_keypoints(T_cam_obj)
        z = float(transform_points(T_cam_obj, self.center[None])[0, 2])
        radius = p.support_radius + 0.01 * max(z - 0.5, 0.0)
        ev.supporters, ev.on_surface, ev.offer = keypoint_support(
            T_cam_obj, self.points_obj, kp_idx, S, kp_idx if sim_cols is None else sim_cols, feats.points, q_location,
            self.cloud_icp, frame.depth, frame.intrinsics, radius, self.support_sim, p.depth_tol,
            1.0 if self.unit else -1.0, seen[1])
        return ev

    def _offered_keypoints(self, T_cam_obj: np.ndarray) -> np.ndarray:
        """Global indices of the keypoints of the views within support_views_deg of the query's optical axis."""
        axis = T_cam_obj[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the query camera's axis in the object frame
        views = np.flatnonzero(self.axes @ axis >= np.cos(np.radians(self.params.support_views_deg)))
        if len(views) == 0:
            views = np.array([int(np.argmax(self.axes @ axis))])
        return np.concatenate([np.arange(self.offsets[v], self.offsets[v + 1]) for v in views]).astype(np.int64)

    # ------------------------------------------------------------------------------------------------
    def _query_keypoints(self, feats: Features, S: np.ndarray) -> _QueryKeypoints:
        order, starts = coincident_groups(feats.points)
        location = np.empty(len(feats), np.int64)
        location[order] = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(feats)]))
        return _QueryKeypoints(feats, S, location, order, starts, order[starts])

    def _match_hypotheses(self, v: int, qk: _QueryKeypoints) -> list[tuple[np.ndarray, float]]:
        """GMatch of view v's neighbourhood (its keypoints and its neighbours', in v's camera frame) against the
        query: its best list first, then the hypotheses at most `runner_up_margin` shorter (and at least
        `accept.min_matches` long): a short correct list ties with the lists clutter offers, and the evidence
        decides between them. Each as (matches [M x 2] (global template keypoint, query keypoint), cost).
        Keypoints sharing a 3D point (SIFT orientations of one location) are matched as one, by their closest
        descriptors."""
        idx = self.nb_idx[v]
        s_order, s_starts = self.nb_groups[v]
        gs = idx[s_order[s_starts]]  # source row -> global template keypoint
        gq = qk.group_kp  # target column -> query keypoint
        # the candidates of the [Ns x G] group distance block, read from S without building the block
        cand = qk.candidates.get(v)
        if cand is None:
            cand = neighbourhood_candidates(qk.S, self.unit, qk.order, qk.starts, self.nb_tgroups[v], self.eps_f,
                                            self.params.gmatch.order)
        res = search_candidates(self.nb_points[v][s_order[s_starts]], qk.feats.points[gq], cand, self.params.gmatch)
        best = np.asarray(res.matches, dtype=np.int64).reshape(-1, 2)
        out = [(np.stack([gs[best[:, 0]], gq[best[:, 1]]], 1), float(res.cost))]
        n_min = max(self.params.accept.min_matches, len(best) - self.params.runner_up_margin)
        hyps = np.flatnonzero(res.hyp_length >= n_min)
        if len(hyps):
            hm = res.hyp_matches[hyps].astype(np.int64)  # [H x L x 2], -1 past each length
            g = np.stack([gs[np.maximum(hm[..., 0], 0)], gq[np.maximum(hm[..., 1], 0)]], -1)
            out += [(g[i, :res.hyp_length[h]], float(res.hyp_cost[h])) for i, h in enumerate(hyps)]
        return out

    def _match_view(self, v: int, qk: _QueryKeypoints) -> tuple[np.ndarray, float]:
        """The best GMatch list of view v's neighbourhood (see `_match_hypotheses`)."""
        return self._match_hypotheses(v, qk)[0]

    def _features(self, frame: RGBDFrame, mask: np.ndarray | None, lift: bool) -> Features:
        """Query keypoints; with a mask, detection runs on the mask's bounding box (+ margin) only.
        Without `lift` (PnP mode) every keypoint is kept: a unit placeholder depth is lifted, so only
        pixels and descriptors are meaningful."""
        fparams = self.params.features if lift else replace(self.params.features, lift_window=0)
        if not lift:
            frame = RGBDFrame(frame.name, frame.color, np.ones_like(frame.depth), frame.intrinsics)
        if mask is None:
            return extract_features(frame, fparams)
        if not mask.any():
            return empty_features(fparams.kind)
        boxes = region_boxes(mask, self.params.crop_margin, self.params.min_region_px)
        if len(boxes) <= 1:
            return extract_features_in_mask(frame, mask, fparams, self.params.crop_margin)
        parts = []
        for box in boxes:  # one detection per box: SIFT's cost follows the area it scans
            parts.append(extract_features_in_mask(frame, mask, fparams, self.params.crop_margin, within=box))
        return Features(np.concatenate([f.pixels for f in parts]), np.concatenate([f.points for f in parts]),
                        np.concatenate([f.descriptors for f in parts]), fparams.kind,
                        np.concatenate([f.scales for f in parts]))

    def _retrieve(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Query descriptors [M x D] -> (similarity or distance matrix [M x N], votes per view [V])."""
        return self._retrieve_nearest(q)[:2]

    def _retrieve_nearest(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """`_retrieve`, and each query keypoint's nearest template keypoint [M] with its value in S [M]."""
        if self.unit:
            S = np.matmul(q.astype(np.float32), self.descriptors.T)  # cosine similarity of unit vectors
        else:
            S = descriptor_distances(q, self.descriptors, self.kind)
        nn, best = self._nearest(S)
        ok = best >= 1.0 - 0.5 * self.params.retrieval_dist ** 2 if self.unit else best < self.eps_f
        # each query keypoint votes for the view holding its nearest template descriptor
        return S, np.bincount(self.kp_view[nn[ok]], minlength=len(self.view_names)), (nn, best)

    def _nearest(self, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each row's nearest template keypoint in S [M x N] (first on ties) and its value: ([M], [M])."""
        nn = np.argmax(S, axis=1) if self.unit else np.argmin(S, axis=1)
        return nn, S[np.arange(len(S)), nn]

    def _top_views(self, votes: np.ndarray) -> list[int]:
        """The top_k views by votes (ties by view order), views without a vote left out."""
        order = np.lexsort((np.arange(len(votes)), -votes))
        return [int(v) for v in order[: self.params.top_k] if votes[v] > 0]

    def _top_neighbourhoods(self, votes: np.ndarray) -> list[int]:
        """Central views of the neighbourhoods to match: views by their own votes (ties by view order), each
        taken unless a neighbourhood already taken holds it, up to top_k; views without a vote are left out.
        Clutter spreads votes over many views: taking a view's neighbours with it leaves room for a view of
        another side of the object."""
        chosen: list[int] = []
        covered: set[int] = set()
        for v in np.lexsort((np.arange(len(votes)), -votes)):
            if votes[v] <= 0 or len(chosen) >= self.params.top_k:
                break
            if int(v) not in covered:
                chosen.append(int(v))
                covered.update(int(u) for u in self.neighbours[v])
        return chosen

    def _dist(self, S: np.ndarray) -> np.ndarray:
        """Similarity block (unit descriptors) or distance block -> L2/Hamming distances."""
        if self.unit:
            return np.sqrt(np.maximum(2.0 - 2.0 * S, 0.0))
        return S

    def refine(self, q: QueryFrame, T_cam_obj: np.ndarray, anchors: tuple[np.ndarray, np.ndarray] | None,
               region: np.ndarray | None, max_dists: tuple[float, ...] | None = None,
               max_points: int | None = None) -> np.ndarray:
        """ICP of the visible template cloud onto the query cloud cropped to `region` ([H x W] bool, or None) and
        to a sphere around the predicted object (module docstring, stage 5). max_dists: correspondence
        distances, coarse to fine (default: icp_max_dist alone); max_points: template points used (default:
        icp_max_points). Returns T_cam_obj unchanged when ICP has too
        little to work with or moves the pose implausibly far."""
        p = self.params
        idx, _, _ = visible(T_cam_obj, q.frame.intrinsics, self.cloud_icp)
        if len(idx) < 30:
            return T_cam_obj
        max_dists = (p.icp_max_dist,) if max_dists is None else max_dists
        c = transform_points(T_cam_obj, self.center[None])[0]
        tgt = q.points_near(c, 1.2 * self.radius + max(max_dists), region)
        if len(tgt) < 30:
            return T_cam_obj
        tgt = voxel_mean(tgt, p.icp_target_voxel)  # averaging, not picking: depth noise shrinks
        idx = idx[:: max(1, int(np.ceil(len(idx) / (max_points or p.icp_max_points))))]
        T, fitness = icp_anchored(self.cloud_icp[idx], self.normals_icp[idx], tgt, T_cam_obj, max_dists,
                                  p.icp_iterations, anchors, p.icp_anchor_weight)
        dR = T[:3, :3] @ T_cam_obj[:3, :3].T
        moved = np.linalg.norm(T[:3, 3] - T_cam_obj[:3, 3])
        if fitness <= 0 or moved > self.radius or np.trace(dR) < 1.0 + 2.0 * np.cos(np.radians(MAX_REFINE_DEG)):
            log.debug("ICP rejected (fitness %.2f, moved %.3f m)", fitness, moved)
            return T_cam_obj
        return T

    def _found(self, T: np.ndarray, score: float, n: int, view: str, tm: dict[str, float], t_all: float,
               method: str, evidence: Evidence | None = None) -> EstimateResult:
        tm["total"] = ms_since(t_all)
        grasps = {k: T @ G for k, G in self.grasps.items()}
        return EstimateResult(T, float(score), int(n), view, None, grasps, tm, method, evidence)

    def _fail(self, tm: dict[str, float], t_all: float, reason: str, n: int = 0, view: str | None = None,
              score: float = 0.0, method: str = "gmatch", evidence: Evidence | None = None) -> EstimateResult:
        tm["total"] = ms_since(t_all)
        log.info("not found: %s", reason)
        return EstimateResult(None, float(score), int(n), view, reason, {}, tm, method, evidence)


def _group_reduce(A: np.ndarray, order: np.ndarray, starts: np.ndarray, axis: int, reduce: np.ufunc) -> np.ndarray:
    """Rows (axis 0) or columns (axis 1) of A taken in `order` and reduced over each group
    order[starts[g]:starts[g+1]] with `reduce` (np.maximum / np.minimum) -> one row or column per group.
    Most groups hold one member: the first members are gathered at once and the k-th members of the larger
    groups folded in, k = 2, 3, ... (a gather per rank instead of a reduceat over the whole matrix)."""
    if len(starts) == 0:
        return np.take(A, np.zeros(0, np.int64), axis=axis)
    out = np.take(A, order[starts], axis=axis)
    sizes = np.diff(np.r_[starts, len(order)])
    for k in range(1, int(sizes.max())):
        g = np.flatnonzero(sizes > k)
        members = np.take(A, order[starts[g] + k], axis=axis)
        if axis == 0:
            out[g] = reduce(out[g], members)
        else:
            out[:, g] = reduce(out[:, g], members)
    return out


def region_boxes(mask: np.ndarray, margin: int, min_px: int, max_fill: float = 0.7) -> list[tuple[int, int, int, int]]:
    """Detection boxes (x0, y0, x1, y1) of a search region [H x W] bool: the bounding boxes of its connected
    blobs of at least min_px pixels, grown by `margin` and merged while they overlap. One box (the region's
    bounding box) when the blobs' boxes cover more than `max_fill` of it, or none of them is large enough."""
    import cv2

    H, W = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return []
    # the blobs of the region's bounding box (a crop: the labelling's cost follows the pixels it scans)
    crop = mask[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1].astype(np.uint8)
    _, _, stats, _ = cv2.connectedComponentsWithStats(crop, connectivity=8)
    stats[:, 0] += cols[0]
    stats[:, 1] += rows[0]
    boxes = [[max(0, x - margin), max(0, y - margin), min(W, x + w + margin), min(H, y + h + margin)]
             for x, y, w, h, a in stats[1:] if a >= min_px]
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    if len(boxes) <= 1:
        return [tuple(b) for b in boxes]
    union = (cols[-1] - cols[0] + 1 + 2 * margin) * (rows[-1] - rows[0] + 1 + 2 * margin)
    if sum((b[2] - b[0]) * (b[3] - b[1]) for b in boxes) > max_fill * union:
        return []
    return sorted((int(b[0]), int(b[1]), int(b[2]), int(b[3])) for b in boxes)

