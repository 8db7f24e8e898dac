"""SE(3) helpers, Kabsch / Umeyama alignment and ICP refinement.

Transforms are [4 x 4] float64 matrices named by frames: `T_a_b` maps points in frame b
into frame a (`p_a = T_a_b @ p_b`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[3 x 3] rotation and [3] translation -> [4 x 4] transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


RIGID_ATOL = 1e-3  # tolerance on R^T R = I: poses written with 4-5 decimals still count as rigid
MAX_TRANSLATION_M = 1e4  # a camera or object pose 10 km away is a unit or parsing error


def is_rigid(T: np.ndarray, atol: float = RIGID_ATOL, max_translation: float = MAX_TRANSLATION_M) -> bool:
    """T [4 x 4] is finite, its rotation orthonormal (to `atol`) with det +1, its last row 0 0 0 1 and
    its translation within `max_translation` (metres) on every axis."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(np.allclose(R.T @ R, np.eye(3), atol=atol) and np.linalg.det(R) > 0
                and np.allclose(T[3], [0, 0, 0, 1], atol=1e-6) and np.abs(T[:3, 3]).max() <= max_translation)


def nearest_rigid(T: np.ndarray) -> np.ndarray:
    """T [4 x 4] with its rotation block replaced by the nearest rotation (SVD, det +1) and the last row
    0 0 0 1: a pose written with limited precision (or scaled, as KinectFusion's trajectories are: det
    0.9997) otherwise reads as a rotation of about 1.4 deg when compared with an exact one."""
    T = np.asarray(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return make_T(U @ D @ Vt, T[:3, 3])


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid [4 x 4] transform."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply [4 x 4] T to [N x 3] points."""
    pts = np.asarray(pts, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


def rotvec_to_R(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: axis * angle [3] -> [3 x 3] rotation."""
    rv = np.asarray(rotvec, dtype=float).reshape(3)
    theta = np.linalg.norm(rv)
    if theta < 1e-12:
        return np.eye(3)
    k = rv / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees in [0, 180]: atan2(sin, cos) of the angle, from the skew part and
    the trace (arccos of the trace alone loses half the digits near 0: a rounding of 1e-16 reads 1e-6 deg)."""
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    c = (np.trace(R) - 1.0) / 2.0
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.degrees(np.arctan2(s, c)))


def pose_error(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) between two transforms."""
    dR = T_est[:3, :3] @ T_gt[:3, :3].T
    return rotation_angle_deg(dR), float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """T_world_cam of an OpenCV camera at `eye` looking at `target` (x right, y down, z forward)."""
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), eye)


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
            with_scale: bool = False) -> np.ndarray:
    """Least-squares rigid (or similarity) transform T with dst ~= T @ src.

    src, dst: [N x 3], N >= 3 (weights [N] optional). A reflection is never returned
    (the reflection guard flips the smallest singular direction). Returns [4 x 4];
    with_scale puts the scale into the rotation block.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need two [N x 3] arrays with N >= 3, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    C = (xd * w[:, None]).T @ xs
    U, S, Vt = np.linalg.svd(C)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    s = 1.0
    if with_scale:
        var_s = (w * (xs ** 2).sum(1)).sum()
        s = float(np.trace(np.diag(S) @ D) / var_s)
    return make_T(s * R, mu_d - s * R @ mu_s)


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Rigid T (proper rotation) minimising sum |T @ src_i - dst_i|^2. src, dst: [N x 3]."""
    return umeyama(src, dst, weights, with_scale=False)


def leave_one_out_residuals(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """[N] residual |T_k src_k - dst_k| of each pair under T_k = kabsch of the other N - 1 pairs (src, dst
    [N x 3], N >= 4): the N fits in one batched SVD, each from the totals less the pair left out."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 4:
        raise ValueError(f"need two [N x 3] arrays with N >= 4, got {src.shape} and {dst.shape}")
    m = len(src) - 1
    mu_s = (src.sum(0) - src) / m  # [N x 3] centroids without pair k
    mu_d = (dst.sum(0) - dst) / m
    C = dst.T @ src - dst[:, :, None] * src[:, None, :] - m * mu_d[:, :, None] * mu_s[:, None, :]  # [N x 3 x 3]
    U, _, Vt = np.linalg.svd(C)
    U[:, :, 2] *= np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)[:, None]  # reflection guard (umeyama)
    R = U @ Vt
    pred = np.einsum("kij,kj->ki", R, src - mu_s) + mu_d
    return np.linalg.norm(pred - dst, axis=1)


CONSENSUS_MAX_PAIRS = 32  # kabsch_trimmed enumerates the triples of at most this many pairs (4960)


def kabsch_trimmed(src: np.ndarray, dst: np.ndarray, tau: float | np.ndarray, min_sin: float = 0.1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch on matched points src, dst [N x 3] (N >= 3) with gross outliers trimmed: (T, keep [N] bool).
    tau: the distance (m) beyond which a pair is off, one for all pairs or one per pair [N] (a pair's own
    noise, `gscan.registration.noise`); residuals below are compared with it, scores sum them in its units.

    1. Plain Kabsch; when every pair lies within tau of its target under it, all pairs are kept.
    2. Otherwise consensus: every triple of pairs (of the first CONSENSUS_MAX_PAIRS, in list order) whose
       triangles have a sine above min_sin in both clouds is posed by its triad (the two triangles' frames)
       and scored by the sum over all pairs of their residuals truncated at tau (MSAC; lowest wins, first
       on ties: `gscan.geometry.consensus_kernel`). The winner's pairs within tau are re-solved by Kabsch and
       re-selected until the selection is stable (at most 3 times). A pair off by a few centimetres drags
       plain Kabsch so far that trimming the worst residual first drops true pairs: on a whole frame
       (rendered, plain table, 60 deg) one pair 36 cm off among 14 true ones gave 19 deg that way.
       When every triple is degenerate, plain Kabsch on all pairs is returned.
    3. Then the worst pair by leave-one-out residual (against the pose solved without it) is dropped while
       it lies more than tau off, at least 5 pairs are kept and no fewer than half of the list: it catches
       a far-off pair that tilts the fit towards itself (a clustered list plus one distant point).
    Without outliers this is plain Kabsch. The kept pairs may be a minority of the list.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    n = len(src)
    tau = np.broadcast_to(np.asarray(tau, dtype=np.float64), (n,)).copy()
    keep = np.ones(n, bool)
    T = kabsch(src, dst)
    if n > 3 and (np.linalg.norm(transform_points(T, src) - dst, axis=1) > tau).any():  # 2. consensus
        from gscan.geometry.consensus_kernel import best_triple

        i, j, k, T_tri = best_triple(np.ascontiguousarray(src), np.ascontiguousarray(dst),
                                     min(n, CONSENSUS_MAX_PAIRS), tau, float(min_sin))
        if i >= 0:
            keep = np.linalg.norm(transform_points(T_tri, src) - dst, axis=1) < tau
            keep[[i, j, k]] = True
            for _ in range(3):
                T = kabsch(src[keep], dst[keep])
                again = np.linalg.norm(transform_points(T, src) - dst, axis=1) < tau
                if again.sum() < 3 or (again == keep).all():
                    break  # T is the selection's pose
                keep = again
            else:  # the third re-selection changed it
                T = kabsch(src[keep], dst[keep])
    floor = max(3, (n + 1) // 2)
    while keep.sum() >= 5 and keep.sum() - 1 >= floor:  # 3. leave-one-out residuals
        idx = np.flatnonzero(keep)
        r = leave_one_out_residuals(src[idx], dst[idx]) / tau[idx]
        worst = int(np.argmax(r))
        if r[worst] <= 1.0:
            break
        keep[idx[worst]] = False
        T = kabsch(src[keep], dst[keep])
    return T, keep


def mean_pose(Ts: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Chordal mean of rigid transforms: mean translation, rotation projected onto SO(3)."""
    Ts = np.asarray(Ts, dtype=np.float64)
    M = Ts[:, :3, :3].mean(0)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return make_T(U @ D @ Vt, Ts[:, :3, 3].mean(0))


@dataclass
class ICPResult:
    T: np.ndarray  # [4 x 4] refined transform (target <- source)
    fitness: float  # fraction of source points with a correspondence within max_dist
    rmse: float  # inlier RMSE (m)


def icp(src_pts: np.ndarray, tgt_pts: np.ndarray, T_init: np.ndarray, max_dist: float,
        voxel: float = 0.0, iterations: int = 30, point_to_plane: bool = True) -> ICPResult:
    """Refine T (tgt <- src) by open3d ICP (point-to-plane by default) on [N x 3] / [M x 3] clouds.

    `voxel` > 0 downsamples both clouds first. Normals of the target are estimated with a
    radius of 3 voxels (or 3 * max_dist when voxel is 0).
    """
    import open3d as o3d

    def cloud(p: np.ndarray) -> "o3d.geometry.PointCloud":
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(p, dtype=np.float64)))
        return pc.voxel_down_sample(voxel) if voxel > 0 else pc

    src, tgt = cloud(src_pts), cloud(tgt_pts)
    if len(src.points) < 10 or len(tgt.points) < 10:
        return ICPResult(np.asarray(T_init, dtype=float).copy(), 0.0, float("inf"))
    radius = 3 * (voxel if voxel > 0 else max_dist)
    if point_to_plane:
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    else:
        est = o3d.pipelines.registration.TransformationEstimationPointToPoint()
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations)
    res = o3d.pipelines.registration.registration_icp(src, tgt, max_dist, np.asarray(T_init, dtype=float), est, crit)
    return ICPResult(np.asarray(res.transformation).copy(), float(res.fitness), float(res.inlier_rmse))
