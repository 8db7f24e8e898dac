"""2D-3D pose when the depth cannot lift the object's keypoints.

Without usable query depth the query keypoints are detected without depth lifting, matched by descriptor (nearest +
ratio test within each retrieved view; a keypoint matched in several views keeps its closest match, so inliers count
distinct keypoints) to the template's object-frame points, and the pose is estimated by LO-RANSAC PnP + refinement
(pycolmap `estimate_and_refine_absolute_pose`); score = inlier fraction. No ICP in that mode.

The same 2D-3D solve is tried after a failed 3D-3D estimate on the search region's holes in the depth (holes a (2
`holes.open_px` + 1)-pixel square fits in, at least `holes.min_frac` of the region): a dark, shiny or transparent
object leaves a hole in otherwise good depth, its keypoints cannot be lifted, and GMatch sees only the background.
Such a pose is refused when the measured depth would be seen through more than `holes.max_see_through` of the object.
"""
from __future__ import annotations

import cv2
import numpy as np

from gscan.estimate.params import EstimateParams, PnPParams
from gscan.estimate.query import QueryFrame, query_features
from gscan.estimate.result import EstimateResult, found, not_found
from gscan.estimate.retrieval import TemplateIndex
from gscan.estimate.verify import depth_votes
from gscan.features import Features
from gscan.features.depth import joint_features
from gscan.features.keypoints import JOINT
from gscan.io.camera import RGBDFrame
from gscan.progress import StageTimer


def pnp_without_depth(index: TemplateIndex, samples: np.ndarray, q: QueryFrame, failed: EstimateResult,
                      params: EstimateParams, timer: StageTimer,
                      exclude: np.ndarray | None = None) -> EstimateResult:
    """After a failed 3D-3D estimate: 2D-3D PnP on the search region's pixels without depth (dilated by
    `holes.dilate_px`). samples [S x 3]: the template surface (object frame) the see-through check projects;
    exclude: [H x W] bool pixels left out of the holes (those a pose found already explains). Returns the PnP
    result when it finds the object, else `failed` with PnP's reason appended. Skipped when less than
    `holes.min_frac` of the region lacks depth."""
    p = params.holes
    if not p.enabled:
        return failed
    frame, region = q.frame, q.region
    if exclude is not None:
        region = region & ~exclude
    # holes an object could leave: opening drops speckle and the thin bands of stereo shadows
    k = 2 * p.open_px + 1
    holes = cv2.morphologyEx(((frame.depth <= 0) & region).astype(np.uint8), cv2.MORPH_OPEN,
                             np.ones((k, k), np.uint8))
    frac = float(holes.sum()) / max(1, int(region.sum()))
    if frac < p.min_frac:
        return failed
    k = 2 * p.dilate_px + 1
    holes = cv2.dilate(holes, np.ones((k, k), np.uint8)).astype(bool) & region
    with timer.stage("features"):
        feats = query_features(frame, holes, params.features, params.query, lift=False)
        if index.kind == JOINT:  # the template's joint set: the image's keypoints alone (the holes have no depth)
            feats = joint_features(feats, None)
    if len(feats) >= 3:
        with timer.stage("retrieval"):
            r = index.retrieve(feats.descriptors)
        res = estimate_pnp(index, frame, feats, r.S, index.top_views(r.votes), params.pnp, timer)
    else:
        res = not_found("too few keypoints", method="pnp")
    if res.T_cam_obj is not None:  # the object has no depth, but the depth around it must not be seen through it
        _, n_b, n = depth_votes(frame.depth, frame.intrinsics, res.T_cam_obj, samples, params.verify.depth_tol)
        if n_b > p.max_see_through * n:
            res = not_found(f"its pose would let the depth be seen through {n_b / max(1, n):.0%} of the object",
                            method="pnp")
    if res.found:
        return res
    failed.reason = f"{failed.reason}; PnP on the {frac:.0%} of pixels without depth: {res.reason}"
    return failed


def estimate_pnp(index: TemplateIndex, frame: RGBDFrame, feats: Features, S: np.ndarray, views: list[int],
                 params: PnPParams, timer: StageTimer) -> EstimateResult:
    """2D-3D matches of the query keypoints [M] to the retrieved views' keypoints, then LO-RANSAC PnP (module
    docstring). S: the retrieval matrix [M x N] (`TemplateIndex.retrieve`); views: the views matched."""
    import pycolmap

    with timer.stage("match"):
        qi, ti = _matches_2d3d(index, S, views, params.ratio)
    if len(qi) < params.min_inliers:
        return not_found("too few 2D-3D matches for PnP", method="pnp")
    with timer.stage("solve"):
        intr = frame.intrinsics
        cam = pycolmap.Camera(model="PINHOLE", width=intr.width, height=intr.height,
                              params=[intr.fx, intr.fy, intr.cx, intr.cy])
        opts = pycolmap.AbsolutePoseEstimationOptions()
        opts.ransac.max_error = params.max_error_px
        opts.ransac.random_seed = 0
        res = pycolmap.estimate_and_refine_absolute_pose(feats.pixels[qi].astype(np.float64), index.points_obj[ti],
                                                        cam, opts)
    n = 0 if res is None else int(res["num_inliers"])
    if res is None or n < params.min_inliers or n < params.min_inlier_ratio * len(qi):
        return not_found(f"PnP found too few inliers ({n} of {len(qi)} 2D-3D matches)", n, score=n / len(qi),
                         method="pnp")
    T = np.eye(4)
    T[:3, :] = np.asarray(res["cam_from_world"].matrix())
    inl = np.asarray(res["inlier_mask"], dtype=np.bool_)
    n = int(inl.sum())
    votes = np.bincount(index.kp_view[ti[inl]], minlength=len(index.view_names))
    return found(T, n / len(qi), n, index.view_names[int(np.argmax(votes))], "pnp")


def _matches_2d3d(index: TemplateIndex, S: np.ndarray, views: list[int], ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(query keypoints [K], template keypoints [K]): each query keypoint's nearest keypoint within each view by
    descriptor, passing the ratio test and eps_f; a keypoint matched in several views keeps its closest match,
    so that inliers count query keypoints."""
    q_idx, t_idx, d_best = [], [], []
    for v in views:
        a, b = index.offsets[v], index.offsets[v + 1]
        if b - a < 2:
            continue
        D = index.distances(S[:, a:b])  # [M x Nv]
        two = np.argpartition(D, 1, axis=1)[:, :2]
        d2 = np.take_along_axis(D, two, axis=1)
        o = np.argsort(d2, axis=1)
        d1, dn = np.take_along_axis(d2, o, 1)[:, 0], np.take_along_axis(d2, o, 1)[:, 1]
        j = np.take_along_axis(two, o, 1)[:, 0]
        ok = (d1 < ratio * dn) & (d1 < index.eps_f)
        q_idx.append(np.flatnonzero(ok))
        t_idx.append(a + j[ok])
        d_best.append(d1[ok])
    qi = ti = np.zeros(0, np.int64)
    if q_idx:  # one 2D-3D match per query keypoint (its closest over the views)
        qi, ti, d = np.concatenate(q_idx), np.concatenate(t_idx), np.concatenate(d_best)
        o = np.lexsort((np.arange(len(qi)), d, qi))
        first = np.ones(len(o), bool)
        first[1:] = qi[o][1:] != qi[o][:-1]
        keep = np.sort(o[first])
        qi, ti = qi[keep], ti[keep]
    return qi, ti
