"""Baseline keypoint matchers, for comparison with GMatch on the same 3D keypoints.

Every baseline takes the same inputs as GMatch (keypoints [N x 3] per side in their camera frames and
the descriptor distance matrix [Ns x Nt]) and returns a BaselineResult (inlier correspondences and
T_tgt_src). Parameters are fixed and stated (BaselineParams), never tuned per input:

* "ratio":     nearest neighbour + Lowe's ratio test (0.75) -> RANSAC (below).
* "mutual":    mutual nearest neighbours -> RANSAC.
* "ransac":    every source keypoint's nearest neighbour -> RANSAC.
* "lo-ransac": the same nearest-neighbour correspondences -> pycolmap `estimate_rigid3d_robust`
               (LO-RANSAC), max error = inlier distance, 100000 trials max, confidence 0.999.
* "fgr":       open3d Fast Global Registration on the keypoints with their descriptors as features
               (its own mutual + tuple tests), absolute scale, final correspondence distance 2.5 x inlier distance.

RANSAC = open3d `registration_ransac_based_on_correspondence` (3-point samples, point-to-point,
100000 iterations, confidence 0.999, inlier distance = GMatch's eta = 0.01 m), called with clouds that
hold only the matched points (a whole keypoint cloud would inflate the inlier count).
Every method's final pose is the Kabsch fit over its inliers (inlier distance from its own estimate)
among its putative correspondences (FGR: mutual nearest neighbours), then the inliers are recounted.
Randomness is seeded (open3d / pycolmap seed 0), so results are repeatable.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from gscan.geometry.kabsch import kabsch
from gscan.matching.params import BASELINES, BaselineParams

log = logging.getLogger(__name__)



@dataclass
class BaselineResult:
    matches: np.ndarray  # [M x 2] int32 inlier correspondences (source index, target index)
    T_tgt_src: np.ndarray | None  # [4 x 4] or None when the estimator found nothing
    n_putative: int  # correspondences handed to the estimator
    method: str = ""
    timings_ms: dict[str, float] = field(default_factory=dict)


def nearest_neighbours(dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For dist [Ns x Nt]: (nn [Ns] index of the nearest target, d1 [Ns], d2 [Ns] second-nearest distance)."""
    dist = np.asarray(dist, dtype=np.float32)
    if dist.shape[1] >= 2:
        part = np.argpartition(dist, 1, axis=1)[:, :2]
        dd = np.take_along_axis(dist, part, 1)
        swap = dd[:, 1] < dd[:, 0]
        part[swap] = part[swap][:, ::-1]
        dd[swap] = dd[swap][:, ::-1]
        # argpartition ties are arbitrary: resolve the nearest deterministically by the lowest index
        nn = np.argmin(dist, axis=1)
        return nn, dist[np.arange(len(dist)), nn], dd[:, 1]
    nn = np.zeros(len(dist), np.intp)
    return nn, dist[:, 0].copy(), np.full(len(dist), np.inf, np.float32)


def putative_ratio(dist: np.ndarray, ratio: float = 0.75) -> np.ndarray:
    """Nearest neighbour + Lowe's ratio test: [K x 2] int32."""
    if dist.size == 0:
        return np.zeros((0, 2), np.int32)
    nn, d1, d2 = nearest_neighbours(dist)
    keep = d1 < ratio * d2
    return np.stack([np.flatnonzero(keep), nn[keep]], 1).astype(np.int32)


def putative_mutual(dist: np.ndarray) -> np.ndarray:
    """Mutual nearest neighbours: [K x 2] int32."""
    if dist.size == 0:
        return np.zeros((0, 2), np.int32)
    nn_st = np.argmin(dist, axis=1)
    nn_ts = np.argmin(dist, axis=0)
    keep = nn_ts[nn_st] == np.arange(len(nn_st))
    return np.stack([np.flatnonzero(keep), nn_st[keep]], 1).astype(np.int32)


def putative_nn(dist: np.ndarray) -> np.ndarray:
    """Every source keypoint with its nearest target: [Ns x 2] int32."""
    if dist.size == 0:
        return np.zeros((0, 2), np.int32)
    return np.stack([np.arange(dist.shape[0]), np.argmin(dist, axis=1)], 1).astype(np.int32)


def _inliers(pts_s, pts_t, corr, T, d) -> np.ndarray:
    if T is None or len(corr) == 0:
        return np.zeros((0, 2), np.int32)
    r = np.linalg.norm(pts_s[corr[:, 0]] @ T[:3, :3].T + T[:3, 3] - pts_t[corr[:, 1]], axis=1)
    return corr[r < d].astype(np.int32)


def ransac_correspondences(pts_s: np.ndarray, pts_t: np.ndarray, corr: np.ndarray,
                           params: BaselineParams = BaselineParams()) -> np.ndarray | None:
    """open3d correspondence RANSAC on corr [K x 2]; clouds hold only the matched points. T_tgt_src or None."""
    import open3d as o3d

    if len(corr) < 3:
        return None
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts_s, np.float64)[corr[:, 0]]))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts_t, np.float64)[corr[:, 1]]))
    idx = np.repeat(np.arange(len(corr), dtype=np.int32)[:, None], 2, 1)
    o3d.utility.random.seed(params.seed)
    res = reg.registration_ransac_based_on_correspondence(
        src, tgt, o3d.utility.Vector2iVector(idx), params.inlier_dist,
        reg.TransformationEstimationPointToPoint(False), 3, [],
        reg.RANSACConvergenceCriteria(params.iterations, params.confidence))
    if len(res.correspondence_set) < 3:
        return None
    return np.asarray(res.transformation, dtype=np.float64).copy()


def lo_ransac_correspondences(pts_s: np.ndarray, pts_t: np.ndarray, corr: np.ndarray,
                              params: BaselineParams = BaselineParams()) -> np.ndarray | None:
    """pycolmap LO-RANSAC (estimate_rigid3d_robust) on corr [K x 2]. T_tgt_src or None."""
    import pycolmap

    if len(corr) < 3:
        return None
    opt = pycolmap.RANSACOptions()
    opt.max_error = params.inlier_dist
    opt.max_num_trials = params.iterations
    opt.confidence = params.confidence
    opt.random_seed = params.seed
    opt.num_threads = 1
    src = np.asarray(pts_s, np.float64)[corr[:, 0]]
    tgt = np.asarray(pts_t, np.float64)[corr[:, 1]]
    out = pycolmap.estimate_rigid3d_robust(src, tgt, opt)
    if out is None:
        return None
    rig = out["tgt_from_src"] if isinstance(out, dict) else out
    if isinstance(out, dict) and out.get("num_inliers", 3) < 3:
        return None
    return np.vstack([np.asarray(rig.matrix(), dtype=np.float64), [0.0, 0.0, 0.0, 1.0]])


def _fgr_features(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc)
    if d.dtype == np.uint8:  # ORB: bits as 0/1 floats, so squared L2 = Hamming distance
        d = np.unpackbits(d, axis=1)
    return np.ascontiguousarray(d, dtype=np.float64).T


def fgr(pts_s: np.ndarray, pts_t: np.ndarray, desc_s: np.ndarray, desc_t: np.ndarray,
        params: BaselineParams = BaselineParams()) -> np.ndarray | None:
    """open3d FGR with keypoint descriptors [N x D] as features. T_tgt_src or None."""
    import open3d as o3d

    if len(pts_s) < 3 or len(pts_t) < 3:
        return None
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts_s, np.float64)))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts_t, np.float64)))
    fs, ft = reg.Feature(), reg.Feature()
    fs.data = _fgr_features(desc_s)
    ft.data = _fgr_features(desc_t)
    opt = reg.FastGlobalRegistrationOption(use_absolute_scale=True,
                                           maximum_correspondence_distance=params.fgr_dist_factor * params.inlier_dist)
    o3d.utility.random.seed(params.seed)
    res = reg.registration_fgr_based_on_feature_matching(src, tgt, fs, ft, opt)
    T = np.asarray(res.transformation, dtype=np.float64).copy()
    return None if np.allclose(T, np.eye(4)) and len(res.correspondence_set) == 0 else T


def run_baseline(method: str, pts_s: np.ndarray, pts_t: np.ndarray, dist: np.ndarray,
                 desc_s: np.ndarray | None = None, desc_t: np.ndarray | None = None,
                 params: BaselineParams = BaselineParams()) -> BaselineResult:
    """Run baseline `method` (one of BASELINES) on keypoints pts_s [Ns x 3], pts_t [Nt x 3] with
    descriptor distances dist [Ns x Nt] (FGR also needs the descriptors desc_s / desc_t)."""
    if method not in BASELINES:
        raise ValueError(f"unknown baseline {method!r}; expected one of {BASELINES}")
    pts_s = np.asarray(pts_s, np.float64)
    pts_t = np.asarray(pts_t, np.float64)
    dist = np.asarray(dist)
    if dist.shape != (len(pts_s), len(pts_t)):
        raise ValueError(f"distance matrix shape {dist.shape} != ({len(pts_s)}, {len(pts_t)})")
    t0 = time.perf_counter()
    if method == "fgr":
        if desc_s is None or desc_t is None:
            raise ValueError("fgr needs the descriptors")
        T = fgr(pts_s, pts_t, desc_s, desc_t, params)
        corr = putative_mutual(dist)  # report inliers among mutual nearest neighbours
    else:
        corr = {"ratio": lambda: putative_ratio(dist, params.ratio), "mutual": lambda: putative_mutual(dist),
                "ransac": lambda: putative_nn(dist), "lo-ransac": lambda: putative_nn(dist)}[method]()
        est = lo_ransac_correspondences if method == "lo-ransac" else ransac_correspondences
        T = est(pts_s, pts_t, corr, params)
    matches = _inliers(pts_s, pts_t, corr, T, params.inlier_dist)
    if len(matches) >= 3:  # final pose: Kabsch over the inliers (the solver GMatch's matches get)
        T = kabsch(pts_s[matches[:, 0]], pts_t[matches[:, 1]])
        matches = _inliers(pts_s, pts_t, corr, T, params.inlier_dist)
    ms = (time.perf_counter() - t0) * 1e3
    log.debug("%s: %d putative, %d inliers, %.1f ms", method, len(corr), len(matches), ms)
    return BaselineResult(matches, T, len(corr), method, {"match": ms})
