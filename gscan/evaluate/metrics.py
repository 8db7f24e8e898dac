"""Pose and trajectory error metrics: rotation / translation error, ATE, ADD, ADD-S, AUC,
VSD, MSSD, MSPD and BOP recall.

Poses are [4 x 4] rigid transforms. For object metrics `T_est` / `T_gt` are T_cam_obj
(model points `pts` [N x 3] in the object frame, metres); for ATE they are T_world_cam.

References:
- ADD / ADD-S: Hinterstoisser et al., ACCV 2012 (`add`, `adi` in bop_toolkit_lib/pose_error.py).
- AUC: the YCB-Video toolbox of PoseCNN (Xiang et al., RSS 2018), `VOCap` in its MATLAB
  evaluation scripts, reproduced exactly (see `auc`).
- MSSD / MSPD and the recall thresholds: BOP Challenge 2019+ (bop_toolkit_lib/pose_error.py,
  scripts/eval_bop19_pose.py): an error counts as correct when strictly below a threshold.
- VSD (Visible Surface Discrepancy): Hodan et al., "On Evaluation of 6D Object Pose Estimation", ECCVW 2016,
  with the step cost of the SIXD / BOP challenges and BOP19's settings: visibility tolerance delta = 15 mm,
  a pixel with no measured depth counts as visible ("bop19" visibility), misalignment tolerances
  tau = 0.05..0.5 x the object diameter, correctness thresholds 0.05..0.5 on the error.
"""
from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gscan.geometry.kabsch import umeyama
from gscan.geometry.transforms import inv_T, rotation_angle_deg, transform_points
from gscan.io.camera import Intrinsics

#: BOP MSSD thresholds, as fractions of the object diameter: 0.05, 0.10, ..., 0.50.
MSSD_THRESHOLD_FRACTIONS = np.round(np.arange(0.05, 0.51, 0.05), 10)
#: BOP MSPD thresholds in pixels for a 640-pixel-wide image: 5, 10, ..., 50.
MSPD_THRESHOLDS_PX_640 = np.arange(5.0, 51.0, 5.0)
#: BOP19 VSD misalignment tolerances tau, as fractions of the object diameter: 0.05, 0.10, ..., 0.50.
VSD_TAU_FRACTIONS = np.round(np.arange(0.05, 0.51, 0.05), 10)
#: BOP19 VSD correctness thresholds on the error (a fraction of the visible surface): 0.05, ..., 0.50.
VSD_THRESHOLDS = np.round(np.arange(0.05, 0.51, 0.05), 10)
#: BOP19 VSD visibility tolerance (m): a model pixel more than this behind the measured surface is occluded.
VSD_DELTA_M = 0.015
#: Where VSD's model renders sample each pixel (added to its integer coordinates, `MeshRaycaster.depth`'s
#: pixel_offset): the BOP toolkit's renderers project with OpenGL from K, which samples pixel (u, v) at
#: (u + 0.5, v + 0.5); rendering there gives its silhouettes pixel for pixel, and so its VSD errors.
VSD_RENDER_PIXEL_OFFSET = 0.5


def _as_T(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite [4 x 4] transform, got shape {T.shape}")
    return T


def _as_pts(pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"model points must be a non-empty [N x 3] array, got shape {pts.shape}")
    return pts


def rotation_error_deg(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Angle of R_est R_gt^T in degrees, [0, 180]. Accepts [3 x 3] rotations or [4 x 4] poses."""
    R_e = np.asarray(T_est, dtype=np.float64)[:3, :3]
    R_g = np.asarray(T_gt, dtype=np.float64)[:3, :3]
    return rotation_angle_deg(R_e @ R_g.T)


def translation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """|t_est - t_gt| in metres for [4 x 4] poses."""
    return float(np.linalg.norm(_as_T(T_est, "T_est")[:3, 3] - _as_T(T_gt, "T_gt")[:3, 3]))


@dataclass
class ATEResult:
    """Absolute trajectory error after rigid alignment of the estimate onto the ground truth.

    errors: [N] per-pose position errors (m); T_gt_est: [4 x 4] alignment applied to the
    estimated positions (p_gt ~ T_gt_est @ p_est).
    """

    rmse: float
    mean: float
    median: float
    max: float
    errors: np.ndarray
    T_gt_est: np.ndarray


def ate(T_est_list: Sequence[np.ndarray], T_gt_list: Sequence[np.ndarray]) -> ATEResult:
    """ATE of camera positions: rigid (no scale) Umeyama alignment of the estimated positions
    onto the ground-truth ones, then per-pose Euclidean errors. Inputs: lists of [4 x 4]
    T_world_cam in matching order (N >= 1; N = 1 and 2 are solved in closed form)."""
    if len(T_est_list) != len(T_gt_list) or len(T_est_list) == 0:
        raise ValueError(f"need two equally long non-empty pose lists, got {len(T_est_list)} and {len(T_gt_list)}")
    p_est = np.array([_as_T(T, "T_est")[:3, 3] for T in T_est_list])
    p_gt = np.array([_as_T(T, "T_gt")[:3, 3] for T in T_gt_list])
    n = len(p_est)
    if n >= 3:
        T = umeyama(p_est, p_gt, with_scale=False)
    else:  # translate centroids together; for two poses also turn the segment onto the other
        R = np.eye(3)
        if n == 2:
            a, b = p_est[1] - p_est[0], p_gt[1] - p_gt[0]
            if np.linalg.norm(a) > 1e-12 and np.linalg.norm(b) > 1e-12:
                R = umeyama(np.stack([np.zeros(3), a, _perp(a)]), np.stack([np.zeros(3), b, _perp(b)]))[:3, :3]
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = p_gt.mean(0) - R @ p_est.mean(0)
    err = np.linalg.norm(transform_points(T, p_est) - p_gt, axis=1)
    return ATEResult(float(np.sqrt(np.mean(err ** 2))), float(err.mean()), float(np.median(err)), float(err.max()),
                     err, T)


@dataclass
class FrameErrors:
    """Per-frame pose errors of a registered trajectory, free of the choice of world frame.

    rot_deg / trans_m: frame name -> the median, over the other frames, of the error of the relative pose
    inv(T_est[other]) @ T_est[frame] against the ground truth's (a single wrong frame is wrong against
    most others; a right frame against most others, whatever its neighbours).
    """

    rot_deg: dict[str, float]
    trans_m: dict[str, float]

    def wrong(self, max_deg: float, max_m: float) -> list[str]:
        """Frames whose median error exceeds max_deg or max_m, in input order."""
        return [n for n in self.rot_deg if self.rot_deg[n] > max_deg or self.trans_m[n] > max_m]


def frame_errors(T_est: dict[str, np.ndarray], T_gt: dict[str, np.ndarray]) -> FrameErrors:
    """`FrameErrors` of the frames in both dicts (name -> [4 x 4] camera pose, e.g. T_obj_cam against
    T_world_cam: each is compared only with poses of its own dict). Needs two common frames; with one the
    errors are 0."""
    names = [n for n in T_est if n in T_gt]
    E = [np.asarray(T_est[n], np.float64) for n in names]
    G = [np.asarray(T_gt[n], np.float64) for n in names]
    rot: dict[str, float] = {}
    trans: dict[str, float] = {}
    for k, n in enumerate(names):
        r, t = [], []
        for m in range(len(names)):
            if m != k:
                rel_e, rel_g = inv_T(E[m]) @ E[k], inv_T(G[m]) @ G[k]
                r.append(rotation_error_deg(rel_e, rel_g))
                t.append(float(np.linalg.norm(rel_e[:3, 3] - rel_g[:3, 3])))
        rot[n] = float(np.median(r)) if r else 0.0
        trans[n] = float(np.median(t)) if t else 0.0
    return FrameErrors(rot, trans)


def _perp(a: np.ndarray) -> np.ndarray:
    """A vector perpendicular to [3] a, of the same length (deterministic choice)."""
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    p = np.cross(a, e)
    return p / np.linalg.norm(p) * np.linalg.norm(a)


def ate_rmse(T_est_list: Sequence[np.ndarray], T_gt_list: Sequence[np.ndarray]) -> float:
    """RMSE (m) of `ate`."""
    return ate(T_est_list, T_gt_list).rmse


def add(pts: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """ADD: mean distance between model points [N x 3] moved by T_est and by T_gt (m)."""
    pts = _as_pts(pts)
    d = transform_points(_as_T(T_est, "T_est"), pts) - transform_points(_as_T(T_gt, "T_gt"), pts)
    return float(np.linalg.norm(d, axis=1).mean())


def adds(pts: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """ADD-S (ADI): mean over model points in the GT pose of the distance to the nearest
    model point in the estimated pose (m). pts: [N x 3] object frame."""
    from scipy.spatial import cKDTree  # here, not at the top: the batch's ground-truth check needs no scipy

    pts = _as_pts(pts)
    # |T_gt p - T_est q| = |T_est^-1 T_gt p - q|: search the model-frame cloud itself
    query = transform_points(inv_T(_as_T(T_est, "T_est")) @ _as_T(T_gt, "T_gt"), pts)
    d, _ = cKDTree(pts).query(query, k=1)
    return float(np.mean(d))


def auc(errors_m: Sequence[float] | np.ndarray, max_threshold: float = 0.1) -> float:
    """Area under the accuracy-threshold curve of ADD / ADD-S errors, 0..100 (YCB-Video).

    Reproduces `VOCap` of the PoseCNN YCB-Video toolbox: errors above `max_threshold` (and
    NaN / inf, e.g. no pose returned) are failures; the finite errors are sorted to d_1..d_m
    with cumulative accuracy a_k = k / n (n = all errors, failures included); the area is
    sum_k (d_k - d_{k-1}) * a_k + (max_threshold - d_m) * a_m over distinct d (d_0 = 0),
    normalised by max_threshold and scaled to 100. Note this right-endpoint rule exceeds
    the exact integral of the empirical accuracy curve by 100 * d_m / (n * max_threshold)
    (negligible for the thousands of poses of a benchmark, large for a handful).
    """
    e = np.asarray(errors_m, dtype=np.float64).reshape(-1)
    if e.size == 0:
        raise ValueError("auc needs at least one error")
    if max_threshold <= 0:
        raise ValueError(f"max_threshold must be > 0, got {max_threshold}")
    n = e.size
    e = np.where(np.isfinite(e) & (e <= max_threshold), e, np.inf)
    d = np.sort(e)
    acc = np.arange(1, n + 1, dtype=np.float64) / n
    fin = np.isfinite(d)
    if not fin.any():
        return 0.0
    d, acc = d[fin], acc[fin]
    mrec = np.concatenate([[0.0], d, [max_threshold]])
    mpre = np.concatenate([[0.0], acc, [acc[-1]]])
    mpre = np.maximum.accumulate(mpre)
    i = np.flatnonzero(mrec[1:] != mrec[:-1]) + 1
    return float(np.sum((mrec[i] - mrec[i - 1]) * mpre[i]) / max_threshold * 100.0)


def _sym_list(syms: Sequence[np.ndarray] | None) -> list[np.ndarray]:
    """Identity followed by the given [4 x 4] symmetry transforms (object frame)."""
    out = [np.eye(4)]
    for k, S in enumerate(syms or []):
        out.append(_as_T(S, f"symmetry {k}"))
    return out


def mssd(pts: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray, syms: Sequence[np.ndarray] | None = None) -> float:
    """Maximum Symmetry-aware Surface Distance (BOP), metres.

    min over symmetries S (identity implied) of max_i |T_est p_i - T_gt S p_i|.
    pts: [N x 3] model vertices (object frame); syms: [4 x 4] object-frame transforms S
    under which the object looks the same (BOP `get_symmetry_transformations`).
    """
    pts = _as_pts(pts)
    p_est = transform_points(_as_T(T_est, "T_est"), pts)
    T_gt = _as_T(T_gt, "T_gt")
    return float(min(np.linalg.norm(p_est - transform_points(T_gt @ S, pts), axis=1).max() for S in _sym_list(syms)))


def _project_K(pts_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    if np.any(pts_cam[:, 2] <= 0):
        raise ValueError("mspd: a model point lies at or behind the camera plane (z <= 0)")
    p = pts_cam @ K.T
    return p[:, :2] / p[:, 2:3]


def mspd(pts: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray | Intrinsics,
         syms: Sequence[np.ndarray] | None = None) -> float:
    """Maximum Symmetry-aware Projection Distance (BOP), pixels.

    min over symmetries S (identity implied) of max_i |proj(K, T_est p_i) - proj(K, T_gt S p_i)|.
    pts: [N x 3] model vertices; K: [3 x 3] or Intrinsics; poses are T_cam_obj.
    """
    pts = _as_pts(pts)
    K = K.K if isinstance(K, Intrinsics) else np.asarray(K, dtype=np.float64).reshape(3, 3)
    uv_est = _project_K(transform_points(_as_T(T_est, "T_est"), pts), K)
    T_gt = _as_T(T_gt, "T_gt")
    return float(min(np.linalg.norm(uv_est - _project_K(transform_points(T_gt @ S, pts), K), axis=1).max()
                     for S in _sym_list(syms)))


def depth_to_distance(depth: np.ndarray, K: np.ndarray | Intrinsics) -> np.ndarray:
    """[H x W] depth along the optical axis -> distance from the camera centre along each pixel's ray (same
    units; 0 stays 0). Pixel centres at integer coordinates, as gscan's and the BOP toolkit's intrinsics."""
    K = K.K if isinstance(K, Intrinsics) else np.asarray(K, dtype=np.float64).reshape(3, 3)
    d = np.asarray(depth, dtype=np.float64)
    h, w = d.shape
    u, v = np.meshgrid((np.arange(w) - K[0, 2]) / K[0, 0], (np.arange(h) - K[1, 2]) / K[1, 1])
    return d * np.sqrt(u ** 2 + v ** 2 + 1.0)


def visible_surface(dist_test: np.ndarray, dist_model: np.ndarray, delta: float = VSD_DELTA_M) -> np.ndarray:
    """[H x W] bool: where the rendered model (distance image, 0 = none) is visible in the test image: not
    more than `delta` behind the measured surface, or where nothing was measured (BOP19's rule, which
    lets VSD score objects that depth sensors miss)."""
    return (dist_model > 0) & ((dist_model - dist_test <= delta) | (dist_test == 0))


def vsd(depth_test: np.ndarray, depth_est: np.ndarray, depth_gt: np.ndarray, K: np.ndarray | Intrinsics,
        taus: Sequence[float] | np.ndarray, delta: float = VSD_DELTA_M) -> np.ndarray:
    """Visible Surface Discrepancy (BOP19), one error in [0, 1] per misalignment tolerance in `taus`.

    depth_test: [H x W] measured depth; depth_est / depth_gt: [H x W] depth of the model rendered in the
    estimated / ground-truth pose (0 where the model is not), all along the optical axis in metres; K: [3 x 3]
    or Intrinsics. The depths become distances along the rays; V_gt is the model's visible surface in the
    ground-truth pose, V_est the estimate's, to which the ground truth's visible pixels it covers are added
    (an estimate is not blamed for what occludes the object). The error is the fraction of V_gt | V_est
    where the two surfaces are not both visible within tau of each other:
    e = (#(V_gt ^ V_est) + #{p in V_gt & V_est : |D_gt(p) - D_est(p)| >= tau}) / #(V_gt | V_est),
    1 when both are empty."""
    dist_test, dist_est, dist_gt = (depth_to_distance(d, K) for d in (depth_test, depth_est, depth_gt))
    visib_gt = visible_surface(dist_test, dist_gt, delta)
    visib_est = visible_surface(dist_test, dist_est, delta) | (visib_gt & (dist_est > 0))
    inter = visib_gt & visib_est
    n_union = int((visib_gt | visib_est).sum())
    taus = np.asarray(taus, dtype=np.float64).reshape(-1)
    if n_union == 0:
        return np.ones(len(taus))
    d = np.abs(dist_gt[inter] - dist_est[inter])
    n_only = n_union - int(inter.sum())
    return np.array([(n_only + int((d >= tau).sum())) / n_union for tau in taus])


def vsd_taus(diameter: float) -> np.ndarray:
    """[10] BOP19 VSD misalignment tolerances (m): 0.05..0.5 x object diameter."""
    if not diameter > 0:
        raise ValueError(f"object diameter must be > 0, got {diameter}")
    return VSD_TAU_FRACTIONS * float(diameter)


def ar_vsd(errors: np.ndarray | Sequence[Sequence[float]]) -> float:
    """BOP19 AR_VSD in [0, 1] of VSD errors [N x T] (one row per target, one column per tau; NaN / inf count as
    failures): the recall at each threshold in VSD_THRESHOLDS, averaged over thresholds and taus."""
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim != 2 or e.size == 0:
        raise ValueError(f"VSD errors must be a non-empty [N x T] array, got shape {e.shape}")
    return float(np.mean([recall_at(e[:, k], VSD_THRESHOLDS) for k in range(e.shape[1])]))


def mssd_thresholds(diameter: float) -> np.ndarray:
    """[10] BOP MSSD correctness thresholds (m): 0.05..0.5 x object diameter."""
    if not diameter > 0:
        raise ValueError(f"object diameter must be > 0, got {diameter}")
    return MSSD_THRESHOLD_FRACTIONS * float(diameter)


def mspd_thresholds(image_width: int) -> np.ndarray:
    """[10] BOP MSPD correctness thresholds (px): 5..50 scaled by image_width / 640."""
    if not image_width > 0:
        raise ValueError(f"image width must be > 0, got {image_width}")
    return MSPD_THRESHOLDS_PX_640 * (float(image_width) / 640.0)


def recall_at(errors: Sequence[float] | np.ndarray, thresholds: Sequence[float] | np.ndarray) -> np.ndarray:
    """[T] fraction of errors strictly below each threshold (NaN / inf errors count as failures)."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    th = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    if e.size == 0:
        raise ValueError("recall needs at least one error")
    e = np.where(np.isfinite(e), e, np.inf)
    return (e[:, None] < th[None, :]).mean(axis=0)


def bop_matched(errors: np.ndarray, thresholds: Sequence[float] | np.ndarray) -> np.ndarray:
    """[G x T] bool: which ground-truth instances the estimates match at each threshold, as the BOP toolkit's
    `pose_matching.match_poses` matches them. errors [E x G]: the error of each estimate (rows in decreasing score
    order, ties in the results' order) against each ground-truth instance (columns in gt_id order; NaN / inf
    never match). At each threshold every estimate in turn takes the instance not yet matched with the smallest
    error strictly below the threshold (the first of equal ones); each instance is matched at most once."""
    e = np.asarray(errors, dtype=np.float64)
    th = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    if e.ndim != 2:
        raise ValueError(f"errors must be an [E x G] array, got shape {e.shape}")
    e = np.where(np.isfinite(e), e, np.inf)
    out = np.zeros((e.shape[1], len(th)), bool)
    for k, t in enumerate(th):
        for row in e:
            cand = np.where(~out[:, k] & (row < t), row, np.inf)
            if cand.size and np.isfinite(cand).any():
                out[int(np.argmin(cand)), k] = True
    return out


def average_recall(errors: Sequence[float] | np.ndarray, thresholds: Sequence[float] | np.ndarray) -> float:
    """Mean of `recall_at` over the thresholds, in [0, 1] (BOP AR of one error function)."""
    return float(recall_at(errors, thresholds).mean())


def ar_mssd(errors_m: Sequence[float] | np.ndarray, diameter: float) -> float:
    """BOP AR_MSSD of MSSD errors (m) of one object with the given diameter (m)."""
    return average_recall(errors_m, mssd_thresholds(diameter))


def ar_mspd(errors_px: Sequence[float] | np.ndarray, image_width: int = 640) -> float:
    """BOP AR_MSPD of MSPD errors (px) measured in images `image_width` pixels wide."""
    return average_recall(errors_px, mspd_thresholds(image_width))


def diameter(points: np.ndarray) -> float:
    """Largest distance between two of the points [N x 3] (BOP's object diameter), exact: the
    farthest pair lies on the convex hull, whose vertices are compared pairwise in chunks."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        return 0.0
    if len(p) > 4:
        from scipy.spatial import ConvexHull, QhullError

        with contextlib.suppress(QhullError, ValueError):  # flat or degenerate: every point is a candidate
            p = p[ConvexHull(p).vertices]
    best = 0.0
    for i in range(0, len(p), 512):
        d2 = ((p[i:i + 512, None, :] - p[None, :, :]) ** 2).sum(-1)
        best = max(best, float(d2.max()))
    return float(np.sqrt(best))
