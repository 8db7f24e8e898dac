"""Decoding and checking the parts of an estimation request (`gscan serve`): every problem is a
`RequestError` naming the form field, never an exception from deeper down.

Image sizes are read from the headers (PIL, without decoding) and checked against `max_pixels` before any
pixel is decoded, so a small file that decodes to gigabytes is refused for the price of its header.

Depth from a separate camera (not registered to colour): a `gscan.io.camera.DepthCamera` (the request's
`depth_intrinsics` and `depth_to_color` fields, or the service's own) makes `decode_frame` reproject the depth
into the colour camera (`gscan.io.align.align_depth_to_color`, as `gscan estimate --depth-intrinsics` does); the
depth image then has the depth camera's size, which may differ from the colour image's.
"""
from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.io.camera import DepthCamera, Intrinsics, RGBDFrame, implausible_intrinsics

MAX_PIXELS = 4096 * 4096  # largest image a request may hold (pixels, per image)
DEPTH_RANGE_M = (0.05, 20.0)  # plausible median depth: outside it the depth scale is wrong


class RequestError(Exception):
    """A bad request: HTTP `status` with a one-line `detail` naming the field."""

    def __init__(self, field: str, reason: str, status: int = 400):
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason
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


def _numbers(text: str) -> list[float]:
    """The numbers of a matrix written as text: whitespace, commas or brackets between them."""
    return [float(x) for x in text.replace(",", " ").replace("[", " ").replace("]", " ").split()]


def parse_K(text: str, field: str = "intrinsics") -> np.ndarray:
    """[3 x 3] pinhole calibration from the 9 numbers of a cam_K.txt ([[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
    whitespace or commas)."""
    try:
        K = np.array(_numbers(text), dtype=np.float64).reshape(3, 3)
    except (ValueError, OverflowError):
        raise RequestError(field, "expected the 9 numbers of a 3x3 matrix (as cam_K.txt holds them)") from None
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 2] < 0 or K[1, 2] < 0:
        raise RequestError(field, f"invalid values fx={K[0, 0]:g} fy={K[1, 1]:g} cx={K[0, 2]:g} cy={K[1, 2]:g}")
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or K[1, 0] != 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise RequestError(field, "not a pinhole calibration matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    return K


def sized_intrinsics(K: np.ndarray, width: int, height: int, field: str = "intrinsics") -> Intrinsics:
    """Intrinsics of [3 x 3] K for images of width x height; RequestError when K cannot be of that size."""
    why = implausible_intrinsics(K, width, height)
    if why:
        raise RequestError(field, why)
    return Intrinsics.from_matrix(K, width, height)


def parse_intrinsics(text: str, width: int, height: int, field: str = "intrinsics") -> Intrinsics:
    """The 3x3 numbers of a cam_K.txt (`parse_K`) for images of width x height."""
    return sized_intrinsics(parse_K(text, field), width, height, field)


def parse_pose(text: str, field: str) -> np.ndarray:
    """[4 x 4] rigid transform (metres) from text: 16 numbers (or 12, the last row 0 0 0 1 left out) as a pose
    .txt holds them, or JSON `{"T": [[4x4]]}` / a bare 4x4 list, as a pose .json holds it."""
    from gscan.io.poses import check_rigid

    expected = 'expected a 4x4 matrix: 16 numbers (rows of 4), or JSON {"T": [[4x4]]}'
    stripped = text.strip()
    try:
        if stripped.startswith("{"):
            d = json.loads(stripped)
            T = np.asarray(d["T"] if isinstance(d, dict) else d, dtype=np.float64)
        else:
            T = np.array(_numbers(stripped), dtype=np.float64)
            T = T.reshape(-1, 4) if T.size in (12, 16) else T
    except (ValueError, TypeError, KeyError, OverflowError, RecursionError):
        raise RequestError(field, expected) from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise RequestError(field, f"{expected}, got {T.size} {'numbers' if T.ndim == 1 else 'values'}"
                           if T.shape != (4, 4) else "a matrix of finite numbers is needed")
    try:
        return check_rigid(T, Path(field))
    except InputError as e:
        raise RequestError(field, e.reason) from None


def depth_camera_fields(depth_intrinsics: str | None, depth_to_color: str | None) -> DepthCamera | None:
    """The depth camera a request names (None when it names none): `depth_intrinsics` (3x3 text, fitting depth
    images of any size) and `depth_to_color` (T_color_depth; default the colour camera's own centre and axes).
    RequestError naming the field: malformed values, or `depth_to_color` without `depth_intrinsics` (422)."""
    if depth_intrinsics is None or not depth_intrinsics.strip():
        if depth_to_color is not None and depth_to_color.strip():
            raise RequestError("depth_to_color", "given without depth_intrinsics (the depth camera's 3x3 "
                                                 "calibration, as cam_K.txt holds it)", 422)
        return None
    K = parse_K(depth_intrinsics, "depth_intrinsics")
    T = None if depth_to_color is None or not depth_to_color.strip() else parse_pose(depth_to_color, "depth_to_color")
    return DepthCamera(K, T)


def depth_camera_intrinsics(depth_camera: DepthCamera, width: int, height: int, served: bool = False) -> Intrinsics:
    """The depth camera's intrinsics for a depth image of width x height; RequestError when it cannot be of that
    size. `served`: the camera is the service's own (given when it started), whose misfits are the request's
    `depth` field's; a request's own misfits name its `depth_intrinsics` field."""
    if served and depth_camera.size is not None and depth_camera.size != (width, height):
        raise RequestError("depth", f"depth is {width}x{height} but the service's depth camera is calibrated "
                                    f"for {depth_camera.size[0]}x{depth_camera.size[1]} images")
    try:
        return depth_camera.for_size(width, height)
    except ValueError as e:
        if served:
            raise RequestError("depth", f"the service's depth camera does not fit this {width}x{height} depth "
                                        f"image: {e}") from None
        raise RequestError("depth" if depth_camera.size is not None else "depth_intrinsics", str(e)) from None


def nothing_lands(served: bool) -> RequestError:
    """The error for a depth image none of whose pixels lands in the colour image (`served`: through the
    service's own depth camera)."""
    if served:
        return RequestError("depth", "no pixel lands in the colour image through the service's depth camera")
    return RequestError("depth_to_color", "no depth pixel lands in the colour image (is it T_color_depth, the "
                                          "depth camera's pose in the colour camera, in metres?)")


def check_depth_scale(depth_scale: float, field: str = "depth_scale") -> None:
    if not (np.isfinite(depth_scale) and 0 < depth_scale <= 1000.0):
        raise RequestError(field, f"must be a positive number up to 1000 (metres per raw unit), not {depth_scale!r}")


def decode_frame(color: bytes, depth: bytes, intrinsics: str, depth_scale: float, mask: bytes | None = None,
                 name: str = "request", max_pixels: int = MAX_PIXELS, depth_camera: DepthCamera | None = None,
                 served: bool = False) -> RGBDFrame:
    """One RGB-D frame from a request's parts (sizes checked against each other; a median depth outside
    DEPTH_RANGE_M is refused as a wrong depth scale). With `depth_camera` the depth is that camera's image
    (of its own size), reprojected into the colour camera; `served`: it is the service's own, not the request's
    (`depth_camera_intrinsics`)."""
    check_depth_scale(depth_scale)
    rgb = decode_color(color, "color", max_pixels)
    h, w = rgb.shape[:2]
    dh = image_header("depth", depth, ("PNG",), max_pixels)  # before decoding it
    if depth_camera is None and (dh.width, dh.height) != (w, h):
        raise RequestError("depth", f"depth is {dh.width}x{dh.height} but the colour image is {w}x{h}")
    if depth_camera is not None:  # before decoding the depth
        depth_camera_intrinsics(depth_camera, dh.width, dh.height, served)
    d = decode_depth(depth, depth_scale, "depth", max_pixels)
    med = float(np.median(d[d > 0]))
    lo, hi = DEPTH_RANGE_M
    if not lo <= med <= hi:
        raise RequestError("depth_scale", f"{depth_scale:g} puts the scene at {med:.3g} m (expected {lo:g}-{hi:g} m)")
    K = parse_intrinsics(intrinsics, w, h)
    if depth_camera is not None:
        from gscan.io.align import align_depth_to_color  # numba: loaded only for unregistered depth

        d = align_depth_to_color(d, depth_camera, K)
        if not d.any():
            raise nothing_lands(served)
    m = None
    if mask is not None and len(mask):
        mh = image_header("mask", mask, ("PNG", "JPEG"), max_pixels)
        if (mh.width, mh.height) != (w, h):
            raise RequestError("mask", f"mask is {mh.width}x{mh.height} but the colour image is {w}x{h}")
        m = decode_mask(mask, "mask", max_pixels)
    return RGBDFrame(name, rgb, d, K, mask=m)
