"""2D-3D pose when the depth cannot lift the object's keypoints.

Without usable query depth the query keypoints are detected without depth lifting, matched by descriptor
(nearest + ratio test within each retrieved view; a keypoint matched in several views keeps its closest
match, so inliers count distinct keypoints) to the template's object-frame points, and the pose is estimated
by LO-RANSAC PnP + refinement (pycolmap `estimate_and_refine_absolute_pose`); score = inlier fraction. No ICP
in that mode.

The same 2D-3D solve is tried after a failed 3D-3D estimate on the search region's holes in the depth (holes
a 15 px square fits in, at least `hole_min_frac` of the region): a dark, shiny or transparent object leaves a
hole in otherwise good depth, its keypoints cannot be lifted, and GMatch sees only the background. Such a pose
is refused when the measured depth would be seen through more than `max_see_through` of the object.
"""
from __future__ import annotations

import time
from typing import Any, Protocol

import cv2
import numpy as np

from gscan.estimate.query import QueryFrame
from gscan.estimate.result import STAGES, EstimateResult, ms_since
from gscan.estimate.verify import depth_votes
from gscan.features import Features
from gscan.io.camera import RGBDFrame


class Estimator(Protocol):
    """What the fallback uses of `gscan.estimate.estimator.Estimator` (which calls it: the estimator imports
    this module, not the other way round)."""

    params: Any
    eps_f: float
    kp_view: np.ndarray
    offsets: np.ndarray
    points_obj: np.ndarray
    cloud_icp: np.ndarray
    view_names: list[str]

    def _features(self, frame: RGBDFrame, mask: np.ndarray | None, lift: bool) -> Features: ...
    def _retrieve(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def _top_views(self, votes: np.ndarray) -> list[int]: ...
    def _dist(self, S: np.ndarray) -> np.ndarray: ...
    def _found(self, T: np.ndarray, score: float, n: int, view: str, tm: dict[str, float], t_all: float,
               method: str) -> EstimateResult: ...
    def _fail(self, tm: dict[str, float], t_all: float, reason: str, n: int = 0, view: str | None = None,
              score: float = 0.0, method: str = "gmatch") -> EstimateResult: ...


def pnp_without_depth(est: Estimator, q: QueryFrame, failed: EstimateResult, tm: dict[str, float],
                      t_all: float) -> EstimateResult:
    """After a failed 3D-3D estimate: 2D-3D PnP on the search region's pixels without depth (dilated by
    `hole_dilate_px`). Returns the PnP result when it finds the object, else `failed` with PnP's reason
    appended. Skipped when less than `hole_min_frac` of the region lacks depth."""
    p = est.params
    if not p.pnp_in_holes:
        return failed
    frame, region = q.frame, q.region
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
    feats = est._features(frame, holes, lift=False)
    tm["features"] += ms_since(t)
    pnp_tm = dict.fromkeys(STAGES, 0.0)
    if len(feats) >= 3:
        t = time.perf_counter()
        S, votes = est._retrieve(feats.descriptors)
        tm["retrieval"] += ms_since(t)
        res = estimate_pnp(est, frame, feats, S, est._top_views(votes), pnp_tm, t_all)
    else:
        res = est._fail(pnp_tm, t_all, "too few keypoints", method="pnp")
    for key in ("match", "solve"):
        tm[key] += pnp_tm[key]
    if res.T_cam_obj is not None:  # the object has no depth, but the depth around it must not be seen through it
        _, n_b, n = depth_votes(frame.depth, frame.intrinsics, res.T_cam_obj, est.cloud_icp, p.depth_tol)
        if n_b > p.max_see_through * n:
            res = est._fail(pnp_tm, t_all, f"its pose would let the depth be seen through "
                            f"{n_b / max(1, n):.0%} of the object", method="pnp")
    tm["total"] = ms_since(t_all)
    res.timings_ms = tm
    if res.found:
        return res
    failed.reason = f"{failed.reason}; PnP on the {frac:.0%} of pixels without depth: {res.reason}"
    return failed


def estimate_pnp(est: Estimator, frame: RGBDFrame, feats: Features, S: np.ndarray, views: list[int],
                 tm: dict[str, float], t_all: float) -> EstimateResult:
    """2D-3D matches of the query keypoints to the retrieved views' keypoints, then LO-RANSAC PnP (module
    docstring). S: the retrieval matrix [M_query x N_template]."""
    import pycolmap

    p = est.params
    t = time.perf_counter()
    q_idx, t_idx, d_best = [], [], []
    for v in views:
        a, b = est.offsets[v], est.offsets[v + 1]
        if b - a < 2:
            continue
        D = est._dist(S[:, a:b])  # [M x Nv]
        two = np.argpartition(D, 1, axis=1)[:, :2]
        d2 = np.take_along_axis(D, two, axis=1)
        o = np.argsort(d2, axis=1)
        d1, dn = np.take_along_axis(d2, o, 1)[:, 0], np.take_along_axis(d2, o, 1)[:, 1]
        j = np.take_along_axis(two, o, 1)[:, 0]
        ok = (d1 < p.pnp_ratio * dn) & (d1 < est.eps_f)
        q_idx.append(np.flatnonzero(ok))
        t_idx.append(a + j[ok])
        d_best.append(d1[ok])
    qi = ti = np.zeros(0, np.int64)
    if q_idx:  # one 2D-3D match per query keypoint (its closest over the views), so inliers count keypoints
        qi, ti, d = np.concatenate(q_idx), np.concatenate(t_idx), np.concatenate(d_best)
        o = np.lexsort((np.arange(len(qi)), d, qi))
        first = np.ones(len(o), bool)
        first[1:] = qi[o][1:] != qi[o][:-1]
        keep = np.sort(o[first])
        qi, ti = qi[keep], ti[keep]
    tm["match"] = ms_since(t)
    if len(qi) < p.pnp_min_inliers:
        return est._fail(tm, t_all, "too few 2D-3D matches for PnP", method="pnp")
    t = time.perf_counter()
    intr = frame.intrinsics
    cam = pycolmap.Camera(model="PINHOLE", width=intr.width, height=intr.height,
                          params=[intr.fx, intr.fy, intr.cx, intr.cy])
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = p.pnp_max_error_px
    opts.ransac.random_seed = 0
    res = pycolmap.estimate_and_refine_absolute_pose(feats.pixels[qi].astype(np.float64), est.points_obj[ti], cam,
                                                    opts)
    tm["solve"] = ms_since(t)
    n = 0 if res is None else int(res["num_inliers"])
    if res is None or n < p.pnp_min_inliers or n < p.pnp_min_inlier_ratio * len(qi):
        return est._fail(tm, t_all, f"PnP found too few inliers ({n} of {len(qi)} 2D-3D matches)", n,
                         score=n / len(qi), method="pnp")
    T = np.eye(4)
    T[:3, :] = np.asarray(res["cam_from_world"].matrix())
    inl = np.asarray(res["inlier_mask"], dtype=np.bool_)
    n = int(inl.sum())
    votes = np.bincount(est.kp_view[ti[inl]], minlength=len(est.view_names))
    return est._found(T, n / len(qi), n, est.view_names[int(np.argmax(votes))], tm, t_all, "pnp")
