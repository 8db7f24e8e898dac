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

- `PPFPeer`: OpenCV's point-pair-feature detector (Drost et al. 2010, `cv2.ppf_match_3d` of opencv-contrib,
  in a child process: bench/ppf_child.py) on clouds voxelised at 5 % of the model's diameter, its 5 poses with
  most votes refined by open3d's point-to-plane ICP, the best ICP fitness kept; `ppf_icp_chain` chains it like
  the others (model: the earlier frame's cloud).

A pair fails when the peer reports failure (odometry `success` false) or, for FPFH and PPF, when the
RANSAC, ICP or PPF fitness is below `MIN_FITNESS`. A failed frame is left unregistered and the next frame
is tried against the last registered one, so one failure does not end the chain; a frame whose
pose is wrong but not reported as failed stays registered (and shows in the ATE).
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from pathlib import Path

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


def frame_cloud(frame: RGBDFrame, depth_max: float, voxel: float = FPFH_VOXEL) -> o3d.geometry.PointCloud:
    """A frame's points (pixel stride FPFH_STRIDE, 0 < depth <= depth_max), voxelised, with normals (radius two
    voxels, 30 neighbours) turned towards the camera. Camera frame, m."""
    s = FPFH_STRIDE
    d = frame.depth[::s, ::s]
    pts = backproject(frame.depth, frame.intrinsics)[::s, ::s][(d > 0) & (d <= depth_max)]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    pc = pc.voxel_down_sample(voxel)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    pc.orient_normals_towards_camera_location(np.zeros(3))
    return pc


def mesh_cloud(vertices: np.ndarray, triangles: np.ndarray, voxel: float = FPFH_VOXEL) -> o3d.geometry.PointCloud:
    """A model's surface as a cloud: 20 points per voxel face area sampled (open3d's Poisson disk, seeded) on the
    mesh ([V x 3] m, [F x 3]), voxelised, with the mesh's outward normals."""
    o3d.utility.random.seed(0)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(triangles, np.int32)))
    mesh.compute_vertex_normals()
    n = max(1000, int(20 * mesh.get_surface_area() / voxel ** 2))
    pc = mesh.sample_points_poisson_disk(min(n, 200_000), use_triangle_normal=True)
    return unit_normals(pc.voxel_down_sample(voxel))


def unit_normals(pc: o3d.geometry.PointCloud) -> o3d.geometry.PointCloud:
    """The cloud with its normals scaled to unit length (voxelising averages them)."""
    pc.normalize_normals()
    return pc


def fpfh(pc: o3d.geometry.PointCloud, voxel: float = FPFH_VOXEL):
    """FPFH of a cloud with normals (radius five voxels, 100 neighbours)."""
    return o3d.pipelines.registration.compute_fpfh_feature(
        pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))


def fpfh_ransac_icp(src, tgt, voxel: float = FPFH_VOXEL, min_fitness: float = MIN_FITNESS
                    ) -> tuple[np.ndarray | None, str]:
    """T_tgt_src [4 x 4] of two (cloud, FPFH) pairs by feature RANSAC and point-to-plane ICP, or (None, why) when
    either's fitness (share of src points with a tgt point within reach) is below min_fitness."""
    reg = o3d.pipelines.registration
    dist = 1.5 * voxel
    (pc_s, f_s), (pc_t, f_t) = src, tgt
    if len(pc_s.points) < 10 or len(pc_t.points) < 10:
        return None, "too few points"
    r = reg.registration_ransac_based_on_feature_matching(
        pc_s, pc_t, f_s, f_t, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE))
    if r.fitness < min_fitness:
        return None, f"RANSAC fitness {r.fitness:.2f} < {min_fitness}"
    icp = reg.registration_icp(pc_s, pc_t, 2 * voxel, r.transformation, reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(max_iteration=30))
    if icp.fitness < min_fitness:
        return None, f"ICP fitness {icp.fitness:.2f} < {min_fitness}"
    return np.asarray(icp.transformation), ""


def fpfh_ransac_icp_chain(frames: list[RGBDFrame], depth_max: float, seed: int = 0) -> PeerResult:
    """FPFH + feature RANSAC + point-to-plane ICP between consecutive frames, chained. frames: >= 1."""
    o3d.utility.random.seed(seed)

    def prepare(f: RGBDFrame):
        pc = frame_cloud(f, depth_max)
        return pc, fpfh(pc)

    return _chain(frames, prepare, fpfh_ransac_icp, "open3d FPFH+RANSAC+ICP")


CONTRIB = Path(__file__).resolve().parents[1] / ".venv" / "opencv-contrib"  # PPF: opencv-contrib's folder
PPF_VOXEL = 0.05  # of the model's diameter: the clouds given to the PPF detector (its own sampling step)
PPF_TOP = 5  # PPF poses with most votes refined by ICP; the one with the best ICP fitness is kept


class PeerUnavailable(RuntimeError):
    """A peer whose package is not installed (the message says how to install it)."""


class PPFPeer:
    """OpenCV's point-pair-feature detector in a child process (bench/ppf_child.py) run with opencv-contrib's
    folder (GSCAN_OPENCV_CONTRIB, default .venv/opencv-contrib) first on its path. Use as a context manager."""

    def __init__(self) -> None:
        import importlib.metadata
        import os
        import subprocess
        import sys

        site = Path(os.environ.get("GSCAN_OPENCV_CONTRIB", CONTRIB))
        if not (site / "cv2").is_dir():
            version = importlib.metadata.version("opencv-python-headless")
            raise PeerUnavailable(
                f"the PPF peer needs opencv-contrib in {site}: {sys.executable} -m pip install --no-deps --target "
                f"{site} opencv-contrib-python-headless=={version}")
        paths = [str(site), os.environ.get("PYTHONPATH", "")]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in paths if p))
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("ppf_child.py"))],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        self.model: o3d.geometry.PointCloud | None = None  # the model the child was trained on last

    def __enter__(self) -> PPFPeer:
        return self

    def __exit__(self, *exc: object) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=60)

    def register(self, key: str, model: o3d.geometry.PointCloud | None, scene: o3d.geometry.PointCloud,
                 voxel: float) -> tuple[np.ndarray | None, float]:
        """(T_scene_model [4 x 4], or None when PPF finds no pose; the child's CPU seconds): of the PPF_TOP poses
        with most votes, each refined by point-to-plane ICP (two `voxel`s), the one with the highest ICP fitness.
        model: None when `key` was the last model given (the detector stays trained); clouds with unit normals."""
        from ppf_child import read, write

        def rows(pc: o3d.geometry.PointCloud | None):
            if pc is None:
                return None
            return np.hstack([np.asarray(pc.points), np.asarray(pc.normals)]).astype(np.float32)

        if model is not None:
            self.model = model
        write(self.proc.stdin, (key, rows(model), rows(scene), PPF_TOP))
        answer = read(self.proc.stdout)
        if answer is None:
            raise RuntimeError(f"the PPF child ended (exit {self.proc.wait()})")
        poses, seconds = answer
        assert self.model is not None, "the first call gives the model"
        reg = o3d.pipelines.registration
        best, best_fit = None, -1.0
        for T, _votes in poses:  # most votes first: a tie keeps the pose with more votes
            icp = reg.registration_icp(self.model, scene, 2 * voxel, T, reg.TransformationEstimationPointToPlane(),
                                       reg.ICPConvergenceCriteria(max_iteration=30))
            if icp.fitness > best_fit:
                best, best_fit = np.asarray(icp.transformation), icp.fitness
        return best, seconds


def fitness(model: o3d.geometry.PointCloud, scene: o3d.geometry.PointCloud, T_scene_model: np.ndarray,
            dist: float, facing: bool = False) -> float:
    """Share of the model's points with a scene point within `dist` (m) under T_scene_model; with `facing`, of
    those whose normal faces the camera (the scene's origin) under it: the side a camera can see."""
    from scipy.spatial import cKDTree

    from gscan.geometry.transforms import transform_points

    p = transform_points(T_scene_model, np.asarray(model.points))
    if facing:
        n = np.asarray(model.normals) @ T_scene_model[:3, :3].T
        p = p[(n * p).sum(1) < 0]
    if not len(p) or not len(scene.points):
        return 0.0
    return float((cKDTree(np.asarray(scene.points)).query(p, distance_upper_bound=dist)[0] <= dist).mean())


_CHAINS = itertools.count()  # the PPF chains' models are named per chain: the child keeps the last one trained


def ppf_icp_chain(frames: list[RGBDFrame], depth_max: float, peer: PPFPeer) -> PeerResult:
    """PPF (model: the earlier frame's cloud) + ICP between consecutive frames, chained; a pair fails below
    MIN_FITNESS (share of the earlier frame's points with a point of the next within two FPFH voxels). The
    clouds are voxelised at PPF_VOXEL of the first frame's diameter. frames: >= 1."""
    pc0 = frame_cloud(frames[0], depth_max)
    voxel = PPF_VOXEL * float(np.linalg.norm(pc0.get_max_bound() - pc0.get_min_bound()))
    chain = next(_CHAINS)
    count = iter(range(len(frames)))

    def prepare(f: RGBDFrame):
        return f"chain {chain}/{next(count)}", frame_cloud(f, depth_max, voxel)

    def pair(src, tgt):
        (key, pc_s), (_, pc_t) = src, tgt
        if len(pc_s.points) < 10 or len(pc_t.points) < 10:
            return None, "too few points"
        T, _ = peer.register(key, pc_s, pc_t, voxel)
        if T is None:
            return None, "no PPF pose"
        fit = fitness(pc_s, pc_t, T, 2 * FPFH_VOXEL)
        return (T, "") if fit >= MIN_FITNESS else (None, f"PPF fitness {fit:.2f} < {MIN_FITNESS}")

    return _chain(frames, prepare, pair, "OpenCV PPF+ICP")


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
