"""Decoding and checking the parts of an estimation request (`gscan serve`): every problem is a
`RequestError` naming the form field, never an exception from deeper down.

Image sizes are read from the headers (PIL, without decoding) and checked against `max_pixels` before any
pixel is decoded, so a small file that decodes to gigabytes is refused for the price of its header.
"""
from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from gscan.io.camera import Intrinsics, RGBDFrame, implausible_intrinsics

MAX_PIXELS = 4096 * 4096  # largest image a request may hold (pixels, per image)
DEPTH_RANGE_M = (0.05, 20.0)  # plausible median depth: outside it the depth scale is wrong


class RequestError(Exception):
    """A bad request: HTTP `status` with a one-line `detail` naming the field."""

    def __init__(self, field: str, reason: str, status: int = 400):
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.status = status

    @property
    def detail(self) -> str:
        return str(self)


@dataclass(frozen=True)
class ImageHeader:
    width: int
    height: int
    format: str  # PIL format name ("PNG", "JPEG", ...)
    mode: str  # PIL mode ("RGB", "L", "I;16", ...)


def image_header(field: str, data: bytes, formats: tuple[str, ...], max_pixels: int = MAX_PIXELS) -> ImageHeader:
    """The image's size and kind from its header only; RequestError for an empty, unreadable or unexpected
    file, or one larger than max_pixels (413)."""
    from PIL import Image

    if not data:
        raise RequestError(field, "empty file")
    try:
        with Image.open(io.BytesIO(data)) as im:
            h = ImageHeader(int(im.size[0]), int(im.size[1]), str(im.format), str(im.mode))
    except Image.DecompressionBombError:
        raise RequestError(field, f"image is larger than the {max_pixels} pixels allowed", 413) from None
    except Exception as e:  # noqa: BLE001 - PIL raises many types on garbage (UnidentifiedImageError, SyntaxError...)
        raise RequestError(field, f"not a readable image ({e.__class__.__name__})") from None
    if h.format not in formats:
        raise RequestError(field, f"{h.format} image; expected {' or '.join(formats)}")
    if h.width <= 0 or h.height <= 0:
        raise RequestError(field, f"invalid image size {h.width}x{h.height}")
    if h.width * h.height > max_pixels:
        raise RequestError(field, f"image is {h.width}x{h.height}, larger than the {max_pixels} pixels allowed", 413)
    return h


def _decode(field: str, data: bytes, flags: int, header: ImageHeader) -> np.ndarray:
    import cv2

    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        raise RequestError(field, "corrupt or truncated image (cannot be decoded)")
    if img.shape[:2] != (header.height, header.width):  # a header that lies about the pixels
        raise RequestError(field, f"decodes to {img.shape[1]}x{img.shape[0]} but its header says "
                                  f"{header.width}x{header.height}")
    return img


def decode_color(data: bytes, field: str = "color", max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """PNG or JPEG bytes -> [H x W x 3] uint8 RGB."""
    import cv2

    h = image_header(field, data, ("PNG", "JPEG"), max_pixels)
    bgr = _decode(field, data, cv2.IMREAD_COLOR, h)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def decode_depth(data: bytes, depth_scale: float, field: str = "depth", max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """16-bit single-channel PNG bytes -> [H x W] float32 metres (raw * depth_scale, 0 = invalid)."""
    import cv2

    h = image_header(field, data, ("PNG",), max_pixels)
    if not (h.mode.startswith("I;16") or h.mode == "I"):
        raise RequestError(field, f"PNG of mode {h.mode}; depth must be a single-channel 16-bit PNG")
    raw = _decode(field, data, cv2.IMREAD_UNCHANGED, h)
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[:, :, 0]
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise RequestError(field, f"decodes to {raw.dtype} with shape {raw.shape}; depth must be a single-channel "
                                  "16-bit PNG")
    if not raw.any():
        raise RequestError(field, "all zero (no valid depth)")
    depth = raw.astype(np.float32)
    depth *= np.float32(depth_scale)
    return depth


def decode_mask(data: bytes, field: str = "mask", max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """PNG or JPEG bytes -> [H x W] bool (above half the image's own maximum; colour masks greyed first)."""
    import cv2

    h = image_header(field, data, ("PNG", "JPEG"), max_pixels)
    img = _decode(field, data, cv2.IMREAD_UNCHANGED, h)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise RequestError(field, f"unexpected mask layout {img.shape}")
    return img > img.max() / 2


def parse_intrinsics(text: str, width: int, height: int, field: str = "intrinsics") -> Intrinsics:
    """The 3x3 numbers of a cam_K.txt ([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], whitespace or commas) for
    images of width x height."""
    try:
        rows = [[float(x) for x in line.replace(",", " ").replace("[", " ").replace("]", " ").split()]
                for line in text.splitlines() if line.strip()]
        K = np.array([x for row in rows for x in row], dtype=np.float64).reshape(3, 3)
    except (ValueError, OverflowError):
        raise RequestError(field, "expected the 9 numbers of a 3x3 matrix (as cam_K.txt holds them)") from None
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 2] < 0 or K[1, 2] < 0:
        raise RequestError(field, f"invalid values fx={K[0, 0]:g} fy={K[1, 1]:g} cx={K[0, 2]:g} cy={K[1, 2]:g}")
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or K[1, 0] != 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise RequestError(field, "not a pinhole calibration matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    why = implausible_intrinsics(K, width, height)
    if why:
        raise RequestError(field, why)
    return Intrinsics.from_matrix(K, width, height)


def check_depth_scale(depth_scale: float, field: str = "depth_scale") -> None:
    if not (np.isfinite(depth_scale) and 0 < depth_scale <= 1000.0):
        raise RequestError(field, f"must be a positive number up to 1000 (metres per raw unit), not {depth_scale!r}")


def decode_frame(color: bytes, depth: bytes, intrinsics: str, depth_scale: float, mask: bytes | None = None,
                 name: str = "request", max_pixels: int = MAX_PIXELS) -> RGBDFrame:
    """One RGB-D frame from a request's parts (sizes checked against each other; a median depth outside
    DEPTH_RANGE_M is refused as a wrong depth scale)."""
    check_depth_scale(depth_scale)
    rgb = decode_color(color, "color", max_pixels)
    h, w = rgb.shape[:2]
    dh = image_header("depth", depth, ("PNG",), max_pixels)  # before decoding it
    if (dh.width, dh.height) != (w, h):
        raise RequestError("depth", f"depth is {dh.width}x{dh.height} but the colour image is {w}x{h}")
    d = decode_depth(depth, depth_scale, "depth", max_pixels)
    med = float(np.median(d[d > 0]))
    lo, hi = DEPTH_RANGE_M
    if not lo <= med <= hi:
        raise RequestError("depth_scale", f"{depth_scale:g} puts the scene at {med:.3g} m (expected {lo:g}-{hi:g} m)")
    K = parse_intrinsics(intrinsics, w, h)
    m = None
    if mask is not None and len(mask):
        mh = image_header("mask", mask, ("PNG", "JPEG"), max_pixels)
        if (mh.width, mh.height) != (w, h):
            raise RequestError("mask", f"mask is {mh.width}x{mh.height} but the colour image is {w}x{h}")
        m = decode_mask(mask, "mask", max_pixels)
    return RGBDFrame(name, rgb, d, K, mask=m)
