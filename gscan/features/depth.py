"""Keypoints of the depth's own geometry: where the object's surface has shape, described by FPFH.

SIFT sees print; a plain object (a white box, a bare bottle) gives it few keypoints or none. Its depth
still has corners, edges and curved patches. This module finds them and describes them so that GMatch can
search them like SIFT keypoints (its geometric search does not care where the candidates come from):

- the frame's points (the mask's only, when given: the object's) are voxel-downsampled and their normals
  estimated; keypoints are open3d's ISS (intrinsic shape signatures: points whose neighbourhood's scatter
  has three distinct eigenvalues, i.e. a corner or a curved patch, not a plane or a straight edge);
- each keypoint is described by open3d's FPFH (33 bins, three 11-bin angle histograms of the point pairs
  within the feature radius), turned into "RootFPFH" like RootSIFT (each histogram L1-normalised,
  square-rooted, the whole unit-L2) so that L2 distances lie in [0, sqrt(2)] as RootSIFT's do.

Scales (`depth_scales`): every radius is tied to the object's size (twice the 90th percentile of the points'
distance to their median, `size`) and to the depth noise at its depth (sigma from `DepthNoise`): the voxel
is max(size x depth_voxel_rel, depth_noise_voxel x sigma), the normal radius 3 voxels, the ISS salient and
non-maximum radii depth_salient_rel / depth_nonmax_rel of the size, the FPFH radius depth_fpfh_rel of the size
(at least 5 voxels); the depth_* fields of `FeatureParams`. A noise-sized voxel keeps the normals (and so
FPFH's angles) from describing the noise. A keypoint's position is known to voxel / sqrt(3) per axis
(`location_sigma`), which registration adds to the depth noise of its pairs.

Deterministic: the downsampled points are sorted before open3d's normals, ISS and FPFH see them, and the
keypoints are sorted by decreasing saliency (the smallest eigenvalue of their neighbourhood's scatter), ties
by (v, u); the same frame gives identical arrays (tested).

- `depth_keypoints(frame, sigma_of_z, params, mask) -> DepthKeypoints`; `joint_features(image, depth) ->
  Features` (kind rootsift+fpfh); `extract_keypoints(frame, params, source, sigma_of_z, mask)`: one call for
  "sift" | "depth" | "both"; `choose_source(params, counts)`: what `features.keypoints: auto` picks.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gscan.features.keypoints import JOINT, Detection, FeatureParams, Features, empty_features, extract_features
from gscan.io.camera import RGBDFrame, point_cloud
from gscan.io.sequence import spread_indices

log = logging.getLogger(__name__)

FPFH_DIM = 33


@dataclass(frozen=True)
class DepthScales:
    """The radii depth keypoints are found and described at (m), from the object's size and depth noise."""

    size: float  # the object's size: twice the 90th percentile distance of its points to their median
    voxel: float
    normal_radius: float
    salient_radius: float
    nonmax_radius: float
    fpfh_radius: float


# ISS: a point is salient when its scatter's eigenvalues fall by at least this ratio twice (open3d's default),
# with at least this many neighbours
_ISS_GAMMA, _ISS_MIN_NEIGHBORS = 0.975, 5


def object_size(points: np.ndarray) -> float:
    """An object's size (m) from its points [N x 3]: twice the 90th percentile distance to their median."""
    c = np.median(points, axis=0)
    return 2.0 * float(np.percentile(np.linalg.norm(points - c, axis=1), 90))


def median_object_size(point_sets: Iterable[np.ndarray]) -> float | None:
    """The median `object_size` (m) of the views' object points [N_i x 3] of 50 points or more: the one size a
    template's depth keypoints, and a query's, are found at; None when no view has 50 points."""
    sizes = [object_size(np.asarray(p, np.float64)) for p in point_sets if len(p) >= 50]
    return float(np.median(sizes)) if sizes else None


def depth_scales(points: np.ndarray, sigma: float, p: FeatureParams, size: float | None = None) -> DepthScales:
    """The radii for an object of points [N x 3] (m) whose depth noise is sigma (m, per axis, at its depth); size:
    the object's size when known (a template's, for a query whose points are not the object's alone), else
    `object_size(points)`."""
    size = object_size(points) if size is None else float(size)
    voxel = max(size * p.depth_voxel_rel, p.depth_noise_voxel * sigma)
    return DepthScales(size, voxel, 3.0 * voxel, max(size * p.depth_salient_rel, 2.0 * voxel),
                       max(size * p.depth_nonmax_rel, voxel), max(size * p.depth_fpfh_rel, 5.0 * voxel))


def root_fpfh(h: np.ndarray) -> np.ndarray:
    """[N x 33] FPFH histograms -> RootFPFH [N x 33] float32: each 11-bin histogram L1-normalised, square-rooted,
    the vector unit-L2 (a zero histogram stays zero)."""
    h = np.maximum(np.asarray(h, dtype=np.float64).reshape(-1, 3, 11), 0.0)
    h = np.sqrt(h / np.maximum(h.sum(axis=2, keepdims=True), 1e-12)).reshape(-1, FPFH_DIM)
    return (h / np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)).astype(np.float32)


@dataclass
class DepthKeypoints:
    """Depth keypoints of one frame: pixels [N x 2] float32 (u, v), points [N x 3] float32 (camera frame, m),
    descriptors [N x 33] float32 RootFPFH, saliency [N] float64 (ISS smallest eigenvalue), scales (the radii)."""

    pixels: np.ndarray
    points: np.ndarray
    descriptors: np.ndarray
    saliency: np.ndarray
    scales: DepthScales | None

    def __len__(self) -> int:
        return len(self.pixels)

    @property
    def location_sigma(self) -> float:
        """Per-axis standard deviation (m) of each keypoint's position on the surface (`location_sigma`)."""
        return 0.0 if self.scales is None else location_sigma(self.scales)


def location_sigma(scales: DepthScales) -> float:
    """Per-axis standard deviation (m) of a depth keypoint's position on the object's surface.

    A keypoint is a point of the voxel-downsampled cloud (one per occupied voxel) where ISS's saliency peaks
    within the non-maximum radius. Another view voxelises the object on a grid that the object's motion has
    shifted by an arbitrary fraction of a voxel, so the same peak falls on the voxel point of the cell that
    now holds it or on a neighbour's: per axis, anywhere within one voxel either side, uniformly, which gives a
    standard deviation of voxel / sqrt(3). The salient and FPFH radii are larger, but they set what a keypoint
    describes, not where it sits.
    """
    return scales.voxel / float(np.sqrt(3.0))


def _empty() -> DepthKeypoints:
    return DepthKeypoints(np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32),
                          np.zeros((0, FPFH_DIM), np.float32), np.zeros(0), None)


def depth_keypoints(frame: RGBDFrame, sigma_of_z: Callable[[np.ndarray], np.ndarray],
                    params: FeatureParams, mask: np.ndarray | None = None,
                    stride: int = 1, size: float | None = None, max_keypoints: int | None = None) -> DepthKeypoints:
    """Depth keypoints of `frame` (module docstring), on the pixels of `mask` [H x W] bool when given.

    sigma_of_z: the depth noise, a callable z [N] (m) -> per-axis sigma [N] (m) (`DepthNoise.sigma`).
    params: the depth_* fields set the scales and the count (depth_max_keypoints).
    stride: pixel stride of the points read (1: every pixel).
    size: the object's size (m) the scales follow (None: the points', `object_size`: they are the object's).
    max_keypoints: the count kept (None: depth_max_keypoints).
    Returns DepthKeypoints (N <= the count; empty when fewer than 50 points or no salient point).
    """
    import open3d as o3d

    pts = point_cloud(frame, mask, stride)[0].astype(np.float64)
    if len(pts) < 50:
        return _empty()
    z = float(np.median(pts[:, 2]))
    sc = depth_scales(pts, float(np.asarray(sigma_of_z(np.array([z])))[0]), params, size)
    prev = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(sc.voxel)
        down = np.asarray(pcd.points)
        # voxel_down_sample's output order follows its hash map: sort it for determinism
        order = np.lexsort((down[:, 0], down[:, 1], down[:, 2]))
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(down[order]))
        if len(pcd.points) < 20:
            return _empty()
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=sc.normal_radius, max_nn=30))
        # normals towards the camera (the origin): FPFH's angles depend on their sign
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        kp = o3d.geometry.keypoint.compute_iss_keypoints(pcd, salient_radius=sc.salient_radius,
                                                         non_max_radius=sc.nonmax_radius, gamma_21=_ISS_GAMMA,
                                                         gamma_32=_ISS_GAMMA, min_neighbors=_ISS_MIN_NEIGHBORS)
        kpts = np.asarray(kp.points)
        if len(kpts) == 0:
            return _empty()
        cloud = np.asarray(pcd.points)
        tree = o3d.geometry.KDTreeFlann(pcd)
        idx = np.array([tree.search_knn_vector_3d(p, 1)[1][0] for p in kpts], dtype=np.int64)
        idx = np.unique(idx)
        # every point's FPFH, then the keypoints': open3d's indexed variant gives other histograms (measured)
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(  # type: ignore[call-arg]  # stub: indexed form only
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=sc.fpfh_radius, max_nn=100))
        hist = np.asarray(fpfh.data).T[idx]
        sal = _iss_saliency(cloud, idx, tree, sc.salient_radius)
    finally:
        o3d.utility.set_verbosity_level(prev)
    p = cloud[idx]
    intr = frame.intrinsics
    u = intr.fx * p[:, 0] / p[:, 2] + intr.cx
    v = intr.fy * p[:, 1] / p[:, 2] + intr.cy
    keep = np.isfinite(sal) & (hist.sum(axis=1) > 0)
    o = np.flatnonzero(keep)
    o = o[np.lexsort((u[o], v[o], -sal[o]))][: params.depth_max_keypoints if max_keypoints is None else max_keypoints]
    log.debug("frame %s: %d depth keypoints (size %.3f m, voxel %.4f m, fpfh radius %.3f m)", frame.name, len(o),
              sc.size, sc.voxel, sc.fpfh_radius)
    return DepthKeypoints(np.stack([u[o], v[o]], 1).astype(np.float32), p[o].astype(np.float32),
                          root_fpfh(hist[o]), sal[o], sc)


def _iss_saliency(cloud: np.ndarray, idx: np.ndarray, tree: Any, radius: float) -> np.ndarray:
    """[K] the smallest eigenvalue of the scatter matrix of the points within `radius` of cloud[idx] (ISS's
    saliency: large where the surface bends in every direction)."""
    out = np.full(len(idx), np.nan)
    for k, i in enumerate(idx):
        n, nb, _ = tree.search_radius_vector_3d(cloud[i], radius)
        if n < 5:
            continue
        q = cloud[np.asarray(nb)] - cloud[i]
        out[k] = np.linalg.eigvalsh(q.T @ q / n)[0]
    return out


# RootFPFH distances are scaled by this in a joint set, so that one threshold (RootSIFT's eps_f, 0.6) admits
# the FPFH pairs within FPFH_EPS_F: both kinds' candidates are then ranked by one ratio test in one list.
# A pair of different kinds is sqrt(1 + FPFH_SCALE^2) apart, beyond any threshold below sqrt(2).
FPFH_EPS_F = 0.3
FPFH_SCALE = 0.6 / FPFH_EPS_F


def joint_features(image: Features | None, depth: DepthKeypoints | None) -> Features:
    """One keypoint set of kind rootsift+fpfh: `image` (RootSIFT; None: none) then the depth keypoints (None:
    none), each descriptor [161] its own kind's part with zeros in the other's (the FPFH part scaled by
    FPFH_SCALE); a depth keypoint's scale is its location sigma (m, `location_sigma`)."""
    if image is not None and image.kind != "rootsift":
        raise ValueError(f"depth keypoints join rootsift image keypoints, not {image.kind}")
    img = image if image is not None else empty_features("rootsift")
    depth = depth if depth is not None else _empty()
    ni, nd = len(img), len(depth)
    desc = np.zeros((ni + nd, 128 + FPFH_DIM), np.float32)
    desc[:ni, :128] = img.descriptors
    desc[ni:, 128:] = depth.descriptors * np.float32(FPFH_SCALE)
    scales = np.concatenate([img.scales if img.scales is not None else np.zeros(ni, np.float32),
                             np.full(nd, depth.location_sigma, np.float32)]).astype(np.float32)
    return Features(pixels=np.concatenate([img.pixels, depth.pixels]).astype(np.float32),
                    points=np.concatenate([img.points, depth.points]).astype(np.float32),
                    descriptors=desc, kind=JOINT, scales=scales)


def extract_keypoints(frame: RGBDFrame, params: FeatureParams, source: str,
                      sigma_of_z: Callable[[np.ndarray], np.ndarray], mask: np.ndarray | None = None,
                      detection: Detection | None = None) -> Features:
    """A frame's keypoints of `source` ("sift": the image's alone, as `extract_features`; "depth": the depth's
    alone; "both": the image's then the depth's, one rootsift+fpfh set), in `mask` when given.
    sigma_of_z: the depth noise (`depth_keypoints`); detection: the image's, as `extract_features` takes it."""
    if source == "sift":
        return extract_features(frame, params, mask=mask, detection=detection)
    if source not in ("depth", "both"):
        raise ValueError(f"keypoint source must be sift, depth or both, not {source!r}")
    image = extract_features(frame, params, mask=mask, detection=detection) if source == "both" else None
    return joint_features(image, depth_keypoints(frame, sigma_of_z, params, mask))


AUTO_PILOT = 8  # frames spread over a capture whose image keypoints decide `keypoints: auto`


def pilot_frames(n: int) -> list[int]:
    """The indices of the at most AUTO_PILOT frames (or views) spread over n whose image keypoints decide
    `keypoints: auto` (`choose_source`)."""
    return spread_indices(n, AUTO_PILOT)


def choose_source(params: FeatureParams, counts: list[int]) -> str:
    """The keypoints a capture registers with ("sift" | "depth" | "both"): params.keypoints unless "auto";
    auto: "both" when the median of `counts` (image keypoints of the pilot frames) is below
    params.auto_min_keypoints and the image descriptor is rootsift, else "sift"."""
    if params.keypoints != "auto":
        return params.keypoints
    if params.kind != "rootsift" or not counts:
        return "sift"
    return "both" if float(np.median(counts)) < params.auto_min_keypoints else "sift"
