"""Dense evidence for an edge: do the two frames' depth images agree under its pose?

Keypoints say which pixels match; the depth says where the surfaces are. Under a right pose every
surface point of one frame that lands in the other frame's view is either seen there at the same depth
(consistent) or hidden behind a nearer surface (occluded). A point that lands in front of the surface
the other frame measured means that frame looked straight through the place where the first frame saw
a surface (see-through): the pose is wrong, or the scene changed. A list of keypoints can be consistent
and wrong (a repeated print, two identical objects, a mirror-symmetric layout); the depth of the whole
overlap rarely is.

`DenseGeometry` samples a frame's depth on a regular grid (about `samples` points, pixels next to depth
discontinuities left out: a small pose error moves them across the edge) with the surface normal at each
sample (from its neighbouring samples, or from nearer pixels where a neighbouring sample lies across a
discontinuity); `depth_agreement` projects the samples of one frame into the other with the edge's pose and
measures each against the surface found there along its normal (on a slanted table a pixel's shift
changes the depth a lot and the distance to the surface little), with the tolerance of the noise model
(`gscan.registration.noise`): |n . (q - p)| <= k * s(z_q, z_p).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np

from gscan.geometry.transforms import inv_T, transform_points
from gscan.io.camera import Intrinsics
from gscan.registration.colour import (
    ColourAgreement,
    PrintAgreement,
    grey_image,
    image_noise,
    min_texture_std,
    print_tiles,
    texture_image,
    tile_ids,
    tile_scores,
)
from gscan.registration.noise import DepthNoise

EDGE_REL = 0.03  # a neighbour whose depth differs by more than this fraction marks a discontinuity
FINE_STRIDE = 2  # px: the stride of `DenseGeometry.fine` (tiles of 48 px hold 24 x 24 samples)


def image_texture(image: np.ndarray) -> tuple[np.ndarray, float]:
    """An image's ([H x W x 3] RGB or [H x W] grey) texture for the colour check: (band-passed grey levels
    [H x W], the image's noise)."""
    grey = grey_image(image)
    return texture_image(grey), image_noise(grey)


@dataclass(frozen=True)
class DenseGeometry:
    """A frame's depth sampled every `stride` pixels (camera frame, metres).

    depth [h x w] (0 = invalid or left out), grid [h x w x 3] the sampled points, normals [h x w x 3]
    (unit, towards the camera), points [P x 3] of the kept samples; fx, fy, cx, cy the intrinsics of the
    sampled grid. With the frame's grey image: pixels [P x 2] (u, v) of the kept samples in the image,
    full_intrinsics (fx, fy, cx, cy) of the image, texture [H x W] its band-passed grey levels and
    texture_noise the image's noise (`gscan.registration.colour`). mask [H x W] bool: the object's silhouette
    at the image's full resolution, when one was given (`outline`), and rim [R x 3] points on its rim
    (`rim_points`). image_depth [H x W]: the frame's depth at full resolution (the array given, not a copy), for
    `gscan.registration.photometric`.
    """

    depth: np.ndarray
    grid: np.ndarray
    normals: np.ndarray
    points: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    pixels: np.ndarray | None = None
    full_intrinsics: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    texture: np.ndarray | None = None
    texture_noise: float = 0.0
    mask: np.ndarray | None = None
    rim: np.ndarray | None = None
    image_depth: np.ndarray | None = None

    @classmethod
    def from_depth(cls, depth: np.ndarray, intr: Intrinsics, mask: np.ndarray | None = None,
                   samples: int = 5000, image: np.ndarray | None = None,
                   texture: tuple[np.ndarray, float] | None = None) -> DenseGeometry:
        """Samples of depth [H x W] (m) inside mask ([H x W] bool, optional), about `samples` of them; with the
        frame's image ([H x W x 3] RGB or [H x W] grey, registered to the depth), its texture for
        `gscan.registration.colour`: `image_texture(image)`, or `texture` when that was computed already (one
        image read with several depth images)."""
        H, W = depth.shape
        stride = max(1, int(np.sqrt(H * W / samples)))
        off = stride // 2
        h = max(1, stride // 2)  # neighbours at half the stride decide discontinuities
        v = np.arange(off, H, stride)
        u = np.arange(off, W, stride)
        d = depth[np.ix_(v, u)].astype(np.float64)
        good = d > 0
        for sv, su in ((-h, 0), (h, 0), (0, -h), (0, h)):
            n = depth[np.ix_(np.clip(v + sv, 0, H - 1), np.clip(u + su, 0, W - 1))].astype(np.float64)
            good &= (n > 0) & (np.abs(n - d) <= EDGE_REL * np.maximum(n, d))
        if mask is not None:
            good &= mask[np.ix_(v, u)]
        fx, fy = intr.fx / stride, intr.fy / stride
        cx, cy = (intr.cx - off) / stride, (intr.cy - off) / stride
        gu, gv = np.meshgrid(np.arange(len(u)), np.arange(len(v)))
        grid = np.stack([(gu - cx) / fx * d, (gv - cy) / fy * d, d], axis=-1)
        # normals from the neighbouring samples (central differences; one-sided at the border); where a
        # neighbouring sample lies across a discontinuity (a face a few samples wide: a box seen edge on), from
        # the pixels at half the stride instead, which the test above found on the sample's surface
        du = _across(grid, d, 1, _half_step(depth, intr, v, u, 0, h))
        dv = _across(grid, d, 0, _half_step(depth, intr, v, u, h, 0))
        n = np.cross(du, dv)
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.where(norm > 0, n / np.maximum(norm, 1e-12), 0.0)
        n *= np.where(np.sum(n * grid, axis=-1, keepdims=True) > 0, -1.0, 1.0)
        good &= norm[..., 0] > 0
        d = np.where(good, d, 0.0)
        tex = pixels = None
        noise = 0.0
        if texture is not None and texture[0].shape[:2] == depth.shape:
            tex, noise = texture
        elif image is not None and image.shape[:2] == depth.shape:
            tex, noise = image_texture(image)
        if tex is not None:
            pixels = np.stack([u[gu[good]], v[gv[good]]], axis=1)
        mask = mask if mask is not None and mask.shape == depth.shape else None
        return cls(d, grid, n, grid[good], fx, fy, cx, cy, pixels, (intr.fx, intr.fy, intr.cx, intr.cy), tex, noise,
                   mask, None if mask is None else rim_points(depth, intr, mask), depth)

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, keep: np.ndarray) -> DenseGeometry:
        """The samples where keep [h x w] bool holds (of the valid ones), with the frame's texture; no mask or rim."""
        good = self.depth > 0
        keep = keep & good
        index = np.full(self.depth.shape, -1, np.int64)
        index[good] = np.arange(int(good.sum()))  # points and pixels list the valid samples row by row
        kept = index[keep]
        return DenseGeometry(np.where(keep, self.depth, 0.0), self.grid, self.normals, self.points[kept], self.fx,
                             self.fy, self.cx, self.cy, None if self.pixels is None else self.pixels[kept],
                             self.full_intrinsics, self.texture, self.texture_noise)

    @cached_property
    def fine(self) -> DenseGeometry:
        """The frame sampled every `FINE_STRIDE` pixels, with its texture and mask: texture verdicts near the
        image's own resolution. At the default sampling (a stride of 7 px) a tile along an outline or a small
        object's face holds too few samples to be judged (a 41 px wide bottle: 4 tiles; every pixel: 13)."""
        if self.image_depth is None or self.fx >= self.full_intrinsics[0] / FINE_STRIDE:
            return self
        H, W = self.image_depth.shape
        fx, fy, cx, cy = self.full_intrinsics
        texture = None if self.texture is None else (self.texture, self.texture_noise)
        return DenseGeometry.from_depth(self.image_depth, Intrinsics(fx, fy, cx, cy, W, H), self.mask,
                                        H * W // FINE_STRIDE ** 2, texture=texture)

    @cached_property
    def point_normals(self) -> np.ndarray:
        """[P x 3] the normals of `points` (the kept samples), gathered once."""
        return self.normals[self.depth > 0]

    @cached_property
    def outline(self) -> np.ndarray | None:
        """[H x W] float32: each pixel's distance (px) to the mask, 0 inside it (`outside_outline`,
        `_rim_equations`), computed once when asked for; None without a mask."""
        if self.mask is None:
            return None
        import cv2

        return cv2.distanceTransform((~self.mask).astype(np.uint8), cv2.DIST_L2, 3)


def rim_points(depth: np.ndarray, intr: Intrinsics, mask: np.ndarray, window: int = 1, step: int = 2
               ) -> np.ndarray:
    """[R x 3] camera-frame points on the rim of `mask` ([H x W] bool; depth [H x W] m): every `step`-th pixel of
    the mask's one-pixel rim, at the nearest depth inside the mask within `window` px of it (the object's surface
    there: a rim pixel's own depth may mix the object with what lies behind it, and sensors lose depth along
    outlines); rim pixels without depth that near are left out. A depth from farther in is not the rim's: a face
    seen at a grazing angle recedes by up to a centimetre a pixel, and rim points lifted 2 px in landed 3 px off
    the other view's mask at the true pose (a plain box turning 10 deg a frame: 12 of 35 frame pairs over the
    outline check's 1 %; 1 px in: none). Every point of the object projects inside its silhouette in any view, and
    the rim's points are the ones a pose slid along a plain face moves out of it first (the sampled points stay a
    sample's stride inside)."""
    import cv2

    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    v, u = np.nonzero(mask & ~inner)
    v, u = v[::step], u[::step]
    inside = np.where(mask & (depth > 0), depth, np.inf).astype(np.float32)
    near = cv2.erode(inside, np.ones((2 * window + 1, 2 * window + 1), np.uint8))[v, u].astype(np.float64)
    ok = np.isfinite(near)
    v, u, z = v[ok], u[ok], near[ok]
    return np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=1)


def _half_step(depth: np.ndarray, intr: Intrinsics, v: np.ndarray, u: np.ndarray, dv: int, du: int) -> np.ndarray:
    """[len(v) x len(u) x 3]: the point at pixel (v + dv, u + du) minus that at (v - dv, u - du), for the grid of
    pixel rows v and columns u of depth [H x W] (clipped to the image)."""
    H, W = depth.shape
    out = []
    for s in (1, -1):
        vv, uu = np.clip(v + s * dv, 0, H - 1), np.clip(u + s * du, 0, W - 1)
        z = depth[np.ix_(vv, uu)].astype(np.float64)
        out.append(np.stack([(uu[None, :] - intr.cx) / intr.fx * z, (vv[:, None] - intr.cy) / intr.fy * z, z], -1))
    return out[0] - out[1]


def _across(grid: np.ndarray, d: np.ndarray, axis: int, near: np.ndarray) -> np.ndarray:
    """The derivative of grid [h x w x 3] along axis by central differences over its neighbouring samples,
    `near` [h x w x 3] where one of them is invalid or more than EDGE_REL away in depth (d [h x w])."""
    if grid.shape[axis] < 2:
        return np.zeros_like(grid)
    out = np.gradient(grid, axis=axis)
    pad = np.pad(d, [(1, 1) if a == axis else (0, 0) for a in range(2)], mode="edge")
    lo, hi = (pad[:-2], pad[2:]) if axis == 0 else (pad[:, :-2], pad[:, 2:])
    apart = np.zeros(d.shape, bool)
    for nb in (lo, hi):
        apart |= (nb <= 0) | (np.abs(nb - d) > EDGE_REL * np.maximum(nb, d))
    return np.where(apart[..., None], near, out)


@dataclass(frozen=True)
class DepthAgreement:
    """Counts of one frame's depth samples projected into another frame (module docstring)."""

    consistent: int
    see_through: int
    occluded: int
    landed: int  # samples that landed on a sample of the other frame's depth
    total: int  # samples of the projected frame

    @property
    def see_through_fraction(self) -> float:
        """see-through / (consistent + see-through): how much of the visible overlap contradicts the pose."""
        return self.see_through / max(1, self.consistent + self.see_through)

    @property
    def overlap(self) -> float:
        """landed / total: the share of the frame seen by the other one."""
        return self.landed / max(1, self.total)

    def __add__(self, other: DepthAgreement) -> DepthAgreement:
        return DepthAgreement(self.consistent + other.consistent, self.see_through + other.see_through,
                              self.occluded + other.occluded, self.landed + other.landed, self.total + other.total)


def _project(q: np.ndarray, intrinsics: tuple[float, float, float, float], shape: tuple[int, ...]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points q [N x 3] (camera frame) in front of a camera with `intrinsics` (fx, fy, cx, cy) that land inside
    its image of `shape` (H, W): their columns [K] and rows [K] (nearest pixel), depths [K] and indices [K] in q."""
    fx, fy, cx, cy = intrinsics
    front = q[:, 2] > 1e-3
    z = np.where(front, q[:, 2], 1.0)
    u = np.rint(q[:, 0] / z * fx + cx).astype(np.int64)
    v = np.rint(q[:, 1] / z * fy + cy).astype(np.int64)
    idx = np.flatnonzero(front & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0]))
    return u[idx], v[idx], z[idx], idx


def _landing(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """src's samples that land on a valid sample of tgt under T_tgt_src: (their points in tgt's camera
    frame [K x 3], the rows [K] and columns [K] of tgt's samples they land on, their indices [K] in
    src.points)."""
    q = transform_points(T_tgt_src, src.points)
    ui, vi, _, idx = _project(q, (tgt.fx, tgt.fy, tgt.cx, tgt.cy), tgt.depth.shape)
    has = tgt.depth[vi, ui] > 0
    return q[idx[has]], vi[has], ui[has], idx[has]


def depth_agreement(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, noise: DepthNoise,
                    k: float = 3.0) -> DepthAgreement:
    """Agreement of src's depth with tgt's under T_tgt_src, in both directions (src into tgt, tgt into src);
    `noise` is that of a depth pixel."""
    out = DepthAgreement(0, 0, 0, 0, 0)
    for a, b, T in ((src, tgt, T_tgt_src), (tgt, src, inv_T(T_tgt_src))):
        p = plane_residuals(a, b, T)
        e, tol = p.e, k * p.sigma(noise)
        out = out + DepthAgreement(int((np.abs(e) <= tol).sum()), int((e > tol).sum()), int((e < -tol).sum()),
                                   len(e), len(a))
    return out


def colour_agreement(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, noise: DepthNoise,
                     k: float = 3.0) -> ColourAgreement:
    """Colour agreement of two frames' `DenseGeometry` (each with its texture) under T_tgt_src, in both
    directions, over the samples whose depth agrees within k sigmas of `noise` (`gscan.registration.colour`);
    nothing is informative when a frame has no texture."""
    t = colour_tiles(src, tgt, T_tgt_src, noise, k, centres=False)
    return ColourAgreement(len(t.agrees), int(t.agrees.sum()))


@dataclass(frozen=True)
class ColourTiles:
    """The informative tiles of `colour_agreement`, one by one: direction [T] (0: src's tiles landing on tgt, 1:
    tgt's on src), tile id [T] (`gscan.registration.colour.tile_ids` of its source image), agrees [T] bool, and
    centre [T x 3]: the mean of the tile's samples, in its source camera's frame (m; [0 x 3] when not asked for)."""

    direction: np.ndarray
    tile: np.ndarray
    agrees: np.ndarray
    centre: np.ndarray


def colour_tiles(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, noise: DepthNoise,
                 k: float = 3.0, centres: bool = True) -> ColourTiles:
    """The tiles `colour_agreement` counts (`ColourTiles`); none when a frame has no texture. centres: whether to
    locate each tile (its counts alone, on every edge's check, need not)."""
    parts: list[tuple[np.ndarray, ...]] = []
    for d, (a, b, T) in enumerate(((src, tgt, T_tgt_src), (tgt, src, inv_T(T_tgt_src)))):
        if a.texture is None or b.texture is None or a.pixels is None:
            parts = []
            break
        Ia, tiles, u, v, idx = _tile_samples(a, b, T, noise, k)
        ids, informative, agree = tile_scores(Ia, tiles, b.texture, u, v, min_texture_std(a.texture_noise))
        ids, agree = ids[informative], agree[informative]
        if not centres:
            parts.append((np.full(len(ids), d), ids, agree, np.zeros((0, 3))))
            continue
        # each informative tile's centre: the mean of its samples
        at = np.minimum(np.searchsorted(ids, tiles), max(len(ids) - 1, 0))
        mine = ids[at] == tiles if len(ids) else np.zeros(len(tiles), bool)
        n = np.bincount(at[mine], minlength=len(ids))
        pts = a.points[idx[mine]].astype(np.float64)
        centre = np.stack([np.bincount(at[mine], pts[:, j], len(ids)) for j in range(3)], 1) / np.maximum(n, 1)[:, None]
        parts.append((np.full(len(ids), d), ids, agree, centre))
    if not parts:
        return ColourTiles(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros((0, 3)))
    return ColourTiles(*(np.concatenate(x) for x in zip(*parts, strict=True)))


def _tile_samples(a: DenseGeometry, b: DenseGeometry, T_b_a: np.ndarray, noise: DepthNoise, k: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """a's samples (with texture and pixels) whose depth lands on b's within k sigmas of `noise` under T_b_a: (their
    texture in a [K], their tiles of a's image [K], where they land in b's image: u [K], v [K] pixels, their
    indices [K] into a.points)."""
    assert a.texture is not None and a.pixels is not None
    q, _, e, sd, idx = _plane_pairs(a, b, T_b_a, noise)
    ok = np.abs(e) <= k * sd
    q, idx = q[ok], idx[ok]
    fx, fy, cx, cy = b.full_intrinsics
    u = q[:, 0] / q[:, 2] * fx + cx
    v = q[:, 1] / q[:, 2] * fy + cy
    pu, pv = a.pixels[idx, 0], a.pixels[idx, 1]
    return a.texture[pv, pu].astype(np.float64), tile_ids(pu, pv, a.texture.shape[1]), u, v, idx


def chroma_pairs(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, noise: DepthNoise,
                 src_chroma: np.ndarray, tgt_chroma: np.ndarray, k: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """The chromaticities (`gscan.registration.colour.chromaticity`, [H x W x 2] of each frame's image) of src's
    samples (with pixels) whose depth lands on tgt's within k sigmas of `noise` under T_tgt_src, inside tgt's mask
    when it has one: (at the sample in src [K x 2], where it lands in tgt [K x 2], nearest pixel)."""
    assert src.pixels is not None
    q, _, e, sd, idx = _plane_pairs(src, tgt, T_tgt_src, noise)
    u, v, _, kept = _project(q, tgt.full_intrinsics, tgt_chroma.shape[:2])
    ok = np.abs(e[kept]) <= k * sd[kept]
    u, v, idx = u[ok], v[ok], idx[kept][ok]
    if tgt.mask is not None:
        inside = tgt.mask[v, u]
        u, v, idx = u[inside], v[inside], idx[inside]
    pu, pv = src.pixels[idx, 0], src.pixels[idx, 1]
    return src_chroma[pv, pu], tgt_chroma[v, u]


def interior(g: DenseGeometry, noise: DepthNoise, reach_px: float) -> DenseGeometry:
    """g with only the samples on a face's interior: every sample within reach_px pixels (a square of samples) is
    valid (no rim: g leaves out samples across a depth jump and outside its mask) and its normal lies within
    three sigmas of the normals' difference of this one's (no crease). A normal is a cross product of central
    differences over two sample spacings d = z / fx, so each axis' slope has sigma sqrt(2) sigma(z) / (2 d) and
    two normals differ by sqrt(2) times that: the bound is 3 sigma(z) / d radians (at most 90 deg). There the
    shading is smooth (one normal, no occlusion), so a band-passed texture within reach of the samples is the
    surface's own print, not shading."""
    R = int(np.ceil(reach_px * g.fx / g.full_intrinsics[0])) if g.full_intrinsics[0] > 0 else 0
    return g.subset(_smooth_around(g, noise, R))


def _smooth_around(g: DenseGeometry, noise: DepthNoise, R: int, rims: bool = True) -> np.ndarray:
    """[h x w] bool: g's samples whose neighbours within R samples (a square) are all valid (unless not `rims`:
    then the valid ones), with normals within `interior`'s bound of theirs."""
    d, good = g.depth, g.depth > 0
    h, w = d.shape
    spacing = np.where(good, d, 1.0) / g.fx
    cos_max = np.cos(np.minimum(3.0 * noise.sigma(np.where(good, d, 1.0).ravel()).reshape(d.shape) / spacing,
                                np.pi / 2))
    keep = good.copy()
    for dv in range(-R, R + 1):
        rows = np.clip(np.arange(h) + dv, 0, h - 1)
        for du in range(-R, R + 1):
            if dv == 0 and du == 0:
                continue
            cols = np.clip(np.arange(w) + du, 0, w - 1)
            alike = np.sum(g.normals[np.ix_(rows, cols)] * g.normals, axis=-1) >= cos_max
            there = good[np.ix_(rows, cols)]
            keep &= (there & alike) if rims else (~there | alike)
    return keep


def interior_pixels(g: DenseGeometry, noise: DepthNoise, reach_px: float) -> DenseGeometry:
    """g's frame sampled finely (`DenseGeometry.fine`) on a face's interior, located to the pixel: the samples
    at least reach_px from the frame's invalid depth or mask and from a crease, where a sample of g and a
    neighbour's normals differ beyond `interior`'s bound (the crease lies between the two, so within a stride s of
    either: at least reach_px - s from their pixels). Texture there is print, not shading. `interior` keeps g's
    samples whose whole square within reach is smooth: on a box's side seen nearly edge on, a few (Vans from 0
    deg: 5 of 149 samples; here 147 of 2135 fine samples)."""
    import cv2

    fine = g.fine
    if fine is g or g.image_depth is None:
        return interior(g, noise, reach_px)
    H, W = g.image_depth.shape
    s = max(1, int(round(g.full_intrinsics[0] / g.fx)))
    valid = g.image_depth > 0
    if g.mask is not None:
        valid &= g.mask
    # samples beside a crease (the rim `off_rim` measures to the pixel); each stands for the s x s pixels around it
    # (the grid starts s // 2 in)
    crease = np.repeat(np.repeat((g.depth > 0) & ~_smooth_around(g, noise, 1, rims=False), s, 0), s, 1)[:H, :W]
    block = np.zeros((H, W), bool)
    block[:crease.shape[0], :crease.shape[1]] = crease
    off_rim = cv2.distanceTransform(valid.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    off_crease = cv2.distanceTransform((~block).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    ok = (off_rim >= reach_px) & (off_crease >= reach_px - s)
    fs = max(1, int(round(g.full_intrinsics[0] / fine.fx)))
    rows = np.clip(fs // 2 + fs * np.arange(fine.depth.shape[0]), 0, H - 1)
    cols = np.clip(fs // 2 + fs * np.arange(fine.depth.shape[1]), 0, W - 1)
    return fine.subset(ok[np.ix_(rows, cols)])


def print_agreement(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, noise: DepthNoise,
                    k: float = 3.0) -> PrintAgreement:
    """`colour_agreement`'s tiles judged against their counterparts (`gscan.registration.colour.print_tiles`), in
    both directions, over the samples whose depth agrees within k sigmas of `noise`; give it `interior`
    geometries, where texture is print. Nothing is informative when a frame has no texture."""
    out = PrintAgreement(0, 0, 0)
    for a, b, T in ((src, tgt, T_tgt_src), (tgt, src, inv_T(T_tgt_src))):
        if a.texture is None or b.texture is None or a.pixels is None:
            return PrintAgreement(0, 0, 0)
        Ia, tiles, u, v, _ = _tile_samples(a, b, T, noise, k)
        out = out + print_tiles(Ia, tiles, b.texture, u, v, min_texture_std(a.texture_noise),
                                min_texture_std(b.texture_noise))
    return out


def refine_pose(src: DenseGeometry, tgt: DenseGeometry, kp_s: np.ndarray, kp_t: np.ndarray, T_tgt_src: np.ndarray,
                kp_noise: DepthNoise, depth_noise: DepthNoise, gates: tuple[float, ...] = (8.0, 5.0, 3.0, 3.0, 3.0),
                kp_loc: np.ndarray | None = None, rims: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The pose that best explains both the keypoint pairs and the depth: Gauss-Newton on the keypoint
    residuals T kp_s - kp_t ([M x 3] pairs, three axes each, sigma s of `kp_noise` with the pairs' location
    sigmas kp_loc [M], m, None: 0, `DepthNoise.pair_sigma`) and the point-to-plane
    distances of src's depth samples to tgt's surface (projective association, one per sample landing on
    tgt's depth, sigma s of `depth_noise` at their two depths), Huber-weighted beyond HUBER sigmas. Depth samples
    farther than the round's gate (sigmas) from the surface, or facing away from it (MIN_NORMAL_COS), are left
    out; the gate shrinks over the rounds (one GN step each), so a pose a few centimetres off is drawn in first.
    Depth pins what keypoints on a distant wall leave loose (the near table); keypoints pin what depth leaves
    loose (sliding along a plane). rims: each frame's rim points (`rim_points`) that land off the other's mask
    are drawn onto it too (`_rim_equations`): what pins a slide along a plain face where no keypoint does.

    Returns (T_tgt_src [4 x 4], information [6 x 6] of the final pose, rotation first: `pose_information`).
    """
    from gscan.geometry.transforms import make_T, rotvec_to_R

    T = np.asarray(T_tgt_src, dtype=np.float64).copy()
    for gate in gates:
        H, g = _normal_equations(src, tgt, kp_s, kp_t, T, kp_noise, depth_noise, gate, kp_loc, rims)
        try:
            dx = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = make_T(rotvec_to_R(dx[:3]), dx[3:]) @ T
    return T, pose_information(src, tgt, kp_s, kp_t, T, kp_noise, depth_noise, gates[-1], kp_loc, rims)


def pose_information(src: DenseGeometry, tgt: DenseGeometry, kp_s: np.ndarray, kp_t: np.ndarray,
                     T_tgt_src: np.ndarray, kp_noise: DepthNoise, depth_noise: DepthNoise, gate: float = 3.0,
                     kp_loc: np.ndarray | None = None, rims: bool = False) -> np.ndarray:
    """[6 x 6] information (rotation first) of T_tgt_src from the keypoint pairs and the depth samples within
    `gate` sigmas of the surface, as `refine_pose` weighs them, for a small motion in the TARGET frame
    (`in_source_frame` turns it into the source frame's)."""
    T = np.asarray(T_tgt_src, dtype=np.float64)
    return _normal_equations(src, tgt, kp_s, kp_t, T, kp_noise, depth_noise, gate, kp_loc, rims)[0]


def pose_sigma(information: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """(largest rotation standard deviation in degrees, RMS positional standard deviation in metres of
    `points` [N x 3] (target frame) moved by the pose) of a pose with [6 x 6] information (rotation first);
    inf when it is singular. A rotation about an axis through the points barely moves them: what matters for
    a registration is how far its pose can move the surface it was solved on (and, through the rotation, the
    surface far from it)."""
    try:
        C = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    ev = np.linalg.eigvalsh(C)
    if ev.min() < 0:  # numerically singular
        return float("inf"), float("inf")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    # displacement of p for a small motion (w, t): -[p]x w + t = G x; its covariance G C G^T, trace summed
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    zero, one = np.zeros(len(p)), np.ones(len(p))
    var = 0.0
    for G in (np.stack([zero, z, -y, one, zero, zero], 1), np.stack([-z, zero, x, zero, one, zero], 1),
              np.stack([y, -x, zero, zero, zero, one], 1)):
        var += float(np.einsum("ij,jk,ik->", G, C, G)) / max(1, len(p))
    return float(np.degrees(np.sqrt(np.linalg.eigvalsh(C[:3, :3]).max()))), float(np.sqrt(var))


def in_source_frame(information_tgt: np.ndarray, T_tgt_src: np.ndarray) -> np.ndarray:
    """[6 x 6] information of a pose for a small motion applied in the source frame, from that in the target
    frame: exp(d_t) T = T exp(d_s) gives d_t = Ad(T) d_s, Ad(T) = [[R, 0], [[t]x R, R]] (rotation first)."""
    R, t = T_tgt_src[:3, :3], T_tgt_src[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    Ad = np.block([[R, np.zeros((3, 3))], [tx @ R, R]])
    return Ad.T @ np.asarray(information_tgt, dtype=np.float64) @ Ad


MIN_NORMAL_COS = float(np.cos(np.radians(45.0)))  # a depth sample and the surface it lands on face alike
HUBER = 2.0  # residuals beyond this many sigmas weigh as the Huber loss does (linearly)


def _normal_equations(src: DenseGeometry, tgt: DenseGeometry, kp_s: np.ndarray, kp_t: np.ndarray, T: np.ndarray,
                      kp_noise: DepthNoise, depth_noise: DepthNoise, gate: float, kp_loc: np.ndarray | None = None,
                      rims: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(J^T W J [6 x 6], J^T W r [6]) of `refine_pose`'s residuals at T, for a small motion (rotation vector,
    translation) applied in tgt's frame."""
    kp_s = np.asarray(kp_s, dtype=np.float64).reshape(-1, 3)
    kp_t = np.asarray(kp_t, dtype=np.float64).reshape(-1, 3)
    s_kp = kp_noise.pair_sigma(kp_s[:, 2], kp_t[:, 2], 0.0 if kp_loc is None else kp_loc)
    H, g = np.zeros((6, 6)), np.zeros(6)
    q = transform_points(T, kp_s)
    r = q - kp_t
    rn = np.linalg.norm(r, axis=1) / s_kp
    w = np.where(rn <= HUBER, 1.0, HUBER / np.maximum(rn, 1e-12)) / np.square(s_kp)
    for c in range(3):  # d(r_c)/d(omega) = (q x e_c), d(r_c)/d(tau) = e_c
        J = np.zeros((len(q), 6))
        J[:, :3] = np.cross(q, np.eye(3)[c])
        J[:, 3 + c] = 1.0
        H += (J * w[:, None]).T @ J
        g += (J * w[:, None]).T @ r[:, c]
    qd, n, e, sd, idx = _plane_pairs(src, tgt, T, depth_noise)
    # a sample pairs with the surface it lands on only where the two face alike (a side of a box landing on its
    # front near their common edge would pull the pose to hide that side)
    n_src = src.point_normals[idx] @ T[:3, :3].T
    ok = (np.abs(e) <= gate * sd) & (np.sum(n_src * n, axis=1) >= MIN_NORMAL_COS)
    qd, n, e, sd = qd[ok], n[ok], e[ok], sd[ok]
    en = np.abs(e) / sd
    wd = np.where(en <= HUBER, 1.0, HUBER / np.maximum(en, 1e-12)) / np.square(sd)
    Jd = np.concatenate([np.cross(qd, n), n], axis=1)
    H, g = H + (Jd * wd[:, None]).T @ Jd, g + (Jd * wd[:, None]).T @ e
    if rims:
        for a, b, forward in ((src, tgt, True), (tgt, src, False)):
            Hr, gr = _rim_equations(a, b, T, forward)
            H, g = H + Hr, g + gr
    return H, g


RIM_PX = 2.0  # a mask's rim is ragged: a rim point within this many pixels of the other mask lies on it
RIM_SIGMA_PX = 1.0  # ... and beyond them, its distance is uncertain by about a pixel


def _rim_equations(a: DenseGeometry, b: DenseGeometry, T_tgt_src: np.ndarray, forward: bool
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(J^T W J [6 x 6], J^T W r [6]) of a's rim points off b's mask: each point's distance (m, at its depth) to the
    mask where it lands beyond RIM_PX, 0 nearer (one-sided: every point of the object projects inside its
    silhouette; without the band the rim's raggedness would pull every pose inwards), sigma RIM_SIGMA_PX at its
    depth, Huber-weighted; for a small motion applied in the target frame of T_tgt_src, a the
    source when `forward`, else the target (moved by the inverse)."""
    H, g = np.zeros((6, 6)), np.zeros(6)
    far = b.outline
    if a.rim is None or not len(a.rim) or far is None:
        return H, g
    T = T_tgt_src if forward else inv_T(T_tgt_src)
    q = transform_points(T, a.rim)
    u, v, z, idx = _project(q, b.full_intrinsics, far.shape)
    dist = far[v, u] - RIM_PX
    out = dist > 0
    if not out.any():
        return H, g
    q, u, v, z, dist = q[idx][out], u[out], v[out], z[out], dist[out]
    H_img, W_img = far.shape  # the distance's gradient there, by central differences
    gu = 0.5 * (far[v, np.minimum(u + 1, W_img - 1)] - far[v, np.maximum(u - 1, 0)])
    gv = 0.5 * (far[np.minimum(v + 1, H_img - 1), u] - far[np.maximum(v - 1, 0), u])
    fx = b.full_intrinsics[0]
    r = dist * z / fx
    # d r / d q = grad(dist) . d(u, v)/d q * z / f: the gradient along the image axes, less the perspective term
    grad = np.stack([gu, gv, -(gu * q[:, 0] + gv * q[:, 1]) / z], axis=1)
    if forward:  # q = T p moves by (w x q + t)
        J = np.concatenate([np.cross(q, grad), grad], axis=1)
    else:  # q = T^-1 p moves by -R^T (w x p + t), p = T q the point in the target frame
        p = transform_points(T_tgt_src, q)
        b_dir = grad @ T_tgt_src[:3, :3].T
        J = -np.concatenate([np.cross(p, b_dir), b_dir], axis=1)
    s = RIM_SIGMA_PX * z / fx
    rn = r / s
    w = np.where(rn <= HUBER, 1.0, HUBER / np.maximum(rn, 1e-12)) / np.square(s)
    return (J * w[:, None]).T @ J, (J * w[:, None]).T @ r


class PlaneResiduals(NamedTuple):
    """src's samples landing on tgt's depth, measured along tgt's normals there: signed point-to-plane distances
    e [K] (m), the samples' depth in tgt's camera z_src [K] and tgt's measured depth there z_tgt [K], and the |cos|
    at which each frame's ray meets the normal, cos_src [K] and cos_tgt [K] (what the depth noise is estimated
    from: `DepthNoise.normal_sigma`)."""

    e: np.ndarray
    z_src: np.ndarray
    z_tgt: np.ndarray
    cos_src: np.ndarray
    cos_tgt: np.ndarray

    def sigma(self, noise: DepthNoise) -> np.ndarray:
        """[K] standard deviation of e under the depth pixel's `noise`."""
        return noise.normal_sigma(self.z_src, self.z_tgt, self.cos_src, self.cos_tgt)


def _residuals(q: np.ndarray, n: np.ndarray, g: np.ndarray, T_tgt_src: np.ndarray) -> PlaneResiduals:
    """`PlaneResiduals` of src's samples q [K x 3] (in tgt's camera) against tgt's samples g [K x 3] with normals
    n [K x 3]; src's camera sits at T_tgt_src's translation."""
    ray_src = q - T_tgt_src[:3, 3]
    cos_src = np.abs(np.sum(n * ray_src, axis=1)) / np.maximum(np.linalg.norm(ray_src, axis=1), 1e-12)
    cos_tgt = np.abs(np.sum(n * g, axis=1)) / np.maximum(np.linalg.norm(g, axis=1), 1e-12)
    return PlaneResiduals(np.sum(n * (q - g), axis=1), q[:, 2], g[:, 2], cos_src, cos_tgt)


def plane_residuals(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray) -> PlaneResiduals:
    """The point-to-plane distances of src's samples landing on tgt's depth under T_tgt_src (`PlaneResiduals`)."""
    q, vi, ui, _ = _landing(src, tgt, T_tgt_src)
    return _residuals(q, tgt.normals[vi, ui], tgt.grid[vi, ui], T_tgt_src)


def _plane_pairs(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, noise: DepthNoise
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """src's samples in tgt's frame that land on tgt's depth: (points [K x 3], tgt's normals there [K x 3],
    signed point-to-plane distances [K], their sigma [K], their indices [K] in src.points)."""
    q, vi, ui, idx = _landing(src, tgt, T_tgt_src)
    n = tgt.normals[vi, ui]
    p = _residuals(q, n, tgt.grid[vi, ui], T_tgt_src)
    return q, n, p.e, p.sigma(noise), idx


def outside_outline(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, margin_m: float,
                    rim_px: float = RIM_PX) -> float:
    """The share of the rim points (`rim_points`; the samples where a frame has none) of each frame that, moved
    into the other by T_tgt_src, fall inside its image but farther off its mask than `margin_m` at the point's
    depth plus `rim_px` (the mask's ragged rim), at the image's full resolution (`outline`), both directions
    pooled; 0 when none falls inside or a frame has no mask. `outside_silhouette` at the pixel, on the mask alone
    (every point of the object projects inside its silhouette, with depth or not): a pose slid along a plain face
    keeps the face on the face and its depth, and moves the outline by the slide (a plain box at 0.6 m, no
    margin: right poses none; slid 1 cm along any of its axes, 24-45 % of the rim, 0-0.5 % of the samples)."""
    out = inside = 0
    for a, b, T in ((src, tgt, T_tgt_src), (tgt, src, inv_T(T_tgt_src))):
        if b.outline is None:
            return 0.0
        pts = a.points if a.rim is None or not len(a.rim) else a.rim
        u, v, z, _ = _project(transform_points(T, pts), b.full_intrinsics, b.outline.shape)
        inside += len(u)
        out += int(np.count_nonzero(b.outline[v, u] > b.full_intrinsics[0] * margin_m / z + rim_px))
    return out / inside if inside else 0.0


def outside_silhouette(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, margin: int = 2) -> float:
    """The share of the samples of each frame that, moved into the other by T_tgt_src, fall inside its image
    but more than `margin` samples away from any of its valid samples (both directions pooled; 0 when none
    falls inside). With object-only samples (a mask) this is the silhouette test: every point of the object
    projects inside the object's silhouette in any view, hidden or not, so a right pose leaves only the
    depth's holes and the mask's rim outside; a pose turned by a symmetry of the shape rarely fits the
    silhouette too (a box turned a quarter shows its long side where the short one was)."""
    import cv2

    out = inside = 0
    for a, b, T in ((src, tgt, T_tgt_src), (tgt, src, inv_T(T_tgt_src))):
        u, v, _, _ = _project(transform_points(T, a.points), (b.fx, b.fy, b.cx, b.cy), b.depth.shape)
        # samples' distance to the nearest valid sample of b (0 on one)
        far = cv2.distanceTransform((b.depth <= 0).astype(np.uint8), cv2.DIST_L2, 3)
        inside += len(u)
        out += int(np.count_nonzero(far[v, u] > margin))
    return out / inside if inside else 0.0
