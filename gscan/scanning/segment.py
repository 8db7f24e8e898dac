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

Which object (`estimate_working_volume`): the one the views look at. The fixation point is where the optical
axes pass closest (a sweep's nearly parallel axes leave its depth to the views' centre depth); the support
plane is fitted within `SUPPORT_RADII` image half-widths of it, and the support surface is the plane's inliers
under it (holes filled: what stands on it hides it). Among the clusters standing on that surface (the surface
all round their footprint: not beside it, not overhanging its edge) the one held in the central
`CENTRE_REGION` of the most views is the object; when none is there in `CENTRED` of the views, the object is
the surface and what stands on it (a table swept past). The user may choose instead (`object_hint`: a box or
a mask of the first frame). `ChosenObject` says which and why.

The working range comes from the capture, not from a fixed distance: a scan keeps the object in the
middle of the image, so the depth at the image centre (median over a central window) says how far the
object is. Depth beyond `centre_depth_factor` times that is background; the RANSAC band, the height that
counts as off the table and the clustering radius grow with the depth noise (`params.depth_noise`, the
capture's own model) and the pixel spacing at that depth.

Pose estimation's search region (`off_plane_region`): the pixels in front of a query frame's dominant
plane (`support_plane`, a faster RANSAC on a strided cloud). Both plane finders share `ransac_plane`.

Planes: `height(p) = normal . p + offset`, normal pointing up (towards the cameras).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from pydantic import Field

from gscan.errors import InputError
from gscan.geometry.plane import Plane, dominant_plane, ransac_plane
from gscan.geometry.transforms import transform_points
from gscan.io.camera import Intrinsics, RGBDFrame, backproject
from gscan.io.sequence import spread_indices
from gscan.registration.noise import DepthNoise
from gscan.settings import SETTINGS

log = logging.getLogger(__name__)

CENTRE_WINDOW = 0.2        # the central window is this fraction of the image's width and height
SUPPORT_RADII = 2.0        # plane and cluster within this many image half-widths (at the centre depth) of the centre
FIXATION_SPREAD = 0.1      # axes turning less than this (mean sin^2 of their angles, ~18 deg) leave the fixation
                           # point along that direction to the views' centre depth
CENTRE_REGION = 0.5        # a view's centre: this central fraction of its image's width and height
CENTRED = 0.5              # what stands at the centre of at least this share of the views is the object


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
    """Vertical cylinder over the support plane: base centre on the plane, axis = plane normal; with a
    `footprint`, only the part of it over that region of the plane (`Footprint`)."""

    plane_world: Plane
    center_world: np.ndarray    # [3] on the plane
    radius: float               # m
    height: float               # m above the plane
    height_min: float = 0.0     # m: nearer the plane is the plane (its depth noise)
    chosen: ChosenObject | None = None  # which object the volume holds, and why
    footprint: Footprint | None = None  # the region of the plane it stands on (None: the whole disc)

    def contains(self, pts_world: np.ndarray, height_min: float = 0.0) -> np.ndarray:
        """[N x 3] world points -> [N] bool inside the cylinder (heights in [height_min, height])."""
        p = np.asarray(pts_world, dtype=np.float64)
        h = self.plane_world.height(p)
        h0 = self.plane_world.height(self.center_world[None])[0]
        radial = p - self.center_world - (h - h0)[:, None] * self.plane_world.normal
        inside = (h >= height_min) & (h <= self.height) & (np.linalg.norm(radial, axis=1) <= self.radius)
        if self.footprint is not None:
            inside &= self.footprint.covers(p)
        return inside


    def contains_camera(self, pts_cam: np.ndarray, T_world_cam: np.ndarray, height_min: float = 0.0) -> np.ndarray:
        """`contains` for camera-frame points [... x 3] of a camera at T_world_cam (float32 fast path)."""
        T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
        pl = self.plane_world.transformed(T_cam_world)
        c = (T_cam_world[:3, :3] @ self.center_world + T_cam_world[:3, 3]).astype(np.float32)
        n = pl.normal.astype(np.float32)
        d = np.asarray(pts_cam, dtype=np.float32) - c
        along = d @ n  # height above the base centre (the centre is on the plane)
        radial2 = np.einsum("...i,...i->...", d, d) - along * along
        inside = (along >= height_min) & (along <= self.height) & (radial2 <= self.radius ** 2)
        if self.footprint is not None and inside.any():
            pw = transform_points(np.asarray(T_world_cam, dtype=np.float64), np.asarray(pts_cam)[inside])
            inside[inside] = self.footprint.covers(pw)
        return inside


@dataclass(frozen=True)
class Footprint:
    """A region of a plane: cells of `cell` m ([gH x gW] bool `grid`, cell (i, j) at origin + (j, i) * cell in
    the plane coordinates `basis` [2 x 3] . p)."""

    grid: np.ndarray
    origin: np.ndarray
    basis: np.ndarray
    cell: float

    def covers(self, pts_world: np.ndarray) -> np.ndarray:
        """[N x 3] world points -> [N] bool: over the region (along the plane's normal)."""
        ij = np.floor((np.asarray(pts_world, dtype=np.float64) @ self.basis.T - self.origin) / self.cell).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < self.grid.shape[1]) & (ij[:, 1] < self.grid.shape[0])
        out = np.zeros(len(ij), dtype=bool)
        out[ok] = self.grid[ij[ok, 1], ij[ok, 0]]
        return out


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


def _fixation_point(T_world_cam: Sequence[np.ndarray], centre: np.ndarray | None) -> np.ndarray | None:
    """[3] world point the optical axes pass closest to (least squares over the views' axes).

    Along a direction in which the axes hardly turn (a sweep: nearly parallel axes) they do not fix the point;
    there `FIXATION_SPREAD` pulls it to `centre` (the views' centre point, `_centre_point`): views that converge
    (circling an object) set it by their axes, a sweep by its centre depth. None without views, or without a
    centre when the axes do not spread."""
    if not len(T_world_cam):
        return None
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for T in T_world_cam:
        z, c = T[:3, 2], T[:3, 3]
        P = np.eye(3) - np.outer(z, z)
        A += P
        b += P @ c
    w = FIXATION_SPREAD * len(T_world_cam)
    if centre is None:
        return np.linalg.solve(A, b) if np.linalg.eigvalsh(A)[0] > w else None
    return np.linalg.solve(A + w * np.eye(3), b + w * np.asarray(centre, dtype=np.float64))


def _centre_point(frames: list[RGBDFrame], T_world_cam: list[np.ndarray], depths: list[float | None]
                  ) -> np.ndarray | None:
    """[3] world point the frames keep in the middle of the image: per frame the point on the optical axis at
    its `centre_depth` (`depths`, one per frame), then the coordinate-wise median over the frames (robust to a
    few frames that look elsewhere). None when no frame has centre depth."""
    pts = []
    for f, T, z in zip(frames, T_world_cam, depths, strict=True):
        if z is not None:
            K = f.intrinsics
            H, W = f.depth.shape
            ray = np.array([((W - 1) / 2 - K.cx) / K.fx, ((H - 1) / 2 - K.cy) / K.fy, 1.0])
            pts.append(T[:3, :3] @ (z * ray) + T[:3, 3])
    return np.median(np.asarray(pts), axis=0) if pts else None


def _centre_share(point_world: np.ndarray, T_world_cam: Sequence[np.ndarray], K: Intrinsics) -> float:
    """Share of the views (cameras T_world_cam, intrinsics K) that hold the world point [3] in front of them
    and in the central `CENTRE_REGION` of their image: how much the capture is about what is there."""
    if not len(T_world_cam):
        return 0.0
    Ts = np.asarray(T_world_cam, dtype=np.float64)
    d = np.asarray(point_world, dtype=np.float64) - Ts[:, :3, 3]
    p = np.einsum("nji,nj->ni", Ts[:, :3, :3], d)  # R^T (x - t): camera-frame points [N x 3]
    z = np.where(p[:, 2] > 1e-6, p[:, 2], np.nan)
    u, v = K.fx * p[:, 0] / z + K.cx, K.fy * p[:, 1] / z + K.cy
    inside = (np.abs(u - (K.width - 1) / 2) <= CENTRE_REGION * K.width / 2) & (
        np.abs(v - (K.height - 1) / 2) <= CENTRE_REGION * K.height / 2)
    return float(inside.mean())


def _plane_basis(plane: Plane) -> np.ndarray:
    """[2 x 3] orthonormal directions spanning the plane."""
    n = plane.normal
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


def _support_region(inliers_2d: np.ndarray, cell: float, at: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The support surface under the point `at` [2] (plane coordinates; None: the largest surface), from the
    plane's inliers [N x 2]: an occupancy grid of `cell` m, closed over one cell (gaps between samples) and
    opened over one (a wall or cabinet front crossing the plane leaves a thin line of inliers, no surface); its
    connected part under `at` (else the nearest), with the holes it encloses filled (what stands on it hides
    the surface under it). Returns ([gH x gW] bool grid, [2] origin of cell (0, 0))."""
    lo = inliers_2d.min(0) - 2 * cell
    ij = np.floor((inliers_2d - lo) / cell).astype(int)
    shape = ij.max(0) + 3
    grid = np.zeros((int(shape[1]), int(shape[0])), dtype=np.uint8)
    grid[ij[:, 1], ij[:, 0]] = 1
    square = np.ones((3, 3), np.uint8)
    opened = cv2.morphologyEx(cv2.morphologyEx(grid, cv2.MORPH_CLOSE, square), cv2.MORPH_OPEN, square)
    n, labels = cv2.connectedComponents(opened, connectivity=8)
    if n <= 1:
        return opened.astype(bool), lo
    if at is None:
        keep = 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    else:
        c = (np.asarray(at) - lo) / cell
        yy, xx = np.nonzero(labels)
        keep = int(labels[yy, xx][np.argmin((xx + 0.5 - c[0]) ** 2 + (yy + 0.5 - c[1]) ** 2)])
    return _fill_holes(labels == keep, np.ones(grid.shape, dtype=bool)), lo


def _on_support(foot_2d: np.ndarray, region: np.ndarray, origin: np.ndarray, cell: float) -> tuple[float, float]:
    """How the footprint points [N x 2] (plane coordinates) lie on the support region (`_support_region`): the
    share of their cells over it, and the share of the cells around them (two cells wide) over it (what stands
    on a surface has the surface all round; what stands beside its edge or overhangs it does not)."""
    ij = np.floor((foot_2d - origin) / cell).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < region.shape[1]) & (ij[:, 1] < region.shape[0])
    if not ok.any():
        return 0.0, 0.0
    foot = np.zeros(region.shape, dtype=np.uint8)
    foot[ij[ok, 1], ij[ok, 0]] = 1
    ring = cv2.dilate(foot, np.ones((5, 5), np.uint8)).astype(bool) & ~foot.astype(bool)
    over = float(region[ij[ok, 1], ij[ok, 0]].sum()) / len(foot_2d)
    return over, float(region[ring].mean()) if ring.any() else 0.0


@dataclass(frozen=True)
class ObjectHint:
    """The user's choice of the object: a mask [H x W] bool of the frame `frame` (an index into the frames
    segmentation gets), from a box (`by` "roi") or a mask image (`by` "mask")."""

    frame: int
    mask: np.ndarray
    by: str


@dataclass(frozen=True)
class ChosenObject:
    """Which object segmentation chose, and why (the template's "object" meta, `scan --json`, `info --json`).

    by: "fixation" (where the views look), "roi" or "mask" (the user's choice in the first frame);
    size_m: its footprint's length and width on the support plane and its height above it (m);
    centre_share: share of the registered views holding its centre in the central `CENTRE_REGION` of the image;
    fixation_m: its centre's distance to the fixation point (m; None without one);
    on_support: it stands on the support surface under the fixation point (not beside it);
    candidates: the clusters above the support plane it was chosen from; reason: one line.
    """

    by: str
    size_m: tuple[float, float, float]
    centre_share: float
    fixation_m: float | None
    on_support: bool
    candidates: int
    reason: str

    def to_json(self) -> dict[str, Any]:
        return {"by": self.by, "size_m": [round(float(x), 3) for x in self.size_m],
                "centre_share": round(self.centre_share, 3),
                "fixation_m": None if self.fixation_m is None else round(self.fixation_m, 3),
                "on_support": self.on_support, "candidates": self.candidates, "reason": self.reason}


def _footprint_size(C: np.ndarray, plane: Plane) -> tuple[float, float, float]:
    """Length and width of the points' [N x 3] footprint on the plane (along its principal directions) and their
    height above it (m)."""
    f = C @ _plane_basis(plane).T
    f = f - f.mean(0)
    _, _, Vt = np.linalg.svd(f, full_matrices=False)
    r = f @ Vt.T
    ext = np.sort(r.max(0) - r.min(0))[::-1]
    return float(ext[0]), float(ext[1]), float(plane.height(C).max())


def estimate_working_volume(frames: Sequence[RGBDFrame], T_world_cam: list[np.ndarray],
                            params: SegmentParams = SegmentParams(), hint: ObjectHint | None = None
                            ) -> WorkingVolume | None:
    """Support plane (world frame) and a cylinder around the object on it (`frames`: any sequence, only the
    frames used are read), the object chosen from where the views look, or from the user's `hint`.

    The fixation point (`_fixation_point`, over every view's axis) is where the capture looks. The plane is
    fitted on stride-4 points of `volume_frames` frames evenly spaced over the sequence (each in its
    `depth_range`) within `SUPPORT_RADII` image half-widths of it; its inliers, closed over their holes, are the
    support surface. The points above the plane are clustered (DBSCAN); a cluster stands on the surface when
    most of its footprint lies over it and it reaches down to it. The object is the standing cluster held in the
    centre of the most views (`_centre_share`; nearer the fixation point on a tie): a structure at the edge of
    the views, or beside the surface the views look at, is never chosen over it. With a `hint`, the plane is
    fitted around the hint's points and the object is the clusters mostly inside the hint in its frame. The bands
    follow the noise at the median centre depth (`at_depth`). Returns None when no plane or no cluster is found.
    """
    import open3d as o3d

    if not frames:
        return None
    idx = spread_indices(len(frames), params.volume_frames, nearest=True)
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
    fixation = _fixation_point(T_world_cam, _centre_point(used, cams, depths))
    target = fixation
    hint_pts = None
    if hint is not None:
        hf = frames[hint.frame]
        sel = hint.mask & (hf.depth > 0)
        if sel.any():
            hint_pts = transform_points(T_world_cam[hint.frame], backproject(hf.depth, hf.intrinsics)[sel])
            target = np.median(hint_pts, axis=0)
    reach = np.inf
    if target is not None and z_c is not None:
        reach = SUPPORT_RADII * z_c * min(K.width / K.fx, K.height / K.fy) / 2
        P = P[np.linalg.norm(P - target, axis=1) <= reach]
    if hint_pts is not None:
        P = np.concatenate([P, hint_pts[:: max(1, len(hint_pts) // 5000)]])
    plane = fit_support_plane(P, np.mean([T[:3, 3] for T in cams], axis=0), par)
    if plane is None:
        return None
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P)).voxel_down_sample(par.plane_voxel)
    Q = np.asarray(pc.points)
    Q = Q[np.lexsort((Q[:, 2], Q[:, 1], Q[:, 0]))]  # order-independent clustering input
    h = plane.height(Q)
    basis = _plane_basis(plane)
    cell = 2 * par.cluster_eps
    region, origin = _support_region(Q[np.abs(h) < par.plane_distance] @ basis.T, cell,
                                     None if target is None else target @ basis.T)
    Q = Q[(h > par.height_min) & (h < par.height_max)]
    if len(Q) < 20:
        return None
    labels = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(Q)).cluster_dbscan(
        par.cluster_eps, min_points=8))
    clusters = [Q[labels == lab] for lab in range(labels.max() + 1) if (labels == lab).sum() >= 20]
    if not clusters:
        return None
    support = [_on_support(C @ basis.T, region, origin, cell) for C in clusters]
    stands = [over >= 0.5 and around >= 0.75 and plane.height(C).min() <= par.height_min + cell
              for C, (over, around) in zip(clusters, support, strict=True)]
    shares = [_centre_share(C.mean(0), T_world_cam, K) for C in clusters]
    near = [np.inf if fixation is None else float(np.linalg.norm(C.mean(0) - fixation)) for C in clusters]
    if hint is not None:
        hT = np.linalg.inv(np.asarray(T_world_cam[hint.frame], dtype=np.float64))
        inside = []
        for C in clusters:
            p = transform_points(hT, C)
            zc = np.where(p[:, 2] > 1e-6, p[:, 2], np.nan)
            u, v = K.fx * p[:, 0] / zc + K.cx, K.fy * p[:, 1] / zc + K.cy
            ok = np.isfinite(u) & np.isfinite(v)
            ui, vi = np.round(u[ok]).astype(int), np.round(v[ok]).astype(int)
            on = (ui >= 0) & (vi >= 0) & (ui < hint.mask.shape[1]) & (vi < hint.mask.shape[0])
            inside.append(float(hint.mask[vi[on], ui[on]].sum()) / len(C))
        chosen = [k for k, s in enumerate(inside) if s >= 0.5]
        if not chosen:
            return None
        why = (f"the {len(chosen)} cluster(s) above the support plane mostly inside the {hint.by} of the first "
               "frame")
    else:
        order = sorted(range(len(clusters)), key=lambda k: (not stands[k], -shares[k], near[k]))
        if not stands[order[0]] or shares[order[0]] < CENTRED:
            foot = Footprint(region, origin, basis, cell)
            return _surface_volume(plane, foot, [C for C, st in zip(clusters, stands, strict=True) if st],
                                   shares[order[0]] if stands[order[0]] else 0.0, fixation, T_world_cam, par, params,
                                   len(clusters))
        chosen = [order[0]]
        why = ("standing on the support surface under the fixation point" if stands[order[0]] else
               "no cluster stands on the support surface under the fixation point: the one") + (
            f", at the centre of {shares[order[0]]:.0%} of the views (the most)")
    C = np.concatenate([clusters[k] for k in chosen])
    hc = plane.height(C)
    foot = C - hc[:, None] * plane.normal
    centre = foot.mean(0)
    radius = float(np.linalg.norm(foot - centre, axis=1).max()) + params.volume_margin
    cm = C.mean(0)
    obj = ChosenObject("fixation" if hint is None else hint.by, _footprint_size(C, plane),
                       _centre_share(cm, T_world_cam, K),
                       None if fixation is None else float(np.linalg.norm(cm - fixation)),
                       bool(all(stands[k] for k in chosen)), len(clusters), why)
    vol = WorkingVolume(plane, centre, radius, float(hc.max()) + params.volume_margin, par.height_min, obj)
    log.info("working volume: radius %.3f m, height %.3f m, %d cluster points (centre depth %s m); object %s",
             vol.radius, vol.height, len(C), "?" if z_c is None else f"{z_c:.2f}", obj.to_json())
    return vol


def _surface_volume(plane: Plane, foot: Footprint, standing: list[np.ndarray], best_share: float,
                    fixation: np.ndarray | None, T_world_cam: Sequence[np.ndarray], par: SegmentParams,
                    params: SegmentParams, candidates: int) -> WorkingVolume:
    """The volume over the whole support surface `foot` (the plane's region under the fixation point) from just
    below the plane (its depth noise, `par.plane_distance`) to above what stands on it (`standing`: clusters
    [N x 3]): the object of a capture whose views centre on no one thing standing on the surface (the best of
    them at the centre of `best_share` of the views), a table and what is on it."""
    cells = np.argwhere(foot.grid)
    xy = foot.origin + (cells[:, ::-1] + 0.5) * foot.cell
    P0 = xy @ foot.basis - plane.offset * plane.normal  # the cells' centres on the plane [M x 3]
    centre = P0.mean(0)
    radius = float(np.linalg.norm(P0 - centre, axis=1).max()) + foot.cell
    top = max((float(plane.height(C).max()) for C in standing), default=0.0)
    length, width, _ = _footprint_size(P0, plane)
    hit = 0
    for T in T_world_cam:  # views whose optical axis meets the plane over the surface
        c, z = T[:3, 3], T[:3, 2]
        along = float(plane.normal @ z)
        if along < -1e-6:
            hit += bool(foot.covers((c - float(plane.height(c[None])[0]) / along * z)[None])[0])
    share = hit / max(1, len(T_world_cam))
    obj = ChosenObject("fixation", (length, width, top), share,
                       None if fixation is None else float(np.linalg.norm(centre - fixation)), True, candidates,
                       f"no one thing standing on the support surface under the fixation point is at the centre of "
                       f"{CENTRED:.0%} of the views (the most: {best_share:.0%}): the surface and the "
                       f"{len(standing)} things on it")
    vol = WorkingVolume(plane, centre, radius, top + params.volume_margin, -par.plane_distance, obj, foot)
    log.info("working volume: the support surface, %.2f x %.2f m, %.3f m high; object %s", length, width,
             vol.height, obj.to_json())
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


def object_hint(roi: tuple[int, int, int, int] | None, mask: Path | None, first: RGBDFrame, source: Path
                ) -> ObjectHint | None:
    """The user's choice of the object in the first frame `first` (of the capture at `source`), checked: a box
    (x, y, width, height in pixels, inside the image) or a mask image of the frame's size, non-zero on the object
    (any channel). None when neither is given. Raises InputError (fix "roi" / "mask") naming what is wrong."""
    H, W = first.depth.shape
    if roi is not None:
        x, y, w, h = (int(v) for v in roi)
        if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > W or y + h > H:
            raise InputError(source, f"the box x={x}, y={y}, width={w}, height={h} is not inside the first frame "
                             f"{first.name} ({W} x {H} px)", fix="roi")
        m = np.zeros((H, W), dtype=bool)
        m[y:y + h, x:x + w] = True
        return ObjectHint(0, m, "roi")
    if mask is None:
        return None
    if not Path(mask).is_file():
        raise InputError(mask, "is not a file; expected a mask image of the first frame", fix="mask")
    img = cv2.imread(str(mask), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(mask, "cannot be read as an image", fix="mask")
    if img.shape[:2] != (H, W):
        raise InputError(mask, f"is {img.shape[1]} x {img.shape[0]} px; the first frame {first.name} is {W} x {H} px",
                         fix="mask")
    m = np.asarray(img.any(axis=2) if img.ndim == 3 else img > 0, dtype=bool)
    if not m.any():
        raise InputError(mask, "is empty: no pixel marks the object", fix="mask")
    if not (m & (first.depth > 0)).any():
        raise InputError(mask, f"marks no pixel with depth in the first frame {first.name}", fix="mask")
    return ObjectHint(0, m, "mask")
