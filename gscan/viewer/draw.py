"""What the viewer draws, as pure functions (no viser): quality and edge colours, thumbnails, keypoints and
match panels on images. Images are [H x W x 3] uint8 RGB; pixels are (u, v) with the pixel-centre convention.
"""
from __future__ import annotations

import cv2
import numpy as np

from gscan.template.db import Edge

QUERY_CAMERA_COLOR = (40, 120, 255)  # the frustum of a query frame placed by an estimated pose
# coverage cells by how many views see them: none (grey), one (orange), two (yellow), three or more (green)
COUNT_COLORS = np.array([[110, 110, 110], [240, 140, 30], [230, 220, 40], [40, 200, 70]], dtype=np.uint8)
SURFACE_SEEN_COLOR = (90, 160, 230)  # a cell no view looked from, seen through the observed surface's normals


def _rgb(c: np.ndarray) -> tuple[int, int, int]:
    """[3] colour components, rounded to integers."""
    return (int(round(c[0])), int(round(c[1])), int(round(c[2])))


def quality_color(q: float | None) -> tuple[int, int, int]:
    """Quality in [0, 1] (1 best) -> RGB: green (1) .. yellow (0.5) .. red (0); grey when None."""
    if q is None or not np.isfinite(q):
        return (150, 150, 150)
    q = float(np.clip(q, 0.0, 1.0))
    good, mid, bad = np.array([30, 190, 60]), np.array([240, 200, 0]), np.array([220, 30, 30])
    c = mid + (good - mid) * (q - 0.5) * 2 if q >= 0.5 else bad + (mid - bad) * q * 2
    return _rgb(c)


def edge_color(edge: Edge, rmse_red_m: float) -> tuple[int, int, int]:
    """Colour of a pose-graph edge: sequential green..red by RMSE, loop cyan..magenta, rejected grey."""
    if not edge.accepted:
        return (160, 160, 160)
    if edge.rmse is None or not np.isfinite(edge.rmse):
        return (120, 120, 120) if edge.kind == "sequential" else (110, 110, 200)
    t = float(np.clip(edge.rmse / rmse_red_m, 0.0, 1.0))
    if edge.kind == "loop":
        lo, hi = np.array([0, 200, 230]), np.array([230, 0, 200])
        return _rgb(lo + (hi - lo) * t)
    return quality_color(1.0 - t)


def coverage_colors(counts: np.ndarray, surface: np.ndarray | None = None) -> np.ndarray:
    """[K] view counts (and [K] bool: seen through the surface) -> [K x 3] uint8 colours (`COUNT_COLORS`;
    `SURFACE_SEEN_COLOR` where no view but the surface saw the cell)."""
    c = COUNT_COLORS[np.minimum(np.asarray(counts), len(COUNT_COLORS) - 1)]
    if surface is not None:
        c[(np.asarray(counts) == 0) & np.asarray(surface, dtype=bool)] = SURFACE_SEEN_COLOR
    return c
def symmetry_color(fold: int, in_texture: bool) -> tuple[int, int, int]:
    """An axis of symmetry's colour: revolution magenta, a 4-fold (or higher) axis orange, a 2-fold one cyan; pale
    when it holds in shape alone (the texture tells the turned poses apart)."""
    base = (220, 40, 220) if fold == 0 else (240, 140, 20) if fold >= 3 else (20, 190, 220)
    if in_texture:
        return base
    r, g, b = (int(round(0.45 * c + 0.55 * 235)) for c in base)
    return r, g, b


def thumbnail(img: np.ndarray, max_side: int) -> np.ndarray:
    """[H x W x 3] uint8 -> the image downscaled (area filter) so its longest side is <= max_side."""
    h, w = img.shape[:2]
    s = min(1.0, max_side / float(max(h, w)))
    if s >= 1.0:
        return np.ascontiguousarray(img)
    return cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)


OBJECT_OUTLINE_COLOR = (60, 255, 60)  # the object segmentation chose, outlined on a keyframe


def outline_mask(img: np.ndarray, mask: np.ndarray, color: tuple[int, int, int] = OBJECT_OUTLINE_COLOR
                 ) -> np.ndarray:
    """A copy of the image [h x w x 3] with the outline of the mask [H x W] bool (any size: scaled to the image)
    drawn on it, 2 px wide."""
    h, w = img.shape[:2]
    m = cv2.resize(np.asarray(mask, dtype=np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    out = np.ascontiguousarray(img).copy()
    cv2.drawContours(out, contours, -1, color, 2)
    return out


def scale_pixels(pixels: np.ndarray, src_wh: tuple[int, int], dst_wh: tuple[int, int]) -> np.ndarray:
    """[N x 2] pixels (u, v) of a src_wh image -> the same points in a resized dst_wh image
    (pixel-centre convention, per-axis factors)."""
    f = np.array([dst_wh[0] / src_wh[0], dst_wh[1] / src_wh[1]])
    return (np.asarray(pixels, dtype=np.float64).reshape(-1, 2) + 0.5) * f - 0.5


def hue_colors(n: int) -> np.ndarray:
    """[n x 3] uint8 RGB, deterministic well-separated hues."""
    hsv = np.zeros((1, max(n, 1), 3), np.uint8)
    hsv[0, :, 0] = (np.arange(max(n, 1)) * 47) % 180
    hsv[0, :, 1], hsv[0, :, 2] = 230, 255
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, :n]


def image_wh(img: np.ndarray) -> tuple[int, int]:
    """(width, height) of an [H x W (x C)] image."""
    return img.shape[1], img.shape[0]


def draw_keypoints(img: np.ndarray, pixels: np.ndarray, full_wh: tuple[int, int]) -> np.ndarray:
    """Keypoints [N x 2] (u, v in the full_wh image) drawn as small circles on a copy of `img` (a resized
    version of that image)."""
    out = img.copy()
    r = max(1, int(round(img.shape[1] / 320)))
    for u, v in scale_pixels(pixels, full_wh, image_wh(img)):
        cv2.circle(out, (int(round(u)), int(round(v))), r, (40, 255, 40), -1, cv2.LINE_AA)
    return out


def draw_matches(img_s: np.ndarray, px_s: np.ndarray, wh_s: tuple[int, int], img_t: np.ndarray, px_t: np.ndarray,
                 wh_t: tuple[int, int], matches: np.ndarray, max_lines: int, height: int = 240) -> np.ndarray:
    """Two images side by side (each resized to `height`) with matched pairs joined by coloured lines.

    px_s [Ns x 2], px_t [Nt x 2] pixels of the full-resolution images of size wh_s / wh_t (img_* may be
    downscaled versions); matches [M x 2] (source index, target index), all valid. At most `max_lines`
    pairs (evenly spaced) are drawn.
    """
    fs, ft = height / img_s.shape[0], height / img_t.shape[0]
    a = cv2.resize(img_s, (max(1, round(img_s.shape[1] * fs)), height), interpolation=cv2.INTER_AREA)
    b = cv2.resize(img_t, (max(1, round(img_t.shape[1] * ft)), height), interpolation=cv2.INTER_AREA)
    out = np.concatenate([a, b], axis=1)
    m = np.asarray(matches).reshape(-1, 2)
    if len(m) > max_lines:
        m = m[np.linspace(0, len(m) - 1, max_lines).round().astype(int)]
    cols = hue_colors(len(m))
    for (i, j), c in zip(m, cols, strict=True):
        p = scale_pixels(px_s[i], wh_s, image_wh(a))[0]
        q = scale_pixels(px_t[j], wh_t, image_wh(b))[0] + np.array([a.shape[1], 0.0])
        c = tuple(int(x) for x in c)
        p_, q_ = (int(round(p[0])), int(round(p[1]))), (int(round(q[0])), int(round(q[1])))
        cv2.line(out, p_, q_, c, 1, cv2.LINE_AA)
        cv2.circle(out, p_, 2, c, -1, cv2.LINE_AA)
        cv2.circle(out, q_, 2, c, -1, cv2.LINE_AA)
    return out


def legend_html(red_m: float) -> str:
    """HTML legend of the colour scales: view quality, edge RMSE (sequential, loop), rejected edges, query camera,
    coverage cells."""

    def sw(c: tuple[int, int, int]) -> str:
        return (f'<span style="display:inline-block;width:10px;height:10px;margin:0 2px;'
                f'background:rgb{tuple(c)}"></span>')

    seq = "".join(sw(edge_color(Edge("a", "b", None, np.zeros((0, 2)), rmse=r, kind="sequential"), red_m))
                  for r in np.linspace(0, red_m, 5))
    loop = "".join(sw(edge_color(Edge("a", "b", None, np.zeros((0, 2)), rmse=r, kind="loop"), red_m))
                   for r in np.linspace(0, red_m, 5))
    q = "".join(sw(quality_color(x)) for x in np.linspace(1, 0, 5))
    return (f'<div style="font-size:12px;line-height:1.7">'
            f"frustums, quality 1 → 0: {q}<br>"
            f"sequential edges, RMSE 0 → {red_m * 1000:.0f} mm: {seq}<br>"
            f"loop closures, RMSE 0 → {red_m * 1000:.0f} mm: {loop}<br>"
            f"rejected edges: {sw((160, 160, 160))}<br>"
            f"query camera: {sw(QUERY_CAMERA_COLOR)}<br>"
            "coverage, views 0 / 1 / 2 / 3+: " + "".join(sw(_rgb(c)) for c in COUNT_COLORS)
            + f", observed surface only: {sw(SURFACE_SEEN_COLOR)}</div>")
