"""Procedural textures: printed product boxes and table surfaces (wood, fabric, newspaper, plain).

Every texture is a deterministic function of its seed and size. The prints and the wood, fabric and
newspaper tables are rich in non-repeating structure so that SIFT finds many distinctive keypoints; the
plain table (a lab bench's laminate) is nearly featureless, so that a whole frame's keypoints are the
object's.
"""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_PLAIN, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
         cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_COMPLEX_SMALL, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX,
         cv2.FONT_HERSHEY_SCRIPT_COMPLEX)
TABLE_KINDS = ("newspaper", "wood", "fabric", "plain")
_CONSONANTS = "BCDFGHJKLMNPRSTVWXZ"
_VOWELS = "AEIOUY"


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cell: float, octaves: int = 4) -> np.ndarray:
    """[H x W] float32 fractal value noise in about [-1, 1]; `cell` is the coarsest feature size in pixels."""
    h, w = shape
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for _ in range(octaves):
        gh, gw = max(2, int(np.ceil(h / cell)) + 1), max(2, int(np.ceil(w / cell)) + 1)
        grid = rng.uniform(-1, 1, (gh, gw)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= 0.5
        cell = max(cell / 2, 1.0)
    return out / total


def random_word(rng: np.random.Generator, n_min: int = 3, n_max: int = 9) -> str:
    n = int(rng.integers(n_min, n_max + 1))
    return "".join(_CONSONANTS[rng.integers(len(_CONSONANTS))] if (i % 2 == 0) != (rng.random() < 0.2)
                   else _VOWELS[rng.integers(len(_VOWELS))] for i in range(n))


def _color(rng: np.random.Generator, dark: bool | None = None,
           palette: np.ndarray | None = None) -> tuple[int, int, int]:
    if palette is not None and dark is None:  # brand colour with slight jitter
        c = np.clip(palette[rng.integers(len(palette))] + rng.integers(-12, 13, 3), 0, 255)
    elif dark is None:
        c = rng.integers(0, 256, 3)
    else:
        lo, hi = (0, 110) if dark else (150, 256)
        c = rng.integers(lo, hi, 3)
    return (int(c[0]), int(c[1]), int(c[2]))


def _put_text(img: np.ndarray, rng: np.random.Generator, text: str, org: tuple[int, int], height_px: float,
              color: tuple[int, int, int], font: int | None = None) -> None:
    font = FONTS[rng.integers(len(FONTS))] if font is None else font
    if rng.random() < 0.25:
        font |= cv2.FONT_ITALIC
    (_, th), _ = cv2.getTextSize("H", font, 1.0, 1)
    scale = height_px / max(th, 1)
    thick = max(1, int(round(scale * rng.uniform(0.8, 2.5))))
    cv2.putText(img, text, org, font, scale, color, thick, cv2.LINE_AA)


def _star(center: np.ndarray, r_out: float, r_in: float, n: int, phase: float) -> np.ndarray:
    ang = phase + np.arange(2 * n) * np.pi / n
    r = np.where(np.arange(2 * n) % 2 == 0, r_out, r_in)
    return np.round(center + np.stack([np.cos(ang) * r, np.sin(ang) * r], 1)).astype(np.int32)


def _logo(img: np.ndarray, rng: np.random.Generator, c: np.ndarray, r: float,
          palette: np.ndarray | None = None) -> None:
    kind = rng.integers(4)
    col, col2 = _color(rng, palette=palette), _color(rng, palette=palette)
    if kind == 0:  # concentric rings, partly filled
        for k in range(int(rng.integers(2, 5))):
            rr = int(r * (1 - 0.22 * k))
            cv2.circle(img, tuple(int(x) for x in c), rr, col if k % 2 == 0 else col2, -1 if k == 0 else
                       int(rng.integers(2, 6)), cv2.LINE_AA)
    elif kind == 1:  # star burst
        pts = _star(c, r, r * rng.uniform(0.35, 0.7), int(rng.integers(5, 13)), rng.uniform(0, np.pi))
        cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
        cv2.polylines(img, [pts], True, col2, 2, cv2.LINE_AA)
    elif kind == 2:  # polygon with an inner letter
        n = int(rng.integers(3, 8))
        ang = rng.uniform(0, 2 * np.pi) + np.sort(rng.uniform(0, 2 * np.pi, n))
        pts = np.round(c + np.stack([np.cos(ang), np.sin(ang)], 1) * r * rng.uniform(0.6, 1.0, (n, 1))).astype(np.int32)
        cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
        _put_text(img, rng, random_word(rng, 1, 2), (int(c[0] - r / 2), int(c[1] + r / 4)), r * 0.6, col2)
    else:  # ellipse swoosh
        cv2.ellipse(img, tuple(int(x) for x in c), (int(r), int(r * rng.uniform(0.3, 0.7))), rng.uniform(0, 180),
                    rng.uniform(0, 120), rng.uniform(200, 360), col, int(rng.integers(3, 10)), cv2.LINE_AA)
        cv2.circle(img, tuple(int(x) for x in c), int(r * 0.25), col2, -1, cv2.LINE_AA)


def _barcode(img: np.ndarray, rng: np.random.Generator, x: int, y: int, w: int, h: int) -> None:
    cv2.rectangle(img, (x - 4, y - 4), (x + w + 4, y + h + 16), (255, 255, 255), -1)
    pos = x
    while pos < x + w:
        bw = int(rng.integers(1, 5))
        if rng.random() < 0.5:
            cv2.rectangle(img, (pos, y), (min(pos + bw - 1, x + w), y + h), (0, 0, 0), -1)
        pos += bw
    digits = "".join(str(d) for d in rng.integers(0, 10, 12))
    cv2.putText(img, digits, (x, y + h + 13), cv2.FONT_HERSHEY_PLAIN, max(0.6, w / 130), (0, 0, 0), 1, cv2.LINE_AA)


def _stripes(img: np.ndarray, rng: np.random.Generator, palette: np.ndarray | None = None) -> None:
    h, w = img.shape[:2]
    y = int(rng.integers(0, h))
    band = int(rng.integers(h // 30 + 2, h // 8 + 3))
    pos = 0
    while pos < w:  # irregular stripe widths and colours: no period
        sw = int(rng.integers(4, 40))
        cv2.rectangle(img, (pos, y), (pos + sw, y + band), _color(rng, palette=palette), -1)
        pos += sw
    if rng.random() < 0.5:
        img[y:y + band] = np.ascontiguousarray(img[y:y + band, ::-1])


def procedural_box_texture(seed: int = 0, size: tuple[int, int] = (1024, 1536)) -> np.ndarray:
    """[H x W x 3] uint8 RGB printed-packaging texture (size = (H, W)): gradients, text in several
    fonts, sizes and colours, logos, irregular stripe bands, barcodes and dot patches; not repetitive."""
    rng = np.random.default_rng([seed, 0xB0C5])
    h, w = size
    palette = np.concatenate([rng.integers(0, 256, (4, 3)), [[250, 250, 245], [20, 20, 25]]]).astype(np.int64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    c0 = np.array(_color(rng, dark=False), np.float32)
    c1 = np.array(_color(rng, palette=palette), np.float32)
    ang = rng.uniform(0, 2 * np.pi)
    t = ((xx * np.cos(ang) + yy * np.sin(ang)) / max(h, w)) % 1.0
    img = c0 * (1 - t[..., None]) + c1 * t[..., None]
    img += 25 * smooth_noise(rng, (h, w), max(h, w) / 6)[..., None]
    img = np.clip(img, 0, 255).astype(np.uint8)
    area = h * w / (512 * 512)
    for _ in range(int(2.5 * area)):  # colour panels, some with rounded corners
        x0, y0 = int(rng.integers(0, w)), int(rng.integers(0, h))
        x1, y1 = x0 + int(rng.integers(60, w // 3)), y0 + int(rng.integers(40, h // 4))
        col = _color(rng, palette=palette)
        cv2.rectangle(img, (x0, y0), (x1, y1), col, -1)
        if rng.random() < 0.5:
            cv2.rectangle(img, (x0 + 6, y0 + 6), (x1 - 6, y1 - 6), _color(rng, palette=palette), 2, cv2.LINE_AA)
    for _ in range(max(1, int(0.7 * area))):
        _stripes(img, rng, palette)
    for _ in range(int(4 * area)):
        _logo(img, rng, rng.uniform([0, 0], [w, h]), rng.uniform(18, 70), palette)
    for _ in range(int(2.5 * area)):  # dot patches with jittered positions (not periodic)
        x0, y0, n = int(rng.integers(0, w)), int(rng.integers(0, h)), int(rng.integers(15, 45))
        pts = np.array([x0, y0]) + rng.uniform(0, 90, (n, 2))
        col = _color(rng, palette=palette)
        for p, r in zip(pts.astype(int), rng.integers(2, 7, n), strict=True):
            cv2.circle(img, (int(p[0]), int(p[1])), int(r), col, -1, cv2.LINE_AA)
    for _ in range(int(3 * area)):  # titles
        _put_text(img, rng, random_word(rng, 4, 9), (int(rng.integers(-20, w - 100)), int(rng.integers(40, h))),
                  rng.uniform(28, 64), _color(rng, palette=palette))
    for _ in range(int(30 * area)):  # small print
        words = " ".join(random_word(rng, 2, 7) for _ in range(int(rng.integers(1, 5))))
        _put_text(img, rng, words, (int(rng.integers(-20, w - 60)), int(rng.integers(10, h))),
                  rng.uniform(7, 18), _color(rng, dark=bool(rng.random() < 0.7)), FONTS[rng.integers(6)])
    for _ in range(max(1, int(1.0 * area))):
        bw, bh = int(rng.integers(90, 170)), int(rng.integers(40, 70))
        _barcode(img, rng, int(rng.integers(5, w - bw - 10)), int(rng.integers(5, h - bh - 25)), bw, bh)
    return img


def _newspaper(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    paper = 232 + 8 * smooth_noise(rng, (h, w), 200)[..., None] + np.array([0, -2, -10], np.float32)
    img = np.clip(paper, 0, 255).astype(np.uint8)
    y = 0
    while y < h:  # pages of columns with headlines, text and photos
        ncol = int(rng.integers(3, 7))
        block_h = int(rng.integers(h // 5, h // 2))
        colw = w / ncol
        ink = (int(rng.integers(10, 50)),) * 3
        _put_text(img, rng, " ".join(random_word(rng, 3, 9) for _ in range(int(rng.integers(2, 5)))),
                  (int(rng.integers(0, 30)), y + 40), rng.uniform(22, 40), ink, cv2.FONT_HERSHEY_TRIPLEX)
        for c in range(ncol):
            x0, yy = int(c * colw + 8), y + 60
            if rng.random() < 0.35:  # halftone-like photo
                ph = int(rng.integers(60, 180))
                photo = 128 + 110 * smooth_noise(rng, (ph, int(colw - 16)), rng.uniform(15, 60))
                img[yy:yy + ph, x0:x0 + int(colw - 16)] = np.clip(photo, 0, 255).astype(np.uint8)[
                    : max(0, min(ph, h - yy)), : max(0, min(int(colw - 16), w - x0)), None]
                yy += ph + 10
            while yy < y + block_h:
                line = " ".join(random_word(rng, 1, 8) for _ in range(int(colw // 45) + 1))
                cv2.putText(img, line, (x0, yy), cv2.FONT_HERSHEY_PLAIN, rng.uniform(0.7, 0.95), ink, 1, cv2.LINE_AA)
                yy += int(rng.integers(12, 15))
            cv2.line(img, (int((c + 1) * colw), y + 50), (int((c + 1) * colw), y + block_h), ink, 1)
        y += block_h + 10
        cv2.line(img, (0, y - 5), (w, y - 5), ink, 2)
    return img


def _wood(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.zeros((h, w, 3), np.float32)
    planks = int(rng.integers(4, 7))
    edges = np.linspace(0, h, planks + 1).astype(int)
    for p in range(planks):  # each plank: its own grain phase, tone and warp
        y0, y1 = edges[p], edges[p + 1]
        ph = y1 - y0
        py, px = yy[y0:y1], xx[y0:y1]
        warp = 40 * smooth_noise(rng, (ph, w), w / 2, 3) + 6 * smooth_noise(rng, (ph, w), 40, 2)
        rings = py + warp + 0.02 * px * rng.uniform(-1, 1)
        for _ in range(int(rng.integers(0, 3))):  # knots: rings bend around them
            kx, ky, kr = rng.uniform(0, w), rng.uniform(y0, y1), rng.uniform(8, 22)
            d = np.sqrt((px - kx) ** 2 / 6 + (py - ky) ** 2)
            rings += 2.5 * kr * np.exp(-d / (1.5 * kr)) * np.sign(py - ky)
        period = rng.uniform(9, 16)
        lines = (0.5 + 0.5 * np.cos(rings * 2 * np.pi / period)) ** 6  # thin dark late-wood lines
        streaks = cv2.resize(rng.uniform(-1, 1, (ph, max(2, w // 120))).astype(np.float32), (w, ph),
                             interpolation=cv2.INTER_LINEAR)
        tone = rng.uniform(-0.12, 0.12)
        t = np.clip(0.25 + tone + 0.45 * lines + 0.12 * streaks + 0.15 * smooth_noise(rng, (ph, w), 90, 3), 0, 1)
        light, dark = np.array([205, 160, 110], np.float32), np.array([105, 62, 32], np.float32)
        img[y0:y1] = light * (1 - t[..., None]) + dark * t[..., None]
        img[max(0, y0 - 1):y0 + 1] *= 0.5  # seam
    return np.clip(img, 0, 255).astype(np.uint8)


def _fabric(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    base = np.array(_color(rng), np.float32)
    img = np.broadcast_to(base, (h, w, 3)).copy()
    for axis in (0, 1):  # irregular plaid bands
        pos, n = 0, (w if axis == 1 else h)
        while pos < n:
            bw = int(rng.integers(6, 80))
            col, alpha = np.array(_color(rng), np.float32), rng.uniform(0.2, 0.6)
            sl = (slice(None), slice(pos, pos + bw)) if axis == 1 else (slice(pos, pos + bw), slice(None))
            img[sl] = img[sl] * (1 - alpha) + col * alpha
            pos += bw + int(rng.integers(5, 120))
    yy, xx = np.mgrid[0:h, 0:w]
    weave = np.where((xx // 2 + yy // 2) % 2 == 0, 1.06, 0.94).astype(np.float32)
    thread = 1 + 0.08 * cv2.resize(rng.uniform(-1, 1, (h, max(2, w // 25))).astype(np.float32), (w, h))
    img *= (weave * thread)[..., None]
    img *= (1 + 0.25 * smooth_noise(rng, (h, w), 120))[..., None]  # stains and wear
    out = np.clip(img, 0, 255).astype(np.uint8)
    for _ in range(int(h * w / 80000)):  # embroidered motifs
        _logo(out, rng, rng.uniform([0, 0], [w, h]), rng.uniform(10, 30))
    return out


def _plain(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    base = np.array([196, 196, 190], np.float32) * rng.uniform(0.9, 1.05)  # grey-beige laminate
    mottle = 1 + 0.03 * smooth_noise(rng, (h, w), 150, 3) + 0.01 * rng.standard_normal((h, w)).astype(np.float32)
    return np.clip(base * mottle[..., None], 0, 255).astype(np.uint8)


@lru_cache(maxsize=8)
def _table_texture_cached(kind: str, seed: int, size: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 0x7AB1E, TABLE_KINDS.index(kind)])
    img = {"newspaper": _newspaper, "wood": _wood, "fabric": _fabric, "plain": _plain}[kind](rng, size, size)
    img.setflags(write=False)
    return img


def table_texture(kind: str = "newspaper", seed: int = 0, size: int = 2048) -> np.ndarray:
    """[size x size x 3] uint8 RGB table-top texture of `kind` (TABLE_KINDS); read-only, cached."""
    if kind not in TABLE_KINDS:
        raise ValueError(f"unknown table texture {kind!r}; choose one of {TABLE_KINDS}")
    return _table_texture_cached(kind, int(seed), int(size))
