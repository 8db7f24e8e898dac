"""The full-frame work of one query frame, done once: back-projection, support plane, search region; and the
query's keypoints (stage 1).

Every later stage (features, ICP target, scores, the support-plane rule, tracking) reads these arrays
instead of back-projecting the depth again or fitting the plane again. Keypoints are detected on the bounding
boxes of the search region's blobs only (`region_boxes`): SIFT's cost follows the area it scans.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit

from gscan.errors import InputError
from gscan.estimate.params import QueryParams
from gscan.features import FeatureParams, Features, empty_features, extract_features, extract_features_in_mask
from gscan.features.depth import depth_keypoints, joint_features
from gscan.geometry.plane import Plane, dominant_plane
from gscan.io.camera import RGBDFrame, pixel_rays
from gscan.registration.colour import chromaticity
from gscan.registration.dense import DenseGeometry, interior
from gscan.registration.noise import DepthNoise


@dataclass
class QueryFrame:
    """One query frame with its per-frame geometry (see `prepare_query`).

    frame: the RGB-D frame; mask: the caller's search mask [H x W] bool or None; depth_frac: valid-depth
    fraction of the search region; plane: the dominant plane in the camera frame (None without one, with a
    mask, or without usable depth); off_plane: [H x W] bool pixels standing off that plane, or None;
    search: the region keypoints are detected in (mask, else off_plane, else None = whole frame).
    """

    frame: RGBDFrame
    mask: np.ndarray | None
    depth_frac: float
    plane: Plane | None = None
    off_plane: np.ndarray | None = None
    _cloud: np.ndarray | None = field(default=None, repr=False)
    _heights: np.ndarray | None = field(default=None, repr=False)
    _textured: DenseGeometry | None = field(default=None, repr=False)
    _chroma: dict[float, np.ndarray | None] = field(default_factory=dict, repr=False)
    _interior: dict[tuple[DepthNoise, float], DenseGeometry] = field(default_factory=dict, repr=False)

    @property
    def heights(self) -> np.ndarray | None:
        """[H x W] float32 every pixel's height above the plane (None without a plane), computed once."""
        if self.plane is not None and self._heights is None:
            self._heights = plane_heights(self, self.plane)
        return self._heights

    @property
    def search(self) -> np.ndarray | None:
        return self.mask if self.mask is not None else self.off_plane

    @property
    def region(self) -> np.ndarray:
        """[H x W] bool: the caller's mask, or every pixel."""
        return self.mask if self.mask is not None else np.ones(self.frame.depth.shape, bool)

    @property
    def textured(self) -> DenseGeometry:
        """The search region's depth samples with the frame's texture (`DenseGeometry`: what the texture and colour
        checks of a pose the depth alone decided compare), computed once."""
        if self._textured is None:
            self._textured = DenseGeometry.from_depth(self.frame.depth, self.frame.intrinsics, self.search,
                                                      image=self.frame.color)
        return self._textured

    def textured_interior(self, noise: DepthNoise, reach_px: float) -> DenseGeometry:
        """`textured`'s samples on a face's interior (`gscan.registration.dense.interior`), computed once per
        noise model and reach."""
        key = (noise, reach_px)
        if key not in self._interior:
            self._interior[key] = interior(self.textured, noise, reach_px)
        return self._interior[key]

    def chroma(self, max_sigma: float) -> np.ndarray | None:
        """The frame's chromaticity told within max_sigma (`gscan.registration.colour.chromaticity`), computed once
        per bound."""
        if max_sigma not in self._chroma:
            self._chroma[max_sigma] = chromaticity(self.frame.color, max_sigma)
        return self._chroma[max_sigma]

    @property
    def cloud(self) -> np.ndarray:
        """[H x W x 3] float32 camera-frame points of every pixel (zeros without depth), computed once."""
        if self._cloud is None:
            self._cloud = backproject32(self.frame)
        return self._cloud

    def points_near(self, center: np.ndarray, radius: float, region: np.ndarray | None = None,
                    stride: int = 2) -> np.ndarray:
        """[K x 3] float64 valid points of every `stride`-th pixel within `radius` of `center` [3] (camera frame),
        inside `region` ([H x W] bool) when given. Only the rows and columns the sphere's projection can reach
        are read."""
        intr = self.frame.intrinsics
        H, W = self.frame.depth.shape
        z = float(center[2])
        if z - radius <= 1e-3:  # the sphere reaches the camera: every pixel may hold a point
            box = (0, H, 0, W)
        else:
            r_px = radius / (z - radius)
            u0, v0 = center[0] / z * intr.fx + intr.cx, center[1] / z * intr.fy + intr.cy
            box = (int(max(0, np.floor(v0 - r_px * intr.fy))), int(min(H, np.ceil(v0 + r_px * intr.fy) + 1)),
                   int(max(0, np.floor(u0 - r_px * intr.fx))), int(min(W, np.ceil(u0 + r_px * intr.fx) + 1)))
        y0, y1, x0, x1 = box
        if y1 <= y0 or x1 <= x0:
            return np.zeros((0, 3))
        y0, x0 = y0 + (-y0) % stride, x0 + (-x0) % stride  # the same pixel grid whatever the box
        sl = (slice(y0, y1, stride), slice(x0, x1, stride))
        if self._cloud is not None:
            P = self._cloud[sl]
        else:  # only the box is back-projected (tracking never needs the whole frame)
            P = (pixel_rays(intr)[sl] * self.frame.depth[sl][..., None]).astype(np.float32)
        ok = self.frame.depth[sl] > 0
        if region is not None:
            ok &= region[sl]
        P = P[ok].astype(np.float64)
        return P[np.einsum("ij,ij->i", P - center, P - center) < radius * radius]


def backproject32(frame: RGBDFrame) -> np.ndarray:
    """[H x W x 3] float32 camera-frame points (zeros where the depth is 0): each pixel's ray (`pixel_rays`)
    times its depth in float64, rounded to float32 once (one pass, no float64 [H x W x 3] intermediate)."""
    rays = pixel_rays(frame.intrinsics)
    depth = np.ascontiguousarray(frame.depth)
    if depth.dtype not in (np.float32, np.float64) or rays.shape[:2] != depth.shape:
        out = np.empty(rays.shape, np.float32)
        np.multiply(rays, depth[..., None], out=out, casting="unsafe")
        return out
    out = np.empty(rays.shape, np.float32)
    _backproject(depth, np.ascontiguousarray(rays[0, :, 0]), np.ascontiguousarray(rays[:, 0, 1]), out)
    return out


@njit(cache=True, nogil=True)
def _backproject(depth, rx, ry, out):
    """out[v, u] = (rx[u] z, ry[v] z, z), z = depth[v, u], products in float64, stored as float32."""
    for v in range(depth.shape[0]):
        y = ry[v]
        for u in range(depth.shape[1]):
            z = np.float64(depth[v, u])
            out[v, u, 0] = rx[u] * z
            out[v, u, 1] = y * z
            out[v, u, 2] = z


def fit_plane(q: QueryFrame, min_frac: float, iterations: int, stride: int = 6) -> Plane | None:
    """`dominant_plane` of the query's cached cloud."""
    return dominant_plane(q.cloud, min_frac, iterations, stride)


def plane_heights(q: QueryFrame, plane: Plane) -> np.ndarray:
    """[H x W] float32 signed height of every pixel's point above `plane` (meaningless where depth is 0)."""
    n = plane.normal.astype(np.float32)
    return q.cloud @ n + np.float32(plane.offset)


def off_plane_margin(z: np.ndarray | float) -> np.ndarray | float:
    """m: how far in front of the support plane a point at depth z (m) stands to be off it (the search region):
    8 mm + 0.5 % of its depth."""
    return 0.008 + 0.005 * z


def prepare_query(frame: RGBDFrame, mask: np.ndarray | None, params: QueryParams) -> QueryFrame:
    """The frame's per-frame geometry: the valid-depth fraction of the search region and, without a mask (a
    given mask is the search region) and with usable depth, the dominant plane and the pixels in front of it
    by more than 8 mm + 0.5 % of their depth (None when they are fewer than 0.2 % of the frame)."""
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != frame.depth.shape:
            raise InputError(frame.source, f"mask is {mask.shape[1] if mask.ndim > 1 else '?'}x{mask.shape[0]} but "
                                           f"the frame is {frame.depth.shape[1]}x{frame.depth.shape[0]}")
    valid = frame.depth > 0
    n_region = valid.size if mask is None else int(mask.sum())
    n_valid = int(valid.sum()) if mask is None else int((valid & mask).sum())
    q = QueryFrame(frame, mask, n_valid / max(1, n_region))
    if mask is None and params.remove_plane and q.depth_frac >= params.min_depth_frac:
        q.plane = fit_plane(q, params.plane_min_frac, params.plane_iterations)
        heights = q.heights
        if heights is not None:
            region = valid & (heights > off_plane_margin(frame.depth))
            q.off_plane = region if region.mean() >= 0.002 else None
    return q


@dataclass(frozen=True)
class QueryDepth:
    """A query's depth keypoints for a template whose keyframes hold joint keypoints (rootsift+fpfh: the image's
    and the depth's, `gscan.features.depth`): found on the search region's points at the template's object size
    `size` (m; None: no depth keypoints, the image's alone in the joint set) and its capture's depth noise `noise`,
    with the depth_* settings of the estimator's `features`, at most its max_keypoints (the image keypoints'
    count: the region holds the clutter too, whose salient points compete with the object's)."""

    size: float | None
    noise: DepthNoise


def join_depth(frame: RGBDFrame, region: np.ndarray | None, image: Features, features: FeatureParams,
               depth: QueryDepth | None, lift: bool = True) -> Features:
    """`image` (the region's image keypoints) as the template reads them: unchanged without `depth`; else joined
    with the depth keypoints of `region` ([H x W] bool; None: the whole frame) into one rootsift+fpfh set (none
    without `lift`: a frame without usable depth)."""
    if depth is None:
        return image
    dk = None
    if lift and depth.size is not None and (region is None or region.any()):
        dk = depth_keypoints(frame, depth.noise.sigma, features, region, size=depth.size,
                             max_keypoints=features.max_keypoints)
    return joint_features(image, dk)


def query_features(frame: RGBDFrame, mask: np.ndarray | None, features: FeatureParams, params: QueryParams,
                   lift: bool = True, depth: QueryDepth | None = None) -> Features:
    """The query keypoints (stage 1) inside `mask` ([H x W] bool; None: the whole frame), detected on the
    mask's blobs' boxes (`region_boxes`), joined with the mask's depth keypoints for a template that holds them
    (`depth`, `join_depth`). Without `lift` (PnP) every keypoint is kept: a unit placeholder depth is lifted, so
    only pixels and descriptors are meaningful."""
    image = _image_features(frame, mask, features, params, lift)
    return join_depth(frame, mask, image, features, depth, lift)


def _image_features(frame: RGBDFrame, mask: np.ndarray | None, features: FeatureParams, params: QueryParams,
                    lift: bool) -> Features:
    fparams = features if lift else replace(features, lift_window=0)
    if not lift:
        frame = RGBDFrame(frame.name, frame.color, np.ones_like(frame.depth), frame.intrinsics)
    if mask is None:
        return extract_features(frame, fparams)
    if not mask.any():
        return empty_features(fparams.kind)
    boxes = region_boxes(mask, params.crop_margin, params.min_region_px)
    if len(boxes) <= 1:
        return extract_features_in_mask(frame, mask, fparams, params.crop_margin)
    parts = [extract_features_in_mask(frame, mask, fparams, params.crop_margin, within=box) for box in boxes]
    return Features(np.concatenate([f.pixels for f in parts]), np.concatenate([f.points for f in parts]),
                    np.concatenate([f.descriptors for f in parts]), fparams.kind,
                    np.concatenate([f.scales for f in parts]))


def region_boxes(mask: np.ndarray, margin: int, min_px: int, max_fill: float = 0.7) -> list[tuple[int, int, int, int]]:
    """Detection boxes (x0, y0, x1, y1) of a search region [H x W] bool: the bounding boxes of its connected
    blobs of at least min_px pixels, grown by `margin` and merged while they overlap. One box (the region's
    bounding box) when the blobs' boxes cover more than `max_fill` of it, or none of them is large enough."""
    import cv2

    H, W = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return []
    # the blobs of the region's bounding box (a crop: the labelling's cost follows the pixels it scans)
    crop = mask[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1].astype(np.uint8)
    _, _, stats, _ = cv2.connectedComponentsWithStats(crop, connectivity=8)
    stats[:, 0] += cols[0]
    stats[:, 1] += rows[0]
    boxes = [[max(0, x - margin), max(0, y - margin), min(W, x + w + margin), min(H, y + h + margin)]
             for x, y, w, h, a in stats[1:] if a >= min_px]
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    if len(boxes) <= 1:
        return [tuple(b) for b in boxes]
    union = (cols[-1] - cols[0] + 1 + 2 * margin) * (rows[-1] - rows[0] + 1 + 2 * margin)
    if sum((b[2] - b[0]) * (b[3] - b[1]) for b in boxes) > max_fill * union:
        return []
    return sorted((int(b[0]), int(b[1]), int(b[2]), int(b[3])) for b in boxes)

