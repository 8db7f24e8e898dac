"""Object segmentation in RGB-D frames: support plane + working volume, single frame or whole sequence.

Single frame (`segment_frame`): a given mask wins; otherwise the dominant support plane is
found by a seeded RANSAC on a downsampled cloud, the points in a
height band above it and inside the depth range are split into connected components on the
image grid (depth discontinuities cut them), and the component nearest the image centre
(weighted by its area) is the object. Without a plane, the same component choice runs on all
valid pixels in the depth range.

Sequence (`segment_sequence`): with registered poses T_world_cam the plane is estimated once
in the world frame from several frames, the object cluster above it (DBSCAN) defines a
cylindrical working volume (axis along the plane normal), and every frame is segmented by
that volume, so all masks agree with each other.

The working range comes from the capture, not from a fixed distance: a scan keeps the object in the
middle of the image, so the depth at the image centre (median over a central window) says how far the
object is. Depth beyond `centre_depth_factor` times that is background; the plane and the cluster are
looked for within `SUPPORT_RADII` image half-widths of the point the frames keep centred, among what most
frames have in view (`seen_by`); the RANSAC
band, the height that counts as off the table and the clustering radius grow with the depth noise
(`params.depth_noise`, the capture's own model) and the pixel spacing at that depth.

Pose estimation's search region (`off_plane_region`): the pixels in front of a query frame's dominant
plane (`support_plane`, a faster RANSAC on a strided cloud). Both plane finders share `ransac_plane`.

Planes: `height(p) = normal . p + offset`, normal pointing up (towards the cameras).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Annotated

import cv2
import numpy as np
from pydantic import Field

from gscan.errors import InputError
from gscan.geometry.plane import Plane, dominant_plane, ransac_plane
from gscan.geometry.transforms import transform_points
from gscan.io.camera import RGBDFrame, backproject
from gscan.registration.noise import DepthNoise
from gscan.settings import SETTINGS

log = logging.getLogger(__name__)

CENTRE_WINDOW = 0.2        # the central window is this fraction of the image's width and height
SUPPORT_RADII = 2.0        # plane and cluster within this many image half-widths (at the centre depth) of the centre


@dataclass(frozen=True)
class SegmentParams:
    """Where the object is looked for (working depths, support plane, working volume)."""

    __pydantic_config__ = SETTINGS

    depth_min: Annotated[float, Field(ge=0.05, le=20, description="the object is looked for at depths from this "
                                      "(m) ...")] = 0.1
    depth_max: Annotated[float | None, Field(gt=0.05, le=20, description="... to this (m); null = 1.5 x the depth at "
                                             "the image centre, where a scan keeps the object")] = None
    plane_voxel: Annotated[float, Field(gt=0, description="downsampling before the support plane's RANSAC (m)")] = 0.005
    plane_distance: Annotated[float, Field(gt=0, description="RANSAC inlier threshold (m)")] = 0.004
    plane_iterations: Annotated[int, Field(ge=1, description="RANSAC iterations")] = 1000
    plane_max_points: Annotated[int, Field(ge=3, description="RANSAC scores hypotheses on at most this many points "
                                           "(seeded subsample)")] = 5000
    min_plane_fraction: Annotated[float, Field(gt=0, le=1, description="the plane must hold this share of the sampled "
                                               "points")] = 0.15
    height_min: Annotated[float, Field(ge=0, description="band above the plane that may be object, from (m) ...")] = (
        0.004)
    height_max: Annotated[float, Field(ge=0.01, le=5, description="... to: the object stands at most this high above "
                                       "its support plane (m)")] = 0.5
    depth_edge_rel: Annotated[float, Field(gt=0, description="neighbour depth jump (relative) that separates "
                                           "components")] = 0.03
    min_area_px: Annotated[int, Field(ge=1, description="smallest component considered an object (pixels)")] = 150
    cluster_eps: Annotated[float, Field(gt=0, description="DBSCAN radius of the sequence's working volume (m)")] = 0.015
    volume_margin: Annotated[float, Field(ge=0, description="added around the object cluster, radius and height "
                                          "(m)")] = 0.02
    volume_frames: Annotated[int, Field(ge=1, description="frames (evenly spaced) the working volume is built "
                                        "from")] = 6
    seed: Annotated[int, Field(ge=0, description="random seed")] = 0
    centre_depth_factor: Annotated[float, Field(gt=1, le=10, description="with depth_max null, the working range "
                                                "ends at this multiple of the depth at the image centre")] = 1.5
    noise_sigmas: Annotated[float, Field(gt=0, description="a point is off the plane when it is this many depth "
                                         "sigmas above it (the bands widen with the depth noise)")] = 3.0
    seen_by: Annotated[float, Field(gt=0, le=1, description="the object is inside the image of at least this share "
                                    "of the frames (what most frames leave out is not the object)")] = 0.8
    background_frames: Annotated[int, Field(ge=1, le=1000, description="a moving object without a support plane (in "
                                            "hand) is what stands out of the background depth, taken from this many "
                                            "kept frames (evenly spaced)")] = 30
    depth_noise: Annotated[DepthNoise, Field(description="depth noise that widens the bands above at depth: the prior "
                                             "a moving object's masks are found with at the load; a scan's segment "
                                             "stage uses the capture's own")] = DepthNoise()

    def __post_init__(self) -> None:
        if self.depth_max is not None and self.depth_max <= self.depth_min:
            raise ValueError("depth_max must be greater than depth_min")


def centre_depth(frame: RGBDFrame) -> float | None:
    """Median depth (m) of the valid pixels in the central window (`CENTRE_WINDOW` of each image side): how far
    the camera keeps the object. None when that window has no depth."""
    H, W = frame.depth.shape
    h, w = max(1, round(H * CENTRE_WINDOW / 2)), max(1, round(W * CENTRE_WINDOW / 2))
    win = frame.depth[H // 2 - h: H // 2 + h, W // 2 - w: W // 2 + w]
    z = win[win > 0]
    return float(np.median(z)) if len(z) else None


def depth_range(params: SegmentParams, z: float | None) -> tuple[float, float]:
    """(min, max) depth (m) where the object is looked for in a frame of `centre_depth` z: `params.depth_max` when
    set, else `centre_depth_factor` x z (all depth when the centre has none)."""
    if params.depth_max is not None:
        return params.depth_min, params.depth_max
    return params.depth_min, (np.inf if z is None else max(params.centre_depth_factor * z, params.depth_min + 0.05))


def at_depth(params: SegmentParams, z: float | None, focal_px: float, stride: int = 1) -> SegmentParams:
    """`params` with the plane band, the off-plane height and the clustering radius widened to the depth noise
    (`noise_sigmas` sigma) and the spacing of every `stride`-th pixel at depth z (m); unchanged without z."""
    if z is None:
        return params
    sigma = float(params.depth_noise.sigma(z))
    spacing = stride * z / focal_px
    return replace(params, plane_distance=max(params.plane_distance, 2.5 * sigma),
                   height_min=max(params.height_min, params.noise_sigmas * sigma),
                   cluster_eps=max(params.cluster_eps, 1.5 * spacing, params.noise_sigmas * sigma))


@dataclass
class Segmentation:
    mask: np.ndarray            # [H x W] bool
    plane_cam: Plane | None     # support plane in the camera frame (None: not found / not estimated)
    method: str                 # "given" | "plane" | "depth" | "volume"
    reason: str | None = None   # note when a fallback was used


@dataclass(frozen=True)
class WorkingVolume:
    """Vertical cylinder over the support plane: base centre on the plane, axis = plane normal."""

    plane_world: Plane
    center_world: np.ndarray    # [3] on the plane
    radius: float               # m
    height: float               # m above the plane
    height_min: float = 0.0     # m: nearer the plane is the plane (its depth noise)

    def contains(self, pts_world: np.ndarray, height_min: float = 0.0) -> np.ndarray:
        """[N x 3] world points -> [N] bool inside the cylinder (heights in [height_min, height])."""
        p = np.asarray(pts_world, dtype=np.float64)
        h = self.plane_world.height(p)
        h0 = self.plane_world.height(self.center_world[None])[0]
        radial = p - self.center_world - (h - h0)[:, None] * self.plane_world.normal
        return (h >= height_min) & (h <= self.height) & (np.linalg.norm(radial, axis=1) <= self.radius)


    def contains_camera(self, pts_cam: np.ndarray, T_world_cam: np.ndarray, height_min: float = 0.0) -> np.ndarray:
        """`contains` for camera-frame points [... x 3] of a camera at T_world_cam (float32 fast path)."""
        T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
        pl = self.plane_world.transformed(T_cam_world)
        c = (T_cam_world[:3, :3] @ self.center_world + T_cam_world[:3, 3]).astype(np.float32)
        n = pl.normal.astype(np.float32)
        d = np.asarray(pts_cam, dtype=np.float32) - c
        along = d @ n  # height above the base centre (the centre is on the plane)
        radial2 = np.einsum("...i,...i->...", d, d) - along * along
        return (along >= height_min) & (along <= self.height) & (radial2 <= self.radius ** 2)


def fit_support_plane(points: np.ndarray, viewpoint: np.ndarray,
                      params: SegmentParams = SegmentParams()) -> Plane | None:
    """Dominant plane of [N x 3] points by seeded RANSAC, normal oriented towards `viewpoint` [3].

    The points are voxel-downsampled (`plane_voxel`) and sorted, then `ransac_plane` scores
    `plane_iterations` random triplets (numpy generator seeded by `params.seed`; open3d's
    `segment_plane` is not repeatable across runs because of its threading) by inlier count within
    `plane_distance` on at most `plane_max_points` points; the best plane is refined by least squares
    on all its inliers (twice). Returns None when the plane holds fewer than `min_plane_fraction` of
    the downsampled points.
    """
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    P = np.asarray(pc.voxel_down_sample(params.plane_voxel).points)
    P = P[np.lexsort((P[:, 2], P[:, 1], P[:, 0]))]
    n = len(P)
    if n < 50:
        return None
    rng = np.random.default_rng(params.seed)
    S = P if n <= params.plane_max_points else P[np.sort(rng.choice(n, params.plane_max_points, replace=False))]
    found = ransac_plane(S, params.plane_iterations, rng, params.plane_distance, viewpoint)
    best_count = 0 if found is None else int(found[1].sum())
    if found is None or best_count < params.min_plane_fraction * len(S):
        log.debug("support plane: %d of %d points, below %.2f", best_count, len(S), params.min_plane_fraction)
        return None
    normal, offset = found[0].normal, found[0].offset
    for _ in range(2):  # least-squares refinement on the inliers
        inl = P[np.abs(P @ normal + offset) < params.plane_distance]
        if len(inl) < 3:
            break
        mu = inl.mean(0)
        _, _, Vt = np.linalg.svd(inl - mu, full_matrices=False)
        normal = Vt[2] * (1.0 if Vt[2] @ normal >= 0 else -1.0)
        offset = float(-normal @ mu)
    plane = Plane(normal, float(offset))
    if plane.height(np.asarray(viewpoint, dtype=np.float64)[None])[0] < 0:
        plane = Plane(-plane.normal, -plane.offset)
    return plane


def support_plane(frame: RGBDFrame, min_frac: float = 0.3, iterations: int = 64, stride: int = 6) -> Plane | None:
    """The frame's dominant plane (a table top) in its camera frame, normal towards the camera, or None when
    no plane holds `min_frac` of the valid depth: `dominant_plane` of its cloud, the fast finder pose estimation
    uses."""
    return dominant_plane(backproject(frame.depth, frame.intrinsics), min_frac, iterations, stride)


def in_front_of(frame: RGBDFrame, plane: Plane) -> np.ndarray | None:
    """[H x W] bool: valid-depth pixels on the camera's side of `plane` (camera frame) by more than 8 mm +
    0.5 % of their depth, or None when they are fewer than 0.2 % of the frame (nothing stands on it)."""
    depth = frame.depth
    hp = plane.height(backproject(depth, frame.intrinsics).reshape(-1, 3))
    z = depth.reshape(-1)
    region = (z > 0) & (hp > 0.008 + 0.005 * z)
    if region.mean() < 0.002:
        return None
    return region.reshape(depth.shape)


def off_plane_region(frame: RGBDFrame, min_frac: float = 0.3, iterations: int = 64, stride: int = 6
                     ) -> np.ndarray | None:
    """`in_front_of` the frame's `support_plane`: the pixels standing off the table, or None without a plane
    or with nothing on it."""
    plane = support_plane(frame, min_frac, iterations, stride)
    return None if plane is None else in_front_of(frame, plane)


def _depth_edges(depth: np.ndarray, rel: float) -> np.ndarray:
    """[H x W] bool: pixels with a 4-neighbour whose depth differs by more than rel * depth."""
    d = depth.astype(np.float32)
    edge = np.zeros(d.shape, dtype=bool)
    for dy, dx in ((0, 1), (1, 0)):
        a, b = d[: d.shape[0] - dy, : d.shape[1] - dx], d[dy:, dx:]
        jump = np.abs(a - b) > rel * np.maximum(a, b)
        edge[: d.shape[0] - dy, : d.shape[1] - dx] |= jump
        edge[dy:, dx:] |= jump
    return edge


def _fill_holes(mask: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """Add enclosed holes of `mask` where `allowed` ([H x W] bool) is True."""
    m = mask.astype(np.uint8)
    padded = np.pad(1 - m, 1, constant_values=1)
    ff = padded.copy()
    cv2.floodFill(ff, None, (0, 0), 2)
    holes = (ff[1:-1, 1:-1] == 1)
    return mask | (holes & allowed)


def pick_component(cand: np.ndarray, depth: np.ndarray, params: SegmentParams, keep_fraction: float = 0.0
                   ) -> np.ndarray:
    """Object mask from candidate pixels [H x W] bool: connected components cut at depth edges.

    The chosen component maximises area / (1 + (distance of its centroid to the image centre
    / (0.25 * image diagonal))^2); with keep_fraction > 0 every component of at least that
    fraction of the chosen one's area is kept too. The result is grown back over the edge
    pixels (2 px, within `cand`) and its enclosed holes without depth are filled.
    """
    H, W = cand.shape
    core = cand & ~_depth_edges(depth, params.depth_edge_rel)
    n, labels, stats, cents = cv2.connectedComponentsWithStats(core.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(cand)
    areas = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    dist = np.linalg.norm(cents[1:] - np.array([(W - 1) / 2, (H - 1) / 2]), axis=1)
    score = np.where(areas >= params.min_area_px, areas / (1.0 + (dist / (0.25 * np.hypot(W, H))) ** 2), -1.0)
    best = int(np.argmax(score))
    if score[best] < 0:
        return np.zeros_like(cand)
    keep = np.zeros(n, dtype=bool)
    keep[best + 1] = True
    if keep_fraction > 0:
        keep[1:] |= (areas >= max(keep_fraction * areas[best], params.min_area_px))
    mask = keep[labels]
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool) & cand
    return _fill_holes(mask | grown, depth <= 0)


def segment_frame(frame: RGBDFrame, params: SegmentParams = SegmentParams(),
                  mask: np.ndarray | None = None) -> Segmentation:
    """Object mask of one frame: `mask`, else `frame.mask` (returned as given), else automatic
    (support plane + component; without a usable plane, the central component of the valid depth).

    Raises InputError (naming the frame's file) when a given mask's size differs from the depth's.
    """
    given = mask if mask is not None else frame.mask
    if given is not None:
        given = np.asarray(given, dtype=bool)
        if given.shape != frame.depth.shape:
            raise InputError(frame.source, f"mask {given.shape[1::-1]} and depth {frame.depth.shape[1::-1]} "
                             f"sizes differ (frame {frame.name})")
        return Segmentation(given.copy(), None, "given")
    depth = frame.depth
    z = centre_depth(frame)
    lo, hi = depth_range(params, z)
    params = at_depth(params, z, frame.intrinsics.fx, 2)
    valid = (depth >= lo) & (depth <= hi)
    pts = backproject(depth, frame.intrinsics)
    plane = fit_support_plane(pts[::2, ::2][valid[::2, ::2]], np.zeros(3), params)
    if plane is not None:
        h = plane.height(pts)
        cand = valid & (h > params.height_min) & (h < params.height_max)
        m = pick_component(cand, depth, params)
        if m.any():
            return Segmentation(m, plane, "plane")
        why = "nothing above the dominant plane (an object face?)"
    else:
        why = "no support plane found"
    m = pick_component(valid, depth, params)
    return Segmentation(m, None, "depth", f"{why}: component nearest the image centre")


def _look_at_point(T_world_cam: list[np.ndarray], plane: Plane) -> np.ndarray:
    """[3] point the cameras look at: least-squares meeting point of the optical axes when they
    spread, else where the first optical axis meets the plane."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for T in T_world_cam:
        z, c = T[:3, 2], T[:3, 3]
        P = np.eye(3) - np.outer(z, z)
        A += P
        b += P @ c
    if len(T_world_cam) >= 2 and np.linalg.cond(A) < 1e4:
        return np.linalg.solve(A, b)
    c, z = T_world_cam[0][:3, 3], T_world_cam[0][:3, 2]
    denom = plane.normal @ z
    t = -plane.height(c[None])[0] / denom if abs(denom) > 1e-6 else 0.5
    return c + max(t, 0.0) * z


def _centre_point(frames: list[RGBDFrame], T_world_cam: list[np.ndarray], depths: list[float | None]
                  ) -> np.ndarray | None:
    """[3] world point the frames keep in the middle of the image: per frame the point on the optical axis at
    its `centre_depth` (`depths`, one per frame), then the coordinate-wise median over the frames (robust to a
    few frames that look elsewhere). Unlike the axes' meeting point it needs no spread of viewing directions (a
    hand-held sweep looks along nearly parallel axes). None when no frame has centre depth."""
    pts = []
    for f, T, z in zip(frames, T_world_cam, depths, strict=True):
        if z is not None:
            K = f.intrinsics
            H, W = f.depth.shape
            ray = np.array([((W - 1) / 2 - K.cx) / K.fx, ((H - 1) / 2 - K.cy) / K.fy, 1.0])
            pts.append(T[:3, :3] @ (z * ray) + T[:3, 3])
    return np.median(np.asarray(pts), axis=0) if pts else None


def _seen_by_most(points_world: np.ndarray, frames: list[RGBDFrame], T_world_cam: list[np.ndarray],
                  seen_by: float) -> np.ndarray:
    """[N] bool: the points [N x 3] inside the image of at least `seen_by` of the frames: a scan keeps its
    object in view, so what most frames leave out (the far end of a room a sweep passes) is not the object."""
    seen = np.zeros(len(points_world), dtype=int)
    for f, T in zip(frames, T_world_cam, strict=True):
        p = transform_points(np.linalg.inv(T), points_world)
        K = f.intrinsics
        z = np.where(p[:, 2] > 1e-6, p[:, 2], np.nan)
        u, v = K.fx * p[:, 0] / z + K.cx, K.fy * p[:, 1] / z + K.cy
        seen += (u >= 0) & (u <= K.width - 1) & (v >= 0) & (v <= K.height - 1)
    return seen >= seen_by * len(frames)


def estimate_working_volume(frames: Sequence[RGBDFrame], T_world_cam: list[np.ndarray],
                            params: SegmentParams = SegmentParams()) -> WorkingVolume | None:
    """Support plane (world frame) and a cylinder around the object cluster on it (`frames`: any sequence,
    only the frames used are read).

    Uses `volume_frames` frames evenly spaced over the sequence (stride-4 points in each frame's
    `depth_range`) within `SUPPORT_RADII` image half-widths of the point they keep centred; the bands follow
    the noise at the median centre depth (`at_depth`). The cluster nearest that point (by size and distance)
    is the object. Returns None when no plane or no cluster above it is found.
    """
    import open3d as o3d

    if not frames:
        return None
    idx = np.unique(np.linspace(0, len(frames) - 1, min(params.volume_frames, len(frames))).round().astype(int))
    used = [frames[i] for i in idx]
    cams = [T_world_cam[i] for i in idx]
    depths = [centre_depth(f) for f in used]
    known = [z for z in depths if z is not None]
    z_c = float(np.median(known)) if known else None
    K = used[0].intrinsics
    par = at_depth(params, z_c, K.fx, 4)
    pts = []
    for f, T, z in zip(used, cams, depths, strict=True):
        lo, hi = depth_range(params, z)
        valid = (f.depth >= lo) & (f.depth <= hi)
        p = backproject(f.depth, f.intrinsics)[::4, ::4][valid[::4, ::4]]
        pts.append(transform_points(T, p))
    P = np.concatenate(pts)
    centre = _centre_point(used, cams, depths)
    reach = np.inf
    if centre is not None and z_c is not None:
        reach = SUPPORT_RADII * z_c * min(K.width / K.fx, K.height / K.fy) / 2
        P = P[np.linalg.norm(P - centre, axis=1) <= reach]
    plane = fit_support_plane(P, np.mean([T[:3, 3] for T in cams], axis=0), par)
    if plane is None:
        return None
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P)).voxel_down_sample(par.plane_voxel)
    Q = np.asarray(pc.points)
    Q = Q[np.lexsort((Q[:, 2], Q[:, 1], Q[:, 0]))]  # order-independent clustering input
    h = plane.height(Q)
    Q = Q[(h > par.height_min) & (h < par.height_max)]
    Q = Q[_seen_by_most(Q, used, cams, params.seen_by)]
    if len(Q) < 20:
        return None
    labels = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(Q)).cluster_dbscan(
        par.cluster_eps, min_points=8))
    target = centre if centre is not None else _look_at_point(cams, plane)
    scale = max(0.1, reach / 8) if np.isfinite(reach) else 0.1
    best, best_score = -1, -np.inf
    for lab in range(labels.max() + 1):
        C = Q[labels == lab]
        d = np.linalg.norm(C.mean(0) - target)
        score = float(len(C) / (1.0 + (d / scale) ** 2))
        if len(C) >= 20 and score > best_score:
            best, best_score = lab, score
    if best < 0:
        return None
    C = Q[labels == best]
    hc = plane.height(C)
    foot = C - hc[:, None] * plane.normal
    centre = foot.mean(0)
    radius = float(np.linalg.norm(foot - centre, axis=1).max()) + params.volume_margin
    vol = WorkingVolume(plane, centre, radius, float(hc.max()) + params.volume_margin, par.height_min)
    log.info("working volume: radius %.3f m, height %.3f m, %d cluster points (centre depth %s m)", vol.radius,
             vol.height, len(C), "?" if z_c is None else f"{z_c:.2f}")
    return vol


def segment_sequence(frames: list[RGBDFrame], T_world_cam: list[np.ndarray | None],
                     params: SegmentParams = SegmentParams()) -> tuple[list[Segmentation], WorkingVolume | None]:
    """Masks of registered frames from one working volume; given masks win.

    Frames whose pose is None get an empty mask. Without a volume (no plane or cluster found)
    every frame falls back to `segment_frame`. `segment_in_volume` segments one frame the same way.
    """
    if len(frames) != len(T_world_cam):
        raise ValueError(f"{len(frames)} frames but {len(T_world_cam)} poses")
    reg = [(f, T) for f, T in zip(frames, T_world_cam, strict=True) if T is not None]
    vol = estimate_working_volume([f for f, _ in reg], [T for _, T in reg], params)
    return [segment_in_volume(f, T, vol, params) for f, T in zip(frames, T_world_cam, strict=True)], vol


def segment_in_volume(frame: RGBDFrame, T_world_cam: np.ndarray | None, vol: WorkingVolume | None,
                      params: SegmentParams = SegmentParams()) -> Segmentation:
    """One frame of `segment_sequence`: its given mask, an empty mask when it has no pose, the component inside
    the working volume `vol`, or without a volume `segment_frame`."""
    f, T = frame, T_world_cam
    if f.mask is not None:
        return segment_frame(f, params)
    if T is None:
        return Segmentation(np.zeros(f.depth.shape, dtype=bool), None, "volume", "frame not registered")
    if vol is None:
        s = segment_frame(f, params)
        s.reason = (s.reason + "; " if s.reason else "") + "no working volume for the sequence"
        return s
    lo, hi = depth_range(params, centre_depth(f))
    valid = (f.depth >= lo) & (f.depth <= hi)
    cand = valid & vol.contains_camera(backproject(f.depth, f.intrinsics), T, vol.height_min)
    m = pick_component(cand, f.depth, params, keep_fraction=0.05)
    return Segmentation(m, vol.plane_world.transformed(np.linalg.inv(T)), "volume")
