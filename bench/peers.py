"""Peer registration pipelines for the scan benchmark (bench/scan.py), built from open3d 0.20.

Both chain consecutive frames of a capture into camera poses T_world_cam (world = the first frame)
from whole frames (object, table and background alike), as a plain odometry front end would:

- `rgbd_odometry_chain`: open3d RGB-D odometry (`compute_rgbd_odometry`, hybrid photometric +
  geometric Jacobian, default pyramid iterations [20, 10, 5], depth_diff_max 0.03 m,
  depth_max as given), identity initialisation.
- `fpfh_ransac_icp_chain`: whole-frame clouds (pixel stride 2, depth <= depth_max, voxel 5 mm),
  normals (radius 1 cm, 30 neighbours), FPFH (radius 2.5 cm, 100 neighbours), open3d
  `registration_ransac_based_on_feature_matching` (mutual filter, point-to-point, ransac_n 3,
  distance 7.5 mm, edge-length 0.9 and distance checkers, 100000 iterations / confidence 0.999,
  open3d RNG seeded 0), then point-to-plane ICP (1 cm correspondence distance, 30 iterations).

A pair fails when the peer reports failure (odometry `success` false) or, for FPFH, when the
RANSAC or ICP fitness is below `MIN_FITNESS`. A failed frame is left unregistered and the next frame
is tried against the last registered one, so one failure does not end the chain; a frame whose
pose is wrong but not reported as failed stays registered (and shows in the ATE).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from gscan.geometry.transforms import inv_T
from gscan.io.camera import RGBDFrame, backproject

FPFH_VOXEL = 0.005  # m
FPFH_STRIDE = 2  # pixel stride of the whole-frame clouds before voxel downsampling
MIN_FITNESS = 0.3  # FPFH chain: RANSAC and ICP fitness below this count as a failed pair
RANSAC_ITERATIONS = 100_000
RANSAC_CONFIDENCE = 0.999


@dataclass
class PeerResult:
    """Poses of one peer on one capture.

    T_world_cam: frame name -> [4 x 4] pose (world = first frame), None when the frame failed.
    seconds: wall time of the whole chain (frame preparation included).
    """

    method: str
    T_world_cam: dict[str, np.ndarray | None]
    seconds: float
    notes: dict[str, str] = field(default_factory=dict)  # frame name -> why it failed

    @property
    def failed(self) -> list[str]:
        return [n for n, T in self.T_world_cam.items() if T is None]


def _pinhole(frame: RGBDFrame) -> o3d.camera.PinholeCameraIntrinsic:
    K = frame.intrinsics
    return o3d.camera.PinholeCameraIntrinsic(int(K.width), int(K.height), K.fx, K.fy, K.cx, K.cy)


def _rgbd_image(frame: RGBDFrame, depth_max: float) -> o3d.geometry.RGBDImage:
    color = o3d.geometry.Image(np.ascontiguousarray(frame.color))
    depth = o3d.geometry.Image(np.ascontiguousarray(frame.depth.astype(np.float32)))
    return o3d.geometry.RGBDImage.create_from_color_and_depth(
        color, depth, depth_scale=1.0, depth_trunc=depth_max, convert_rgb_to_intensity=True)


def _chain(frames: list[RGBDFrame], prepare, pair, method: str) -> PeerResult:
    """Generic chain: pair(prep_src, prep_tgt) -> (T_tgt_src [4 x 4] | None, why)."""
    t0 = time.perf_counter()
    poses: dict[str, np.ndarray | None] = {frames[0].name: np.eye(4)}
    notes: dict[str, str] = {}
    last = 0
    prep_last = prepare(frames[0])
    for j in range(1, len(frames)):
        prep_j = prepare(frames[j])
        T_j_last, why = pair(prep_last, prep_j)
        if T_j_last is None:
            poses[frames[j].name] = None
            notes[frames[j].name] = f"vs {frames[last].name}: {why}"
            continue
        poses[frames[j].name] = poses[frames[last].name] @ inv_T(T_j_last)
        last, prep_last = j, prep_j
    return PeerResult(method, poses, time.perf_counter() - t0, notes)


def rgbd_odometry_chain(frames: list[RGBDFrame], depth_max: float) -> PeerResult:
    """open3d RGB-D odometry (hybrid term) between consecutive frames, chained. frames: >= 1."""
    intr = _pinhole(frames[0])
    option = o3d.pipelines.odometry.OdometryOption(depth_max=float(depth_max))
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def pair(src: o3d.geometry.RGBDImage, tgt: o3d.geometry.RGBDImage):
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(src, tgt, intr, np.eye(4), jac, option)
        return (np.asarray(T) if ok else None), "odometry reported failure"

    return _chain(frames, lambda f: _rgbd_image(f, depth_max), pair, "open3d RGB-D odometry")


def _fpfh_cloud(frame: RGBDFrame, depth_max: float):
    s = FPFH_STRIDE
    d = frame.depth[::s, ::s]
    pts = backproject(frame.depth, frame.intrinsics)[::s, ::s][(d > 0) & (d <= depth_max)]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    pc = pc.voxel_down_sample(FPFH_VOXEL)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * FPFH_VOXEL, max_nn=30))
    pc.orient_normals_towards_camera_location(np.zeros(3))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * FPFH_VOXEL, max_nn=100))
    return pc, fpfh


def fpfh_ransac_icp_chain(frames: list[RGBDFrame], depth_max: float, seed: int = 0) -> PeerResult:
    """FPFH + feature RANSAC + point-to-plane ICP between consecutive frames, chained. frames: >= 1."""
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    dist = 1.5 * FPFH_VOXEL

    def pair(src, tgt):
        (pc_s, f_s), (pc_t, f_t) = src, tgt
        if len(pc_s.points) < 10 or len(pc_t.points) < 10:
            return None, "too few points"
        r = reg.registration_ransac_based_on_feature_matching(
            pc_s, pc_t, f_s, f_t, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE))
        if r.fitness < MIN_FITNESS:
            return None, f"RANSAC fitness {r.fitness:.2f} < {MIN_FITNESS}"
        icp = reg.registration_icp(pc_s, pc_t, 2 * FPFH_VOXEL, r.transformation,
                                   reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(max_iteration=30))
        if icp.fitness < MIN_FITNESS:
            return None, f"ICP fitness {icp.fitness:.2f} < {MIN_FITNESS}"
        return np.asarray(icp.transformation), ""

    return _chain(frames, lambda f: _fpfh_cloud(f, depth_max), pair, "open3d FPFH+RANSAC+ICP")


SIFT_RATIO = 0.75  # Lowe's ratio of the SIFT chain
SIFT_RANSAC_DIST = 0.03  # m: the SIFT chain's 3-point RANSAC inlier distance (room-scale depth noise)
SIFT_MIN_INLIERS = 10  # the SIFT chain's pair fails with fewer RANSAC inliers
SIFT_ICP_VOXEL = 0.02  # m: the SIFT chain's ICP clouds (whole frames, depth <= depth_max)
SIFT_ICP_DIST = 0.05  # m: the SIFT chain's ICP correspondence distance


def sift_ransac_icp_chain(frames: list[RGBDFrame], depth_max: float = 4.0, seed: int = 0) -> PeerResult:
    """The plain odometry front end: OpenCV SIFT keypoints lifted with the depth at their pixel, Lowe's
    ratio test, open3d 3-point correspondence RANSAC, point-to-plane ICP on whole-frame clouds; consecutive
    frames chained. A pair fails with fewer than SIFT_MIN_INLIERS RANSAC inliers or ICP fitness below
    MIN_FITNESS. frames: >= 1."""
    import cv2

    from gscan.geometry.icp import icp
    from gscan.matching.baselines import BaselineParams, putative_ratio, ransac_correspondences

    sift = cv2.SIFT_create()
    params = BaselineParams(ratio=SIFT_RATIO, inlier_dist=SIFT_RANSAC_DIST, seed=seed)

    def prepare(f: RGBDFrame):
        gray = cv2.cvtColor(f.color, cv2.COLOR_RGB2GRAY)
        kps, desc = sift.detectAndCompute(gray, None)
        px = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
        ui = np.clip(np.rint(px).astype(int), 0, [f.depth.shape[1] - 1, f.depth.shape[0] - 1])
        z = f.depth[ui[:, 1], ui[:, 0]].astype(np.float64)
        ok = (z > 0) & (z <= depth_max)
        K = f.intrinsics
        pts = np.stack([(px[:, 0] - K.cx) / K.fx * z, (px[:, 1] - K.cy) / K.fy * z, z], 1)[ok]
        d = f.depth.copy()
        d[d > depth_max] = 0
        cloud = backproject(d, K)[::2, ::2][d[::2, ::2] > 0]
        return pts, (desc if desc is not None else np.zeros((0, 128), np.float32))[ok], cloud

    def pair(src, tgt):
        (ps, ds, cs), (pt, dt, ct) = src, tgt
        if len(ps) < 3 or len(pt) < 3:
            return None, "too few keypoints with depth"
        dist = np.sqrt(np.maximum((ds ** 2).sum(1)[:, None] + (dt ** 2).sum(1)[None] - 2 * ds @ dt.T, 0))
        corr = putative_ratio(dist, params.ratio)
        T = ransac_correspondences(ps, pt, corr, params)
        if T is None:
            return None, "RANSAC found nothing"
        r = np.linalg.norm(ps[corr[:, 0]] @ T[:3, :3].T + T[:3, 3] - pt[corr[:, 1]], axis=1)
        if (r < params.inlier_dist).sum() < SIFT_MIN_INLIERS:
            return None, f"{int((r < params.inlier_dist).sum())} RANSAC inliers < {SIFT_MIN_INLIERS}"
        res = icp(cs, ct, T, SIFT_ICP_DIST, SIFT_ICP_VOXEL, 30, True)
        if res.fitness < MIN_FITNESS:
            return None, f"ICP fitness {res.fitness:.2f} < {MIN_FITNESS}"
        return res.T, ""

    return _chain(frames, prepare, pair, "SIFT+ratio+RANSAC+ICP")
