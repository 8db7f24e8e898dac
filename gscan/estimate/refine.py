"""Pose refinement: point-to-plane ICP of the template's visible surface onto the query cloud, anchored by the
match list.

The template's normals give the planes (its clean surface, not the noisy query's). The matched keypoint pairs
enter the same least-squares step as weak point-to-point terms: where the surface alone leaves a direction
free (a can turning about its axis, a flat face sliding in its plane) they hold the pose where the matches put
it, and elsewhere the surface's many pairs outweigh them. Deterministic: bit-identical output for identical
input.

`refine_pose` is stage 5 of an estimate (and a tracked frame's refinement): the template's samples visible
from the predicted pose onto the query cloud cropped to a sphere of `crop_radii` object radii around the
predicted centre; a refinement that moves the pose by more than the object radius or `max_turn_deg` is
discarded.
"""
from __future__ import annotations

import logging

import numpy as np
from numba import njit

from gscan.estimate.model import ObjectModel
from gscan.estimate.params import RefineParams
from gscan.estimate.query import QueryFrame
from gscan.estimate.verify import visible
from gscan.geometry.pointset import voxel_mean
from gscan.geometry.transforms import make_T, rotvec_to_R, transform_points

log = logging.getLogger(__name__)


@njit(cache=True, nogil=True)
def normal_equations(p, j, tgt, nrm, R, anc_p, anc_q, anc_w, H, g):
    """The point-to-plane step's 6 x 6 system in (rotation vector, translation), accumulated in H and g: every
    pair (p[i], tgt[j[i]]) with j[i] >= 0 (p [N x 3] moved source points, nrm [N x 3] their object-frame normals
    turned by R [3 x 3]) adds a a^T and a r, a = [p x n, n], r = (p - q) . n; every anchor (anc_p [K x 3] moved,
    anc_q [K x 3]) adds anc_w J^T J and anc_w J^T (anc_p - anc_q), J the Jacobian of (omega x p + t). Returns
    the number of pairs."""
    H[:] = 0.0
    g[:] = 0.0
    a = np.empty(6)
    n_pairs = 0
    for i in range(p.shape[0]):
        k = j[i]
        if k < 0:
            continue
        n_pairs += 1
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        nx = R[0, 0] * nrm[i, 0] + R[0, 1] * nrm[i, 1] + R[0, 2] * nrm[i, 2]
        ny = R[1, 0] * nrm[i, 0] + R[1, 1] * nrm[i, 1] + R[1, 2] * nrm[i, 2]
        nz = R[2, 0] * nrm[i, 0] + R[2, 1] * nrm[i, 1] + R[2, 2] * nrm[i, 2]
        r = (px - tgt[k, 0]) * nx + (py - tgt[k, 1]) * ny + (pz - tgt[k, 2]) * nz
        a[0] = py * nz - pz * ny
        a[1] = pz * nx - px * nz
        a[2] = px * ny - py * nx
        a[3] = nx
        a[4] = ny
        a[5] = nz
        for u in range(6):
            g[u] += a[u] * r
            for v in range(u, 6):
                H[u, v] += a[u] * a[v]
    for m in range(anc_p.shape[0]):  # J = [[0, z, -y, 1, 0, 0], [-z, 0, x, 0, 1, 0], [y, -x, 0, 0, 0, 1]]
        x, y, z = anc_p[m, 0], anc_p[m, 1], anc_p[m, 2]
        ex, ey, ez = x - anc_q[m, 0], y - anc_q[m, 1], z - anc_q[m, 2]
        J = ((0.0, z, -y, 1.0, 0.0, 0.0), (-z, 0.0, x, 0.0, 1.0, 0.0), (y, -x, 0.0, 0.0, 0.0, 1.0))
        e = (ex, ey, ez)
        for c in range(3):
            row = J[c]
            for u in range(6):
                g[u] += anc_w * row[u] * e[c]
                for v in range(u, 6):
                    H[u, v] += anc_w * row[u] * row[v]
    for u in range(6):
        for v in range(u):
            H[u, v] = H[v, u]
    return n_pairs


def icp_anchored(src: np.ndarray, src_normals: np.ndarray, tgt: np.ndarray, T_init: np.ndarray,
                 max_dists: tuple[float, ...], iterations: int, anchors: tuple[np.ndarray, np.ndarray] | None = None,
                 anchor_weight: float = 0.1) -> tuple[np.ndarray, float]:
    """ICP of src [N x 3] (object frame, normals src_normals [N x 3]) onto tgt [M x 3] (camera frame) from
    T_init (tgt <- src) -> (T [4 x 4], fitness: the fraction of src points paired in the last iteration).

    max_dists: correspondence distances, coarse to fine (m); each runs up to `iterations` steps (fewer once a
    step moves less than 0.6 mdeg and 10 um). anchors: (object-frame points [K x 3], camera-frame points
    [K x 3]) of the match list, each pair weighted `anchor_weight` against one surface pair."""
    from scipy.spatial import cKDTree

    from gscan.geometry.grid_kernel import NearestGrid

    src = np.asarray(src, dtype=np.float64)
    tgt = np.asarray(tgt, dtype=np.float64)
    T = np.asarray(T_init, dtype=np.float64).copy()
    if len(src) < 10 or len(tgt) < 10:
        return T, 0.0
    tree = None
    fitness = 0.0
    H, g = np.empty((6, 6)), np.empty(6)
    src_normals = np.ascontiguousarray(src_normals, dtype=np.float64)
    a_obj = a_cam = np.zeros((0, 3))
    if anchors is not None:
        a_obj, a_cam = (np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3) for a in anchors)
    for max_dist in max_dists:
        # the nearest target point within max_dist: a grid of that cell size (a kd-tree when the target is too
        # wide for one), the same pairs
        grid = NearestGrid.build(tgt, max_dist)
        if grid is None and tree is None:
            tree = cKDTree(tgt)
        for _ in range(iterations):
            p = src @ T[:3, :3].T + T[:3, 3]
            if grid is not None:
                ok, j = grid.query(p)
            else:
                assert tree is not None
                d, j = tree.query(p, distance_upper_bound=max_dist, workers=1)
                ok = np.isfinite(d)
            fitness = float(ok.mean())
            if normal_equations(p, np.where(ok, j, -1), tgt, src_normals, T[:3, :3], a_obj @ T[:3, :3].T + T[:3, 3],
                                 a_cam, anchor_weight, H, g) < 10:
                return T, fitness
            H += 1e-9 * np.eye(6)
            x = np.linalg.solve(H, -g)
            T = make_T(rotvec_to_R(x[:3]), x[3:]) @ T
            if np.linalg.norm(x[:3]) < 1e-5 and np.linalg.norm(x[3:]) < 1e-5:
                break
    return T, fitness


def refine_pose(model: ObjectModel, q: QueryFrame, T_cam_obj: np.ndarray,
                anchors: tuple[np.ndarray, np.ndarray] | None, region: np.ndarray | None, params: RefineParams,
                max_dists: tuple[float, ...] | None = None, max_points: int | None = None) -> np.ndarray:
    """ICP of the model's samples visible at T_cam_obj [4 x 4] onto the query cloud cropped to `region`
    ([H x W] bool, or None) and to a sphere around the predicted object (module docstring). anchors: the match
    list's (object-frame points [K x 3], camera-frame points [K x 3]); max_dists: correspondence distances,
    coarse to fine (default: params.max_dist alone); max_points: samples used (default: params.max_points).
    Returns T_cam_obj unchanged when ICP has too little to work with or moves the pose implausibly far."""
    idx, _, _ = visible(T_cam_obj, q.frame.intrinsics, model.samples)
    if len(idx) < 30:
        return T_cam_obj
    max_dists = (params.max_dist,) if max_dists is None else max_dists
    c = transform_points(T_cam_obj, model.center[None])[0]
    tgt = q.points_near(c, params.crop_radii * model.radius + max(max_dists), region)
    if len(tgt) < 30:
        return T_cam_obj
    tgt = voxel_mean(tgt, params.target_voxel)  # averaging, not picking: depth noise shrinks
    idx = idx[:: max(1, int(np.ceil(len(idx) / (max_points or params.max_points))))]
    T, fitness = icp_anchored(model.samples[idx], model.normals[idx], tgt, T_cam_obj, max_dists, params.iterations,
                              anchors, params.anchor_weight)
    dR = T[:3, :3] @ T_cam_obj[:3, :3].T
    moved = np.linalg.norm(T[:3, 3] - T_cam_obj[:3, 3])
    if fitness <= 0 or moved > model.radius or np.trace(dR) < 1.0 + 2.0 * np.cos(np.radians(params.max_turn_deg)):
        log.debug("ICP rejected (fitness %.2f, moved %.3f m)", fitness, moved)
        return T_cam_obj
    return T
