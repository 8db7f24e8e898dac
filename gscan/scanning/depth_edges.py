"""Is the depth registered to the colour? Its discontinuities against the colour image's edges.

Where the depth jumps (an occluding contour: a table's edge, a mug's side), the colour image has an edge too. With
depth registered to colour under the given intrinsics, the depth's jumps lie on colour edges; a depth camera of
another focal length or position puts them off by a scale about the principal point and a shift (7-Scenes' Kinect:
585 px against 525 px and 2.5 cm apart, 10-30 px off). For each frame the depth's jump pixels are mapped by
u' = c + s (u - c) + d for s in the calibration check's scales and shifts d in whole pixels up to `max_shift_px`,
and scored by their mean distance to the nearest colour edge (truncated at `truncate_px`: a jump on a colour edge
that a uniform surface hides costs the same under every mapping). A frame is off when its best mapping moves the
jumps by more than `tolerance_px` on average from where they are; the depth is not registered when significantly
more frames are off than not (a sign test), registered when significantly fewer, and undecided otherwise (too
few frames with depth jumps, or frames that disagree).

Depth jumps: neighbouring pixels whose depths differ by more than `jump_sigmas` times the noise of their difference
(gscan.registration.noise.DepthNoise), on the near side; holes (depth 0) are not jumps (a structured-light
sensor's shadows lie beside the contour, on one side).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

import cv2
import numpy as np
from pydantic import Field

from gscan.io.camera import RGBDFrame
from gscan.registration.noise import DepthNoise, sign_test
from gscan.settings import SETTINGS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EdgeParams:
    """The depth-edge test's settings (module docstring)."""

    __pydantic_config__ = SETTINGS

    jump_sigmas: Annotated[float, Field(gt=0, description="a depth jump: neighbours this many noise sigmas "
                                        "apart")] = 8.0
    max_shift_px: Annotated[int, Field(ge=1, description="the largest shift tried (pixels)")] = 24
    truncate_px: Annotated[float, Field(gt=0, description="distances to a colour edge counted up to this")] = 8.0
    tolerance_px: Annotated[float, Field(gt=0, description="a frame whose best mapping moves its depth jumps less "
                                         "than this (mean, pixels) lines up: a structured-light depth's contour "
                                         "is a few pixels wide")] = 4.0
    min_jumps: Annotated[int, Field(ge=10, description="the fewest depth-jump pixels a frame needs to "
                                    "count")] = 200
    max_jumps: Annotated[int, Field(ge=10, description="depth-jump pixels kept per frame (evenly)")] = 1500
    alpha: Annotated[float, Field(gt=0, lt=1, description="the sign test's level")] = 0.05


@dataclass(frozen=True)
class FrameEdges:
    """One frame's best mapping of its depth jumps onto the colour edges: scale s and shift (dx, dy) px; offset_px:
    how far it moves the jumps (mean, px); cost_given / cost_best: the jumps' mean (truncated) distance to a colour
    edge where they are and under the best mapping (px); jumps: depth-jump pixels scored."""

    name: str
    scale: float
    shift_px: tuple[int, int]
    offset_px: float
    cost_given: float
    cost_best: float
    jumps: int


@dataclass(frozen=True)
class EdgeEvidence:
    """verdict: "registered" | "not registered" | "undecided"; frames: the frames scored (with enough depth jumps);
    off: how many of them are off by more than the tolerance; p_value: the sign test's (for the verdict given);
    offset_px / scale: the frames' median offset and best scale."""

    verdict: str
    frames: tuple[FrameEdges, ...]
    off: int
    p_value: float
    offset_px: float
    scale: float

    def to_dict(self) -> dict:
        """JSON-ready (null for the medians of no frame)."""
        def num(x: float, digits: int) -> float | None:
            return round(x, digits) if np.isfinite(x) else None

        return {"verdict": self.verdict, "frames": len(self.frames), "off": self.off,
                "p_value": round(self.p_value, 4), "median_offset_px": num(self.offset_px, 1),
                "median_scale": num(self.scale, 3)}


def depth_jumps(depth: np.ndarray, sigmas: float, noise: DepthNoise = DepthNoise()) -> np.ndarray:
    """[H x W] bool: pixels on the near side of a depth jump (depth [H x W] metres, 0 = invalid)."""
    z = depth.astype(np.float64)
    out = np.zeros(z.shape, bool)
    for a, b, ia, ib in ((z[:, :-1], z[:, 1:], (slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                         (z[:-1, :], z[1:, :], (slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        ok = (a > 0) & (b > 0)
        jump = ok & (np.abs(a - b) > sigmas * noise.pair_sigma(np.where(ok, a, 1.0), np.where(ok, b, 1.0)))
        out[ia] |= jump & (a < b)
        out[ib] |= jump & (b < a)
    return out


def colour_edge_distance(color: np.ndarray, truncate: float) -> np.ndarray:
    """[H x W] float32 distance (px) to the nearest colour edge, at most `truncate` (Canny on the grey image, its
    thresholds at the 90th and 80th percentiles of the gradient magnitude: the image's own contrast)."""
    gray = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY) if color.ndim == 3 else color
    gray = cv2.GaussianBlur(gray, (5, 5), 1.0)
    mag = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
    hi, lo = np.percentile(mag, 90), np.percentile(mag, 80)
    edges = cv2.Canny(gray, float(lo), float(max(hi, lo + 1)), L2gradient=True)
    dist = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
    return np.minimum(dist, truncate).astype(np.float32)


def frame_edges(frame: RGBDFrame, scales: Sequence[float], params: EdgeParams = EdgeParams()) -> FrameEdges | None:
    """The best mapping of one frame's depth jumps onto its colour edges (module docstring); None when it has
    fewer than `params.min_jumps` depth-jump pixels."""
    jumps = depth_jumps(frame.depth, params.jump_sigmas)
    v, u = np.nonzero(jumps)
    if len(u) < params.min_jumps:
        return None
    if len(u) > params.max_jumps:  # evenly along the image's raster order (deterministic)
        keep = np.linspace(0, len(u) - 1, params.max_jumps).astype(int)
        u, v = u[keep], v[keep]
    dist = colour_edge_distance(frame.color, params.truncate_px)
    H, W = dist.shape
    K = frame.intrinsics
    def cost(s: float, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """[len(dx)] the jumps' mean truncated distance to a colour edge under scale s and shifts (dx, dy)."""
        us = np.rint(K.cx + s * (u - K.cx)).astype(np.int64)
        vs = np.rint(K.cy + s * (v - K.cy)).astype(np.int64)
        U, V = us[None, :] + dx[:, None], vs[None, :] + dy[:, None]
        inside = (U >= 0) & (U < W) & (V >= 0) & (V < H)
        return np.where(inside, dist[np.clip(V, 0, H - 1), np.clip(U, 0, W - 1)], params.truncate_px).mean(axis=1)

    def grid(r: int, step: int, at: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
        g = np.arange(-r, r + 1, step)
        dx, dy = np.meshgrid(g + at[0], g + at[1])
        return dx.ravel(), dy.ravel()

    # coarse: every scale, shifts every `step` px (a distance map is smooth over a few px); then the best
    # scale's neighbours and shifts around the best, every px
    step = 3
    best = (np.inf, 1.0, 0, 0)
    for s in scales:
        dx, dy = grid(params.max_shift_px - params.max_shift_px % step, step)
        c = cost(s, dx, dy)
        k = int(np.argmin(c))
        if c[k] < best[0] - 1e-9:
            best = (float(c[k]), float(s), int(dx[k]), int(dy[k]))
    i = list(scales).index(best[1])
    for s in scales[max(0, i - 1):i + 2]:
        dx, dy = grid(step, 1, (best[2], best[3]))
        c = cost(s, dx, dy)
        k = int(np.argmin(c))
        if c[k] < best[0] - 1e-9:
            best = (float(c[k]), float(s), int(dx[k]), int(dy[k]))
    given = float(cost(1.0, np.zeros(1, np.int64), np.zeros(1, np.int64))[0])
    c_best, s_best, bx, by = best
    offset = float(np.mean(np.hypot((s_best - 1) * (u - K.cx) + bx, (s_best - 1) * (v - K.cy) + by)))
    return FrameEdges(frame.name, s_best, (bx, by), offset, given, c_best, len(u))


def edge_evidence(frames: Sequence[RGBDFrame], scales: Sequence[float], params: EdgeParams = EdgeParams()
                  ) -> EdgeEvidence:
    """The module docstring's verdict over `frames` (each scored alone; those with too few depth jumps left
    out)."""
    got = tuple(f for f in (frame_edges(fr, scales, params) for fr in frames) if f is not None)
    for f in got:
        log.debug("depth edges of %s: best x%.2f shift %s (offset %.1f px), cost %.2f px given, %.2f px best",
                  f.name, f.scale, f.shift_px, f.offset_px, f.cost_given, f.cost_best)
    off = sum(f.offset_px > params.tolerance_px for f in got)
    on = len(got) - off
    p_off, p_on = sign_test(off, on), sign_test(on, off)
    if got and p_off < params.alpha:
        verdict, p = "not registered", p_off
    elif got and p_on < params.alpha:
        verdict, p = "registered", p_on
    else:
        verdict, p = "undecided", min(p_off, p_on)
    med_off = float(np.median([f.offset_px for f in got])) if got else float("nan")
    med_s = float(np.median([f.scale for f in got])) if got else float("nan")
    return EdgeEvidence(verdict, got, off, p, med_off, med_s)
