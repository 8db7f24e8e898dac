"""Colour evidence for an edge: does the texture of one frame line up with the other's under its pose?

Depth cannot tell a pose from its mirror when the geometry is symmetric: a box on a table turned 180 deg
about its vertical axis puts every surface back on a surface, and the depth check passes it. The texture
tells them apart: under a right pose the table's grain, the print and the shadows of one frame land on the
same texture in the other; under a wrong one on unrelated texture, however alike the keypoints are.

`texture_image` band-passes a grey image (minus its Gaussian blur at `BAND_SIGMA` px): exposure and shading
differences between the views go, the texture stays. `gscan.registration.dense.colour_agreement` samples,
for the depth samples of one frame that land on the other's surface, the other frame's texture where they
land, and groups them in tiles of `TILE` px of the first frame (`tile_scores`). A tile is informative
when its texture varies beyond the image noise (`image_noise`, estimated from the image itself). The whole
overlap is first shifted by the one image displacement within `SEARCH` that correlates best (a right
pose is good to a few pixels); a tile then agrees when its normalised cross-correlation there beats each
of its correlations at the `len(FAR)` displacements `FAR_RADIUS` px around it, its own baseline. Unrelated
texture passes that rank test in about 1 tile of 17; a right pose in most tiles, fewer where the views
differ (highlights, a steep change of viewpoint).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from gscan.registration.colour_kernel import shifted_sums

BAND_SIGMA = 4.5  # px: the blur subtracted by `texture_image` (texture finer than this is kept)
TILE = 48  # px: the side of a tile of the source image
MIN_TILE_SAMPLES = 16  # samples a tile needs to correlate
TEXTURE_SNR = 3.0  # a tile is informative when its texture's std is this many times the image noise ...
MIN_TEXTURE = 1.0  # ... and at least this many grey levels (8-bit quantisation and compression floor)
PRINT_REACH_PX = 3.0 * BAND_SIGMA  # px: how far the band-pass's blur carries a rim's or a crease's shading
SEARCH = tuple((dx, dy) for dx in range(-6, 7, 3) for dy in range(-6, 7, 3))  # px: where the pose's alignment is sought
FAR_RADIUS = 15.0  # px: the baseline's displacements, beyond the band-pass's reach
FAR = tuple((round(FAR_RADIUS * np.cos(a)), round(FAR_RADIUS * np.sin(a))) for a in np.arange(16) * np.pi / 8)


def grey_image(image: np.ndarray) -> np.ndarray:
    """[H x W] float32 grey levels of an [H x W x 3] RGB or [H x W] grey image."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    return img.astype(np.float32)


def texture_image(grey: np.ndarray) -> np.ndarray:
    """[H x W] float32: grey [H x W] (any range) minus its Gaussian blur at BAND_SIGMA px."""
    g = np.asarray(grey, dtype=np.float32)
    return g - cv2.GaussianBlur(g, (0, 0), BAND_SIGMA)


def image_noise(grey: np.ndarray) -> float:
    """Standard deviation (grey levels) of an image's pixel noise, by Immerkaer's Laplacian-difference estimator
    (Fast noise variance estimation, CVIU 1996): texture mostly cancels in the mask, noise does not."""
    g = np.asarray(grey, dtype=np.float32)
    if min(g.shape) < 3:
        return 0.0
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    n = cv2.filter2D(g, cv2.CV_32F, mask, borderType=cv2.BORDER_REPLICATE)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2) * np.mean(np.abs(n), dtype=np.float64) / 6.0)


def tile_ids(u: np.ndarray, v: np.ndarray, width: int) -> np.ndarray:
    """[K] the TILE x TILE tile of each integer pixel (u [K], v [K]) of an image `width` pixels wide."""
    return (v // TILE) * (width // TILE + 1) + u // TILE


def min_texture_std(noise: float) -> float:
    """The texture's standard deviation (grey levels) that makes a tile informative in an image of `noise`."""
    return max(TEXTURE_SNR * noise, MIN_TEXTURE)


@dataclass(frozen=True)
class ColourAgreement:
    """Tiles of the overlap (both directions): informative ones, and those whose texture lines up."""

    informative: int
    agreeing: int

    @property
    def agreeing_fraction(self) -> float:
        return self.agreeing / max(1, self.informative)

    def refutes(self, min_tiles: int, min_agreement: float) -> bool:
        """Whether the texture refutes the pose (registration's rule 3): at least `min_tiles` informative tiles,
        fewer than `min_agreement` of them lining up."""
        return self.informative >= min_tiles and self.agreeing_fraction < min_agreement

    def settles(self, min_tiles: int, min_agreement: float) -> bool:
        """Whether the texture settles the pose: at least `min_tiles` informative tiles, at least `min_agreement`
        of them lining up."""
        return self.informative >= min_tiles and self.agreeing_fraction >= min_agreement

    def mostly_agrees(self, min_tiles: int) -> bool:
        """Whether most of at least `min_tiles` informative tiles line up."""
        return self.informative >= min_tiles and 2 * self.agreeing > self.informative

    def __add__(self, other: ColourAgreement) -> ColourAgreement:
        return ColourAgreement(self.informative + other.informative, self.agreeing + other.agreeing)


def _tile_zncc(Ia: np.ndarray, t: np.ndarray, n_tiles: int, tgt_texture: np.ndarray, u: np.ndarray,
               v: np.ndarray, shifts: tuple[tuple[int, int], ...]) -> np.ndarray:
    """[len(shifts) x n_tiles] normalised cross-correlation per tile (ids t [K], each of 0..n_tiles-1 present)
    of Ia [K] with the target's texture, bilinearly interpolated, at (u + dx, v + dy) [K]; the positions must
    keep one pixel inside the image at every shift. The shifts are whole pixels, so the interpolation weights
    are those of (u, v) for all of them."""
    order = np.argsort(t, kind="stable")
    t, Ia, u, v = t[order], np.ascontiguousarray(Ia[order], np.float64), u[order], v[order]
    starts = np.flatnonzero(np.r_[True, t[1:] != t[:-1]])
    W = tgt_texture.shape[1]
    x0, y0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fx, fy = u - x0, v - y0
    flat = np.ascontiguousarray(tgt_texture).ravel()
    offsets = np.array([dy * W + dx for dx, dy in shifts], dtype=np.int64)
    sb, sbb, sab = (np.empty((len(shifts), len(starts))) for _ in range(3))
    bounds = np.r_[starts, len(t)].astype(np.int64)  # tile g holds samples bounds[g]:bounds[g + 1]
    shifted_sums(Ia, bounds, flat, W, y0 * W + x0, np.asarray(fx, np.float64), np.asarray(fy, np.float64), offsets,
                 sb, sbb, sab)
    n = np.diff(bounds).astype(np.float64)
    sa = np.add.reduceat(Ia, starts)
    var_a = np.add.reduceat(Ia * Ia, starts) - sa * sa / n
    var_b = sbb - sb * sb / n
    cov = sab - sa * sb / n
    return cov / np.sqrt(np.maximum(var_a * var_b, 1e-12))


def _correlatable(u: np.ndarray, v: np.ndarray, shape: tuple[int, ...], search: tuple[tuple[int, int], ...]
                  ) -> np.ndarray:
    """[K] bool: the landing positions (u [K], v [K]) that stay inside an image of `shape` at every displacement
    `tile_scores` tries (search and its baseline's)."""
    H, W = shape[:2]
    m = max(abs(c) for s in search + FAR for c in s) * 2 + 1
    return (u >= m) & (u < W - 1 - m) & (v >= m) & (v < H - 1 - m)


def tile_scores(Ia: np.ndarray, tiles: np.ndarray, tgt_texture: np.ndarray, u: np.ndarray, v: np.ndarray,
                min_std: float, search: tuple[tuple[int, int], ...] = SEARCH
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rank test of the module docstring, per tile. Ia [K]: the source samples' texture; tiles [K]: their
    tile ids; (u [K], v [K]): where they land in the target image (pixels); min_std: an informative tile's
    texture; search: the image displacements tried for the whole overlap. Returns (tile ids [T], informative [T]
    bool, agreeing [T] bool)."""
    keep = _correlatable(u, v, tgt_texture.shape, search)
    Ia, tiles, u, v = Ia[keep], tiles[keep], u[keep], v[keep]
    ids, t = np.unique(tiles, return_inverse=True)
    n = np.bincount(t, minlength=len(ids))
    dev = Ia - (np.bincount(t, Ia, len(ids)) / np.maximum(n, 1))[t]
    std = np.sqrt(np.bincount(t, dev * dev, len(ids)) / np.maximum(n - 1, 1))
    informative = (n >= MIN_TILE_SAMPLES) & (std >= min_std)
    if not informative.any():
        return ids, informative, informative.copy()
    # one image shift for the whole overlap (the pose's own error, a few pixels), then each tile against
    # its own baseline around that shift
    near = _tile_zncc(Ia, t, len(ids), tgt_texture, u, v, search)
    best = int(np.argmax(near[:, informative].sum(axis=1)))
    bx, by = search[best]
    far = _tile_zncc(Ia, t, len(ids), tgt_texture, u, v, tuple((bx + dx, by + dy) for dx, dy in FAR)).max(axis=0)
    return ids, informative, informative & (near[best] > far) & (near[best] > 0)


@dataclass(frozen=True)
class PrintAgreement:
    """Tiles of the overlap (both directions) on the faces' interiors (`gscan.registration.dense.interior`):
    informative ones (textured in the image they tile), those whose counterpart in the other image is plain
    (one-sided: print one image has and the other lacks), and those that line up with a textured counterpart."""

    informative: int
    one_sided: int
    agreeing: int

    def __add__(self, other: PrintAgreement) -> PrintAgreement:
        return PrintAgreement(self.informative + other.informative, self.one_sided + other.one_sided,
                              self.agreeing + other.agreeing)


def print_tiles(Ia: np.ndarray, tiles: np.ndarray, tgt_texture: np.ndarray, u: np.ndarray, v: np.ndarray,
                min_std: float, tgt_min_std: float) -> PrintAgreement:
    """`tile_scores` of the source samples (Ia [K], tiles [K], landing at u [K], v [K] in the target's texture),
    with each informative tile's counterpart judged: plain when the target's texture where its samples land
    (nearest pixel) varies less than tgt_min_std, the target image's informative level. A one-sided tile never
    counts as lining up: the rank test passes on noise against a plain counterpart about 1 time in 17."""
    ids, informative, agree = tile_scores(Ia, tiles, tgt_texture, u, v, min_std)
    if not informative.any():
        return PrintAgreement(0, 0, 0)
    keep = _correlatable(u, v, tgt_texture.shape, SEARCH)
    H, W = tgt_texture.shape
    ub = np.clip(np.rint(u[keep]).astype(np.int64), 0, W - 1)
    vb = np.clip(np.rint(v[keep]).astype(np.int64), 0, H - 1)
    b = tgt_texture[vb, ub].astype(np.float64)
    t = np.searchsorted(ids, tiles[keep])  # ids: the sorted tiles of the same kept samples
    n = np.bincount(t, minlength=len(ids))
    dev = b - (np.bincount(t, b, len(ids)) / np.maximum(n, 1))[t]
    plain = np.sqrt(np.bincount(t, dev * dev, len(ids)) / np.maximum(n - 1, 1)) < tgt_min_std
    one_sided = informative & plain
    return PrintAgreement(int(informative.sum()), int(one_sided.sum()), int((agree & ~one_sided).sum()))


CHROMA_BOX = 5  # px: the box a pixel's chromaticity is averaged over (its noise falls by this factor)


def chromaticity(image: np.ndarray, max_sigma: float) -> np.ndarray | None:
    """[H x W x 2] float32: the (r, g) chromaticity, each channel over the channels' sum, of an [H x W x 3] RGB image
    averaged over CHROMA_BOX px boxes; NaN where the image is too dark to tell it: a channel of noise sigma
    (`image_noise`) moves the chromaticity of a sum S by about sqrt(2) sigma / (CHROMA_BOX S), kept where that is at
    most max_sigma. Shading scales the channels alike and leaves it; a surface of another colour moves it. None for a
    grey image."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] < 3:
        return None
    rgb = cv2.blur(img[..., :3].astype(np.float32), (CHROMA_BOX, CHROMA_BOX))
    s = rgb.sum(axis=2)
    dark = np.sqrt(2.0) * max(image_noise(grey_image(img)), 1.0 / np.sqrt(12.0)) / (CHROMA_BOX * max_sigma)
    return np.where((s >= dark)[..., None], rgb[..., :2] / np.maximum(s, 1e-6)[..., None], np.nan).astype(np.float32)


def chroma_shift(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """(shift, n): how far the chromaticities b [K x 2] lie from a [K x 2] pair by pair, the median of the pairs'
    distances, over the n pairs known in both (not NaN); (0, 0) without any. A light or white balance that differs
    moves every pair alike (the median is that move); a surface of another colour moves most pairs, each its own
    way (a print's colours: their mean difference would cancel)."""
    d = np.asarray(b, np.float64) - np.asarray(a, np.float64)
    d = d[np.isfinite(d).all(axis=1)]
    if not len(d):
        return 0.0, 0
    return float(np.median(np.linalg.norm(d, axis=1))), len(d)
