"""Pose of a templated object in a new RGB-D frame (`gscan estimate`).

Pipeline of `Estimator.estimate` (every stage timed, `EstimateResult.timings_ms`):

1. features: RootSIFT keypoints of the query, lifted with the query depth into the camera frame,
   inside `mask` when given (the frame is then cropped to the mask's bounding box before detection,
   which is where most of the time goes); without a mask, inside the pixels standing off the
   dominant plane (`gscan.scan.segment.off_plane_region`: the table top, whose texture would otherwise
   take most of the keypoints), or the whole frame when there is no such plane.
2. retrieval: one GEMM of the query descriptors against the template's stacked descriptors
   (normalised once at load); every query keypoint whose nearest template descriptor is closer than
   `retrieval_dist` (unit descriptors, RootSIFT; `eps_f` for SIFT and ORB) votes for that descriptor's
   view; the top-`top_k` views by votes are kept.
3. match: GMatch (gscan.matching.gmatch) of each retrieved view's keypoints, expressed in THAT view's camera
   frame (view direction +z), against the query keypoints (+z); descriptor distances are sliced
   from the retrieval GEMM, never recomputed.
4. solve: Kabsch on the best view's match list (object-frame template points -> query camera points);
   the view with the most matches wins (ties: lower GMatch cost). Every retrieved view is matched:
   stopping at the first full-length list saved ~40 % of the match time but let a look-alike
   distractor win ties that the cost decides (BENCHMARKS.md).
5. refine: point-to-plane ICP (`icp_point_to_plane`, deterministic, template normals) of the
   template cloud's points visible from the predicted pose onto the query cloud cropped to a sphere
   of 1.2 object radii around the predicted centre and, without a mask, to the off-plane pixels. A
   given mask does not crop it: ICP pairs the template's whole visible surface with the query, and a
   mask that clips the silhouette (eroded, or cut by an occluder) pulled the pose toward the cut
   (held-out sample frames, true, eroded and half masks: 0.3-5.6 mm with the mask crop, 0.3-2.0 mm
   without, BENCHMARKS.md).
   A refinement that moves the pose by more than the object radius or 30 degrees is discarded.
6. score: the visible template cloud is projected into the query depth; score = consistent /
   (consistent + see-through) points, where "consistent" is |z_query - z_pred| < tol and
   "see-through" means the query surface lies behind the predicted object (occluded points, with
   query depth in front, count for neither). Not found (T_cam_obj None, `reason`) when the best
   list has fewer than `min_matches` matches, the score is below `min_score`, or too few visible
   points are confirmed by the depth.
7. support plane (without a mask): when the frame has a dominant plane (`gscan.scan.segment.support_plane`),
   a pose that puts more than `max_below_frac` of the template's points deeper than `below_tol` into it
   is not found (an object rests on the table; such a pose fits the object's print to the table's
   texture, its face flush with the table top, and the depth agrees), unless most of the plane lies
   inside the pose's silhouette (then the plane is the object's own face). Applies to PnP poses too.

Without usable query depth (valid fraction of the search region < `min_depth_frac`) the pose is
solved 2D-3D: the query keypoints are detected without depth lifting, matched by descriptor
(nearest + ratio test within each retrieved view; a keypoint matched in several views keeps its
closest match, so inliers count distinct keypoints) to the template's object-frame points, and the
pose is estimated by LO-RANSAC PnP + refinement (pycolmap `estimate_and_refine_absolute_pose`);
score = inlier fraction. No ICP in that mode. The same 2D-3D solve is tried after a failed 3D-3D
estimate on the search region's holes in the depth (`pnp_in_holes`; holes a 15 px square fits in, at least
`hole_min_frac` of the region): a dark, shiny or transparent object leaves a hole in otherwise good depth,
its keypoints cannot be lifted, and GMatch sees only the background (held-out sample frames with the
object's depth erased: found in 4 of 4, <= 0.5 deg / 0.6 mm from the full-depth pose). Such a pose is
refused when the measured depth would be seen through more than `max_see_through` of the object.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from gscan.io.camera import Intrinsics, RGBDFrame, backproject
from gscan.errors import InputError
from gscan.features import (OBJECT_FEATURES, FeatureParams, Features, descriptor_distances, empty_features,
                            extract_features, extract_features_in_mask)
from gscan.geometry.kabsch import kabsch_trimmed
from gscan.geometry.transforms import inv_T, transform_points
from gscan.matching.gmatch import GMatchParams, default_eps_f, gmatch
from gscan.geometry.icp import icp_point_to_plane
from gscan.geometry.pointset import coincident_groups, pca_normals, voxel_down_indices, voxel_mean
from gscan.geometry.plane import Plane
from gscan.scan.segment import in_front_of, support_plane
from gscan.template.db import Template, open_template

log = logging.getLogger(__name__)

STAGES = ("features", "retrieval", "match", "solve", "refine", "total")


@dataclass(frozen=True)
class EstimateParams:
    # query keypoints (kind follows the template's), the same settings as the template's object keypoints
    features: FeatureParams = OBJECT_FEATURES
    gmatch: GMatchParams = GMatchParams()  # matcher parameters (eps_f None -> default of the kind)
    top_k: int = 4  # template views retrieved and matched
    # stop matching retrieved views once one gives a full-length (L) GMatch list (only a lower-cost
    # tie could replace it). Off: it saves 2-3 searches (masked 75 -> 45 ms on the sample) but took a
    # near-identical distractor product in 1 of 84 benchmark scenes that the full search got right
    stop_at_full_length: bool = False
    retrieval_dist: float = 0.5  # descriptor distance under which a query keypoint votes for a view (RootSIFT L2)
    min_matches: int = 14  # fewer GMatch matches -> not found (bench: correct lists >= 15, wrong ones <= 13)
    min_score: float = 0.6  # depth-consistency score below this -> not found
    min_confirmed: float = 0.15  # fraction of visible template points confirmed by depth below this -> not found
    trim_tau: float = 0.008  # m, the match list's pose drops pairs off by more (gscan.geometry.transforms.kabsch_trimmed)
    icp_max_dist: float = 0.005  # m, ICP correspondence distance
    icp_voxel: float = 0.003  # m, template cloud downsampling (ICP source, score)
    icp_target_voxel: float = 0.004  # m, query cloud voxel averaging (ICP target)
    icp_iterations: int = 20
    icp_max_points: int = 1500  # source (template) points used by ICP, evenly subsampled
    crop_margin: int = 16  # px around the mask's bounding box kept for detection
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


@dataclass
class EstimateResult:
    """Outcome of one estimate. T_cam_obj [4 x 4] or None (not found, see `reason`); grasps
    {name: T_cam_grasp [4 x 4]} = T_cam_obj @ T_obj_grasp (empty when not found); timings_ms per stage."""

    T_cam_obj: np.ndarray | None
    score: float
    n_matches: int
    view: str | None
    reason: str | None
    grasps: dict[str, np.ndarray] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)
    method: str = "gmatch"  # "gmatch" (3D-3D) | "pnp" (2D-3D, no usable depth)

    @property
    def found(self) -> bool:
        return self.T_cam_obj is not None

    def to_json(self) -> dict:
        """The `gscan estimate --json` object (the command-line contract's keys and "method": "gmatch" | "pnp");
        matrices as nested lists, metres."""
        def mat(T: np.ndarray | None) -> list[list[float]] | None:
            return None if T is None else [[float(x) for x in row] for row in np.asarray(T)]

        return {"T_cam_obj": mat(self.T_cam_obj), "score": float(self.score), "n_matches": int(self.n_matches),
                "view": self.view, "reason": self.reason, "grasps": {k: mat(v) for k, v in self.grasps.items()},
                "timings_ms": {k: float(self.timings_ms.get(k, 0.0)) for k in STAGES}, "method": self.method}


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
        self.kind = tpl.kind
        self.view_names = list(tpl.view_names)
        self.T_obj_cam = tpl.T_obj_cam  # [V x 4 x 4]
        self.points_obj = tpl.points_obj.astype(np.float64)
        desc = tpl.descriptors
        self.descriptors = np.ascontiguousarray(desc, dtype=np.float32 if self.kind != "orb" else np.uint8)
        self.unit = self.kind == "rootsift"
        V = len(self.view_names)
        self.offsets = np.asarray(tpl.view_offsets, dtype=np.int64)  # keypoints of view v: offsets[v]:offsets[v+1]
        self.kp_view = np.asarray(tpl.kp_view, dtype=np.int64)
        # view-camera-frame points of every keypoint (GMatch source side, view direction +z)
        self.points_cam = np.empty_like(self.points_obj)
        for v in range(V):
            a, b = self.offsets[v], self.offsets[v + 1]
            self.points_cam[a:b] = transform_points(inv_T(self.T_obj_cam[v]), self.points_obj[a:b])
        self.groups = [coincident_groups(self.points_obj[self.offsets[v]:self.offsets[v + 1]]) for v in range(V)]
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
        self.eps_f = params.gmatch.eps_f if params.gmatch.eps_f is not None else default_eps_f(self.kind)
        self._warm_up()

    def _warm_up(self) -> None:
        """Load the compiled kernels (numba's cache) now, on a few of the first view's keypoints matched to
        themselves with the estimate's own array types: otherwise the first estimate paid it (GMatch's: about
        170 ms on the sample, against 12 ms later; kabsch_trimmed's consensus, run with one pair moved 1 m
        off: a few hundred ms the first time a list needs it)."""
        a, b = self.offsets[0], min(self.offsets[1], self.offsets[0] + 8)
        if b - a < 4:
            return
        q = self.descriptors[a:b]
        S = q.astype(np.float32) @ q.T.astype(np.float32) if self.unit else descriptor_distances(q, q, self.kind)
        pts = self.points_cam[a:b]
        gmatch(pts, pts.astype(np.float32), self._dist(S), self.eps_f, self.params.gmatch)
        moved = np.array(pts, dtype=np.float64)
        moved[0] += 1.0
        kabsch_trimmed(pts, moved, self.params.trim_tau)

    @classmethod
    def from_path(cls, path: str | Path, params: EstimateParams = EstimateParams()) -> "Estimator":
        """Open a complete template database (InputError for a missing / partial / foreign file)."""
        return cls(open_template(path), params)

    # ------------------------------------------------------------------------------------------------
    def estimate(self, frame: RGBDFrame, mask: np.ndarray | None = None, refine: bool = True) -> EstimateResult:
        """Pose T_cam_obj of the template's object in `frame` (mask: optional [H x W] bool search region)."""
        t_all = time.perf_counter()
        tm: dict[str, float] = {k: 0.0 for k in STAGES}
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != frame.depth.shape:
                raise InputError(frame.source, f"mask is {mask.shape[1]}x{mask.shape[0]} but the frame is "
                                               f"{frame.depth.shape[1]}x{frame.depth.shape[0]}")
        region = mask if mask is not None else np.ones(frame.depth.shape, bool)
        n_region = int(region.sum())
        depth_frac = float(((frame.depth > 0) & region).sum()) / max(1, n_region)
        use_pnp = depth_frac < self.params.min_depth_frac

        t = time.perf_counter()
        plane = off_plane = None
        if mask is None and not use_pnp and self.params.remove_plane:  # a given mask is the search region
            plane = support_plane(frame, self.params.plane_min_frac, self.params.plane_iterations)
            off_plane = None if plane is None else in_front_of(frame, plane)
        search = mask if mask is not None else off_plane
        feats = self._features(frame, search, lift=not use_pnp)
        tm["features"] = _ms(t)
        if len(feats) < 3:
            res = self._fail(tm, t_all, "too few keypoints in the query frame" + (" mask" if mask is not None else ""))
        else:
            t = time.perf_counter()
            S, views = self._retrieve(feats.descriptors)
            tm["retrieval"] = _ms(t)
            if use_pnp:
                res = self._estimate_pnp(frame, feats, S, views, tm, t_all)
                if not res.found:
                    res.reason += " (query depth unusable)"
                return res
            res = self._estimate_gmatch(frame, feats, S, views, off_plane, refine, tm, t_all)
        if not res.found and not use_pnp:
            res = self._pnp_without_depth(frame, region, res, tm, t_all)
        return self._above(frame, plane, res, tm, t_all)

    def _above(self, frame: RGBDFrame, plane: Plane | None, res: EstimateResult, tm: dict[str, float],
               t_all: float) -> EstimateResult:
        """`res`, or not found when its pose sinks more than `max_below_frac` of the template's points deeper
        than `below_tol` into the frame's support plane (camera frame): an object rests on the table, and a
        pose that puts it inside matched the table's texture (a flat print of the object, look-alike print).
        Not applied when most of the plane's pixels lie inside the object's predicted silhouette: then the
        "plane" is the object's own face (a close-up)."""
        if not res.found or plane is None:
            return res
        below = float(np.mean(plane.height(transform_points(res.T_cam_obj, self.cloud_icp)) < -self.params.below_tol))
        if below <= self.params.max_below_frac:
            return res
        _, _, uv = self._visible(res.T_cam_obj, frame.intrinsics, self.cloud_icp)
        sil = np.zeros(frame.depth.shape, np.uint8)
        if len(uv) >= 3:
            cv2.fillConvexPoly(sil, cv2.convexHull(uv.astype(np.int32)), 1)
        P = backproject(frame.depth, frame.intrinsics)
        on_plane = (frame.depth > 0) & (np.abs(plane.height(P.reshape(-1, 3))).reshape(frame.depth.shape) < 0.01)
        if (on_plane & (sil > 0)).sum() > 0.5 * on_plane.sum():
            return res
        return self._fail(tm, t_all, f"pose puts {below:.0%} of the object inside the support plane", res.n_matches,
                          res.view, res.score, res.method)

    def _estimate_gmatch(self, frame: RGBDFrame, feats: Features, S: np.ndarray, views: list[int],
                         off_plane: np.ndarray | None, refine: bool, tm: dict[str, float],
                         t_all: float) -> EstimateResult:
        """Stages 3-6 (module docstring) on the lifted query keypoints."""
        t = time.perf_counter()
        best = None  # (n, -cost, view, matches)
        q_groups = coincident_groups(feats.points)
        for v in views:
            m, cost = self._match_view(int(v), S, feats, q_groups)
            n = len(m)
            if n >= 3 and (best is None or (n, -cost) > (best[0], best[1])):
                best = (n, -cost, int(v), m)
            if self.params.stop_at_full_length and n >= self.params.gmatch.L:
                break  # a full-length list: no later view can be longer (views in retrieval order)
        tm["match"] = _ms(t)
        if best is None or best[0] < self.params.min_matches:
            n = 0 if best is None else best[0]
            return self._fail(tm, t_all, f"too few geometrically consistent matches ({n} < {self.params.min_matches})",
                              n, None if best is None else self.view_names[best[2]])
        n, _, v, m = best
        a = self.offsets[v]
        t = time.perf_counter()
        T_cam_obj, _ = kabsch_trimmed(self.points_obj[a + m[:, 0]], feats.points[m[:, 1]].astype(np.float64),
                                      self.params.trim_tau)
        tm["solve"] = _ms(t)

        t = time.perf_counter()
        if refine:  # the ICP target is not cut by a given mask: a mask that clips the silhouette pulls ICP to the cut
            T_cam_obj = self._refine(frame, off_plane, T_cam_obj)
        score, confirmed = self._score(frame, T_cam_obj, off_plane)
        tm["refine"] = _ms(t)
        view = self.view_names[v]
        if score < self.params.min_score or confirmed < self.params.min_confirmed:
            return self._fail(tm, t_all, f"pose not confirmed by the depth (score {score:.2f}, "
                                         f"{confirmed:.0%} of visible surface confirmed)", n, view, score)
        return self._found(T_cam_obj, score, n, view, tm, t_all, "gmatch")

    # ------------------------------------------------------------------------------------------------
    def _match_view(self, v: int, S: np.ndarray, feats: Features,
                    q_groups: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, float]:
        """GMatch of template view `v` against the query: (matches [M x 2] (keypoint row within the view,
        query keypoint index), cost). S: the retrieval matrix [M_query x N_template]."""
        a, b = self.offsets[v], self.offsets[v + 1]
        s_order, s_starts = self.groups[v]
        q_order, q_starts = q_groups
        dist = self._dist(S[:, a:b]).T  # [Ns x Nt] template view -> query
        # keypoints sharing a 3D point (SIFT orientations of one location) are merged: min distance
        dist = np.minimum.reduceat(np.minimum.reduceat(dist[s_order][:, q_order], s_starts, axis=0), q_starts, axis=1)
        res = gmatch(self.points_cam[a + s_order[s_starts]], feats.points[q_order[q_starts]], dist, self.eps_f,
                     self.params.gmatch)
        m = np.stack([s_order[s_starts[res.matches[:, 0]]], q_order[q_starts[res.matches[:, 1]]]], 1)
        return m.reshape(-1, 2), float(res.cost)

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
        return extract_features_in_mask(frame, mask, fparams, self.params.crop_margin)

    def _retrieve(self, q: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """Query descriptors [M x D] -> (similarity or distance matrix [M x N], top-k view indices)."""
        if self.unit:
            S = q.astype(np.float32) @ self.descriptors.T  # cosine similarity of unit vectors
            nn = np.argmax(S, axis=1)
            ok = S[np.arange(len(S)), nn] >= 1.0 - 0.5 * self.params.retrieval_dist ** 2
        else:
            S = descriptor_distances(q, self.descriptors, self.kind)
            nn = np.argmin(S, axis=1)
            ok = S[np.arange(len(S)), nn] < self.eps_f
        # each query keypoint votes for the view holding its nearest template descriptor
        votes = np.bincount(self.kp_view[nn[ok]], minlength=len(self.view_names))
        order = np.lexsort((np.arange(len(votes)), -votes))  # most votes first, ties by view order
        views = [int(v) for v in order[: self.params.top_k] if votes[v] > 0]
        return S, views

    def _dist(self, S: np.ndarray) -> np.ndarray:
        """Similarity block (unit descriptors) or distance block -> L2/Hamming distances."""
        if self.unit:
            return np.sqrt(np.maximum(2.0 - 2.0 * S, 0.0))
        return S

    def _visible(self, T_cam_obj: np.ndarray, intr: Intrinsics, pts: np.ndarray, cell: int = 4,
                 tol: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Template points [P x 3] visible from the camera at T_cam_obj (coarse z-buffer of `cell` px).
        Returns (indices [K], camera points [K x 3], integer pixels [K x 2])."""
        pc = transform_points(T_cam_obj, pts)
        z = pc[:, 2]
        ok = z > 1e-3
        u = np.full(len(pc), -1.0)
        v = np.full(len(pc), -1.0)
        u[ok] = pc[ok, 0] / z[ok] * intr.fx + intr.cx
        v[ok] = pc[ok, 1] / z[ok] * intr.fy + intr.cy
        ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
        ok &= (ui >= 0) & (ui < intr.width) & (vi >= 0) & (vi < intr.height)
        idx = np.flatnonzero(ok)
        gw, gh = (intr.width + cell - 1) // cell, (intr.height + cell - 1) // cell
        cid = (vi[idx] // cell) * gw + ui[idx] // cell
        zbuf = np.full(gw * gh, np.inf)
        np.minimum.at(zbuf, cid, z[idx])
        vis = z[idx] <= zbuf[cid] + tol + 0.01 * z[idx]
        idx = idx[vis]
        return idx, pc[idx], np.stack([ui[idx], vi[idx]], 1)

    def _refine(self, frame: RGBDFrame, region: np.ndarray | None, T_cam_obj: np.ndarray) -> np.ndarray:
        """Point-to-plane ICP of the visible template cloud onto the query cloud cropped to `region`
        ([H x W] bool, or None) and to a sphere around the predicted object."""
        p = self.params
        idx, _, _ = self._visible(T_cam_obj, frame.intrinsics, self.cloud_icp)
        if len(idx) < 30:
            return T_cam_obj
        st = (slice(None, None, 2), slice(None, None, 2))  # every 2nd pixel: ~2 mm spacing at 0.6 m, ample for ICP
        valid = frame.depth[st] > 0
        if region is not None:
            valid &= region[st]
        tgt = backproject(frame.depth, frame.intrinsics)[st][valid]
        c = transform_points(T_cam_obj, self.center[None])[0]
        tgt = tgt[np.linalg.norm(tgt - c, axis=1) < 1.2 * self.radius + p.icp_max_dist]
        if len(tgt) < 30:
            return T_cam_obj
        tgt = voxel_mean(tgt, p.icp_target_voxel)  # averaging, not picking: depth noise shrinks
        idx = idx[:: max(1, int(np.ceil(len(idx) / p.icp_max_points)))]
        T, fitness = icp_point_to_plane(self.cloud_icp[idx], self.normals_icp[idx], tgt, T_cam_obj, p.icp_max_dist,
                                        p.icp_iterations)
        dR = T[:3, :3] @ T_cam_obj[:3, :3].T
        moved = np.linalg.norm(T[:3, 3] - T_cam_obj[:3, 3])
        if fitness <= 0 or moved > self.radius or np.trace(dR) < 1.0 + 2.0 * np.cos(np.radians(30)):
            log.debug("ICP rejected (fitness %.2f, moved %.3f m)", fitness, moved)
            return T_cam_obj
        return T

    def _score(self, frame: RGBDFrame, T_cam_obj: np.ndarray, region: np.ndarray | None = None) -> tuple[float, float]:
        """(score, confirmed) of the visible template cloud at T_cam_obj: score = consistent /
        (consistent + see-through), confirmed = consistent / visible. With `region` ([H x W] bool, the
        off-plane pixels) a point only counts as consistent inside it."""
        n_c, n_b, n = self._depth_votes(frame, T_cam_obj, region)
        return n_c / max(1, n_c + n_b), n_c / max(1, n)

    def _depth_votes(self, frame: RGBDFrame, T_cam_obj: np.ndarray, region: np.ndarray | None = None
                     ) -> tuple[int, int, int]:
        """(consistent, see-through, visible) counts of the template cloud's points visible at T_cam_obj:
        consistent when the query depth agrees within the tolerance, see-through when the query surface lies
        behind the predicted object (a point over a pixel without depth counts for neither)."""
        _, pc, uv = self._visible(T_cam_obj, frame.intrinsics, self.cloud_icp)
        if len(pc) == 0:
            return 0, 0, 0
        zq = frame.depth[uv[:, 1], uv[:, 0]].astype(np.float64)
        z = pc[:, 2]
        tol = self.params.depth_tol + 0.02 * np.maximum(z - 0.5, 0.0)
        has = zq > 0
        consistent = has & (np.abs(zq - z) < tol)
        if region is not None:
            consistent &= region[uv[:, 1], uv[:, 0]]
        behind = has & (zq > z + tol)
        return int(consistent.sum()), int(behind.sum()), len(pc)

    def _pnp_without_depth(self, frame: RGBDFrame, region: np.ndarray, failed: EstimateResult,
                           tm: dict[str, float], t_all: float) -> EstimateResult:
        """After a failed 3D-3D estimate: 2D-3D PnP on the search region's pixels without depth (dilated by
        `hole_dilate_px`), where a dark, shiny or transparent object leaves holes in otherwise good depth and its
        keypoints were dropped unlifted. Returns the PnP result when it finds the object, else `failed` with
        PnP's reason appended. Skipped when less than `hole_min_frac` of the region lacks depth."""
        p = self.params
        if not p.pnp_in_holes:
            return failed
        # holes an object could leave: opening drops speckle and the thin bands of stereo shadows
        k = 2 * p.hole_open_px + 1
        holes = cv2.morphologyEx(((frame.depth <= 0) & region).astype(np.uint8), cv2.MORPH_OPEN,
                                 np.ones((k, k), np.uint8))
        frac = float(holes.sum()) / max(1, int(region.sum()))
        if frac < p.hole_min_frac:
            return failed
        k = 2 * p.hole_dilate_px + 1
        holes = cv2.dilate(holes, np.ones((k, k), np.uint8)).astype(bool) & region
        t = time.perf_counter()
        feats = self._features(frame, holes, lift=False)
        tm["features"] += _ms(t)
        pnp_tm = {key: 0.0 for key in STAGES}
        if len(feats) >= 3:
            t = time.perf_counter()
            S, views = self._retrieve(feats.descriptors)
            tm["retrieval"] += _ms(t)
            res = self._estimate_pnp(frame, feats, S, views, pnp_tm, t_all)
        else:
            res = self._fail(pnp_tm, t_all, "too few keypoints", method="pnp")
        for key in ("match", "solve"):
            tm[key] += pnp_tm[key]
        if res.found:  # the object has no depth, but the depth around it must not be seen through it
            _, n_b, n = self._depth_votes(frame, res.T_cam_obj)
            if n_b > p.max_see_through * n:
                res = self._fail(pnp_tm, t_all, f"its pose would let the depth be seen through "
                                 f"{n_b / max(1, n):.0%} of the object", method="pnp")
        tm["total"] = _ms(t_all)
        res.timings_ms = tm
        if res.found:
            return res
        failed.reason = f"{failed.reason}; PnP on the {frac:.0%} of pixels without depth: {res.reason}"
        return failed

    # ------------------------------------------------------------------------------------------------
    def _estimate_pnp(self, frame: RGBDFrame, feats: Features, S: np.ndarray, views: list[int],
                      tm: dict[str, float], t_all: float) -> EstimateResult:
        import pycolmap

        p = self.params
        t = time.perf_counter()
        q_idx, t_idx, d_best = [], [], []
        for v in views:
            a, b = self.offsets[v], self.offsets[v + 1]
            if b - a < 2:
                continue
            D = self._dist(S[:, a:b])  # [M x Nv]
            two = np.argpartition(D, 1, axis=1)[:, :2]
            d2 = np.take_along_axis(D, two, axis=1)
            o = np.argsort(d2, axis=1)
            d1, dn = np.take_along_axis(d2, o, 1)[:, 0], np.take_along_axis(d2, o, 1)[:, 1]
            j = np.take_along_axis(two, o, 1)[:, 0]
            ok = (d1 < p.pnp_ratio * dn) & (d1 < self.eps_f)
            q_idx.append(np.flatnonzero(ok))
            t_idx.append(a + j[ok])
            d_best.append(d1[ok])
        if q_idx:  # one 2D-3D match per query keypoint (its closest over the views), so inliers count keypoints
            qi, ti, d = np.concatenate(q_idx), np.concatenate(t_idx), np.concatenate(d_best)
            o = np.lexsort((np.arange(len(qi)), d, qi))
            first = np.ones(len(o), bool)
            first[1:] = qi[o][1:] != qi[o][:-1]
            keep = np.sort(o[first])
            qi, ti = qi[keep], ti[keep]
        tm["match"] = _ms(t)
        if not q_idx or len(qi) < p.pnp_min_inliers:
            return self._fail(tm, t_all, "too few 2D-3D matches for PnP", method="pnp")
        t = time.perf_counter()
        intr = frame.intrinsics
        cam = pycolmap.Camera(model="PINHOLE", width=intr.width, height=intr.height,
                              params=[intr.fx, intr.fy, intr.cx, intr.cy])
        opts = pycolmap.AbsolutePoseEstimationOptions()
        opts.ransac.max_error = p.pnp_max_error_px
        opts.ransac.random_seed = 0
        res = pycolmap.estimate_and_refine_absolute_pose(feats.pixels[qi].astype(np.float64),
                                                        self.points_obj[ti], cam, opts)
        tm["solve"] = _ms(t)
        n = 0 if res is None else int(res["num_inliers"])
        if n < p.pnp_min_inliers or n < p.pnp_min_inlier_ratio * len(qi):
            return self._fail(tm, t_all, f"PnP found too few inliers ({n} of {len(qi)} 2D-3D matches)", n,
                              score=n / len(qi), method="pnp")
        T = np.eye(4)
        T[:3, :] = np.asarray(res["cam_from_world"].matrix())
        inl = np.asarray(res["inlier_mask"], bool)
        n = int(inl.sum())
        votes = np.bincount(self.kp_view[ti[inl]], minlength=len(self.view_names))
        return self._found(T, n / len(qi), n, self.view_names[int(np.argmax(votes))], tm, t_all, "pnp")

    def _found(self, T: np.ndarray, score: float, n: int, view: str, tm: dict[str, float], t_all: float,
               method: str) -> EstimateResult:
        tm["total"] = _ms(t_all)
        grasps = {k: T @ G for k, G in self.grasps.items()}
        return EstimateResult(T, float(score), int(n), view, None, grasps, tm, method)

    def _fail(self, tm: dict[str, float], t_all: float, reason: str, n: int = 0, view: str | None = None,
              score: float = 0.0, method: str = "gmatch") -> EstimateResult:
        tm["total"] = _ms(t_all)
        log.info("not found: %s", reason)
        return EstimateResult(None, float(score), int(n), view, reason, {}, tm, method)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
