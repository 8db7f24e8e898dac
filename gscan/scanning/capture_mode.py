"""Capture mode detection, and object masks for a static camera.

Two capture modes: a static object scanned by a moving camera ("static-object":
the whole frame moves rigidly with the object, so registration may use all of it), or a
moving object in front of a static camera ("moving-object": turntable or object in hand,
only the object's pixels may be registered, the background would pull every pose to identity).

Detection rule (`detect_mode`): compare frame pairs spread over the capture. A pixel is
*static* when both frames have valid depth there, the depths agree within
max(4 mm, 1 % of the depth) and the grey levels within 12, and its tile's texture lines up
at the same pixels (a camera circling a low-contrast table keeps the table's depth and grey
levels at every pixel; only its texture moves). Pixels inside a given object mask (dilated)
are ignored. When the median static fraction over the pairs is at least
`static_fraction` (0.65) the camera did not move: moving-object; otherwise static-object.
"""
from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from gscan.geometry.plane import Plane
from gscan.io.camera import RGBDFrame
from gscan.registration.colour import image_noise, min_texture_std, texture_image, tile_ids, tile_scores
from gscan.scanning.modes import MOVING_OBJECT, STATIC_OBJECT
from gscan.scanning.segment import SegmentParams, segment_frame

log = logging.getLogger(__name__)


@dataclass
class ModeDecision:
    mode: str  # STATIC_OBJECT | MOVING_OBJECT
    static_fraction: float  # median fraction of unchanged background pixels over the tested pairs
    pairs: int  # how many frame pairs were compared


def _static_fraction(a: RGBDFrame, b: RGBDFrame) -> float:
    da, db = a.depth, b.depth
    valid = (da > 0) & (db > 0)
    ignore = np.zeros_like(valid)
    for m in (a.mask, b.mask):
        if m is not None:
            ignore |= cv2.dilate(m.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    valid &= ~ignore
    if valid.sum() < 100:
        return 0.0
    ga = cv2.cvtColor(a.color, cv2.COLOR_RGB2GRAY).astype(np.int16)
    gb = cv2.cvtColor(b.color, cv2.COLOR_RGB2GRAY).astype(np.int16)
    same = (np.abs(da - db) <= np.maximum(0.004, 0.01 * da)) & (np.abs(ga - gb) <= 12)
    same &= ~_texture_moved(ga, gb, valid)
    return float((same & valid).sum() / valid.sum())


def _texture_moved(ga: np.ndarray, gb: np.ndarray, valid: np.ndarray, step: int = 4) -> np.ndarray:
    """[H x W] bool: pixels of the tiles whose texture does not line up between two grey images [H x W] at the
    same pixels (`gscan.registration.colour`'s rank test with no displacement). A camera circling a low-contrast
    table keeps its depth and grey levels at every pixel; only its texture moves."""
    H, W = ga.shape
    vv, uu = np.mgrid[step // 2:H:step, step // 2:W:step]
    sel = valid[vv, uu]
    v, u = vv[sel], uu[sel]
    ta, tb = texture_image(ga), texture_image(gb)
    ids, informative, agree = tile_scores(ta[v, u].astype(np.float64), tile_ids(u, v, W), tb, u.astype(np.float64),
                                          v.astype(np.float64), min_texture_std(image_noise(ga)), search=((0, 0),))
    rows, cs = np.mgrid[0:H, 0:W]
    return np.isin(tile_ids(cs, rows, W), ids[informative & ~agree])


def detect_mode(frames: Sequence[RGBDFrame], static_fraction: float = 0.65) -> ModeDecision:
    """Decide static-object vs moving-object from the frames (see module docstring); `frames` may be a lazy
    sequence: only the frames compared are read.

    The pairs compared are far apart in the sequence (first-last, first-middle, middle-last,
    quarter-three quarters), so that a slowly moving hand-held camera has moved between them.
    """
    n = len(frames)
    if n < 2:
        return ModeDecision(STATIC_OBJECT, 0.0, 0)
    pairs = sorted({(0, n - 1), (0, n // 2), (n // 2, n - 1), (n // 4, (3 * n) // 4)} - {(k, k) for k in range(n)})
    fracs = [_static_fraction(frames[i], frames[j]) for i, j in pairs]
    med = float(np.median(fracs))
    mode = MOVING_OBJECT if med >= static_fraction else STATIC_OBJECT
    log.info("capture mode %s (static background fraction %.2f over %d pairs)", mode, med, len(fracs))
    return ModeDecision(mode, med, len(fracs))


def moving_object_masks(frames: list[RGBDFrame], min_offset: float = 0.01, min_area: int = 400,
                        params: SegmentParams | None = None) -> tuple[list[np.ndarray], list[Plane | None]]:
    """Object masks for a static camera without given masks. Returns ([H x W] bool per frame, the
    support plane found in each frame, camera frame, or None).

    Each frame is segmented on its own by the support plane and the component above it
    (`gscan.scanning.segment.segment_frame` with `params`). A frame without a support plane (object in hand) falls back
    to background subtraction (`background_depth` over the sequence, `foreground_mask`).
    """
    params = params if params is not None else SegmentParams()
    segs = [segment_frame(replace(f, mask=None), params) for f in frames]
    planes = [s.plane_cam for s in segs]
    if all(p is not None for p in planes):
        return [s.mask for s in segs], planes
    bg = background_depth([f.depth for f in frames])
    return [s.mask if s.plane_cam is not None else foreground_mask(f.depth, bg, min_offset, min_area)
            for f, s in zip(frames, segs, strict=True)], planes


def background_depth(depths: list[np.ndarray]) -> np.ndarray:
    """[H x W] the background a static camera sees: per pixel the 90th percentile of the valid depths [H x W] (m)
    of `depths` (the farthest surface seen there), inf where none is valid."""
    stack = np.stack(depths).astype(np.float32)
    stack[stack <= 0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nan_to_num(np.nanpercentile(stack, 90, axis=0), nan=np.inf)


def foreground_mask(depth: np.ndarray, bg: np.ndarray, min_offset: float = 0.01, min_area: int = 400) -> np.ndarray:
    """[H x W] bool: where depth [H x W] (m) is closer than the background `bg` by max(`min_offset`, 2 %), cleaned
    by an opening and kept as the connected components of at least `min_area` pixels (the largest always kept)."""
    d = depth
    fg = (d > 0) & (d < bg - np.maximum(min_offset, 0.02 * np.where(np.isfinite(bg), bg, 0)))
    fg_u8 = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(fg_u8, connectivity=8)
    keep = np.zeros(n, dtype=bool)
    if n > 1:
        areas = stats[1:, cv2.CC_STAT_AREA]
        keep[1:] = areas >= min_area
        keep[1 + int(np.argmax(areas))] = True
    return keep[lab]
