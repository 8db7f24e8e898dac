"""Image readers: colour (RGB), 16-bit depth, masks, odd depth formats (SUN, NYU) and single frames.

Every reader takes a path (spaces and non-ASCII characters are fine: files are read as bytes and
decoded with cv2.imdecode) and raises InputError(path, one-line reason) on any problem.
Depth is returned as [H x W] float32 metres with 0 = invalid.
"""
from __future__ import annotations

import io
import logging
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gscan.errors import InputError, not_a_file
from gscan.io.camera import DepthCamera, Intrinsics, RGBDFrame, load_intrinsics
from gscan.io.layouts import frame_name

log = logging.getLogger(__name__)

#: Plausible median scene depth (metres); outside it the depth scale is almost surely wrong.
DEPTH_RANGE_M = (0.05, 20.0)

# Images larger than this many pixels are refused from their header, before they are decoded: a small
# compressed file can declare a huge image (a 2.6 MB PNG of 30000 x 30000 decodes to 2.7 GB). The default is
# 4096 x 4096 (16.8 MP): above every RGB-D camera's colour stream (Azure Kinect 4096 x 3072, Zivid 2+
# 2448 x 2048, RealSense D4xx 1920 x 1080), since depth registered to colour has the colour image's size;
# one such frame takes about 120 MB decoded (RGB and float depth). GSCAN_MAX_IMAGE_PIXELS raises it.
DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096
MAX_IMAGE_PIXELS_ENV = "GSCAN_MAX_IMAGE_PIXELS"
_EXR_MAGIC = b"\x76\x2f\x31\x01"
EXR_REASON = ("an OpenEXR (float) image, which gscan does not read; convert the depth to a 16-bit PNG in "
              "millimetres (uint16(round(depth_m * 1000)), 0 where there is no depth) and use depth scale 0.001")

_JPEG_SOI = b"\xff\xd8"
_JPEG_EOI = b"\xff\xd9"
_JPEG_SOS = b"\xff\xda"
_CV2_MAJOR = int(cv2.__version__.split(".")[0])


def read_bytes(path: str | Path) -> np.ndarray:
    """Raw bytes of a file as a [N] uint8 array; InputError when missing, empty or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise not_a_file(path, "file")
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except PermissionError:
        raise InputError(path, "permission denied") from None
    except OSError as e:
        raise InputError(path, f"cannot read file ({e.__class__.__name__}: {e.strerror or e})") from None
    if data.size == 0:
        raise InputError(path, "file is empty")
    return data


def max_image_pixels() -> int:
    """The largest image (width x height) gscan decodes: GSCAN_MAX_IMAGE_PIXELS, else DEFAULT_MAX_IMAGE_PIXELS."""
    raw = os.environ.get(MAX_IMAGE_PIXELS_ENV, "").strip()
    if not raw:
        return DEFAULT_MAX_IMAGE_PIXELS
    try:
        value = int(raw.replace("_", ""))
    except ValueError:
        value = 0
    if value <= 0:
        raise InputError(None, f"{MAX_IMAGE_PIXELS_ENV} must be a positive whole number of pixels, not {raw!r}")
    return value


def image_too_large(width: int, height: int) -> str | None:
    """Why an image of width x height is not decoded (above `max_image_pixels`), or None."""
    limit = max_image_pixels()
    if width * height <= limit:
        return None
    return (f"image is {width}x{height} ({width * height / 1e6:.1f} megapixels), above the limit of {limit} pixels "
            f"({limit / 1e6:.1f} MP); set {MAX_IMAGE_PIXELS_ENV} to read larger images")


def image_size(source: str | Path | bytes, limit: bool = True) -> tuple[int, int, str]:
    """(width, height, PIL mode) of an image file or encoded bytes, read from its header only (nothing is
    decoded). Raises ValueError with the reason for an OpenEXR image, or (with `limit`) an image above
    `max_image_pixels`; PIL's errors for a header it cannot read."""
    from PIL import Image

    head = source[:4] if isinstance(source, bytes) else _head(Path(source))
    if head == _EXR_MAGIC:
        raise ValueError(EXR_REASON)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(source) if isinstance(source, bytes) else source) as im:
                w, h = (int(x) for x in im.size)
                mode = str(im.mode)
    except Image.DecompressionBombError as e:  # PIL's own limit (179 MP): the size is in its message
        m = re.search(r"\((\d+) pixels\)", str(e))
        n = int(m.group(1)) if m else 0
        if not m or n > max_image_pixels():
            raise ValueError(f"image of {n} pixels, above the limit of {max_image_pixels()} pixels; set "
                             f"{MAX_IMAGE_PIXELS_ENV} to read larger images") from None
        raise ValueError(f"image of {n} pixels: too large to read its header") from None
    why = image_too_large(w, h) if limit else None
    if why:
        raise ValueError(why)
    return w, h, mode


def _head(path: Path) -> bytes:
    with open(path, "rb") as f:
        return f.read(4)


def decode_image(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """Decode an image file with cv2 (bytes + imdecode, safe for non-ASCII paths).

    Returns the array as cv2 gives it (BGR order for colour). InputError when the file is not a
    decodable image, is larger than `max_image_pixels` (read from its header, before decoding), or is a
    JPEG without its end-of-image marker (truncated).
    """
    path = Path(path)
    data = read_bytes(path)
    try:
        image_size(data.tobytes())
    except ValueError as e:
        raise InputError(path, str(e)) from None
    except Exception:  # noqa: BLE001 - PIL raises many types for a header it cannot read
        raise InputError(path, "corrupt or unrecognised image (cannot read its header)") from None
    try:
        img = cv2.imdecode(data, flags)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        raise InputError(path, "corrupt or truncated image (cannot be decoded)")
    if _CV2_MAJOR < 5 and bytes(data[:2]) == _JPEG_SOI:
        # OpenCV 4.x decodes a truncated JPEG with a grey tail and only a warning (5.x returns None).
        # Truncated: no end-of-image marker after the last start-of-scan (data after EOI is fine).
        raw = data.tobytes()
        if raw.find(_JPEG_EOI, max(raw.rfind(_JPEG_SOS), 0)) < 0:
            raise InputError(path, "truncated JPEG (no end-of-image marker)")
    return img


def read_image_rgb(path: str | Path) -> np.ndarray:
    """Colour image -> [H x W x 3] uint8 RGB (grey images are expanded, 16-bit reduced to 8-bit)."""
    bgr = decode_image(path, cv2.IMREAD_COLOR)
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise InputError(path, f"unexpected colour image layout {bgr.shape} {bgr.dtype}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_depth_raw(path: str | Path) -> np.ndarray:
    """Depth image -> [H x W] uint16 raw values. Refuses 8-bit, float, signed and multi-channel depth."""
    path = Path(path)
    raw = decode_image(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[:, :, 0]
    if raw.ndim != 2:
        raise InputError(path, f"depth has {raw.shape[2]} channels; depth must be a single-channel 16-bit image")
    if raw.dtype != np.uint16:
        kind = {np.dtype(np.uint8): "8-bit", np.dtype(np.float32): "float", np.dtype(np.float64): "float"}.get(
            raw.dtype, str(raw.dtype))
        raise InputError(path, f"depth is {kind}; depth must be 16-bit unsigned (e.g. millimetres)")
    return raw


def read_depth(path: str | Path, depth_scale: float = 0.001) -> np.ndarray:
    """16-bit depth image -> [H x W] float32 metres (raw * depth_scale; 0 = invalid).

    depth_scale: metres per raw unit (0.001 for millimetres, 1/5000 for TUM, 1e-4 for YCB-Video).
    Raises InputError when the image holds no valid depth at all.
    """
    check_depth_scale(depth_scale, path)
    raw = read_depth_raw(path)
    if not np.any(raw):
        raise InputError(path, "depth image is all zero (no valid depth)")
    depth = raw.astype(np.float32)
    depth *= np.float32(depth_scale)
    return depth


def read_mask(path: str | Path) -> np.ndarray:
    """Mask image -> [H x W] bool: above half the mask's own maximum (so 0/255, 0/1 and 0/65535 masks of any
    type all read; a mask of zeros is empty). Colour masks are converted to grey first."""
    img = decode_image(path, cv2.IMREAD_UNCHANGED)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise InputError(path, f"unexpected mask layout {img.shape}")
    return img > img.max() / 2


def read_sun_depth(path: str | Path, max_depth: float = 7.0) -> np.ndarray:
    """SUN RGB-D depth PNG -> [H x W] float32 metres.

    SUN RGB-D stores millimetres rotated left by 3 bits inside the uint16 (the 3 low bits of the
    file sample are the 3 high bits of the value). Open3D's RGBDImage.create_from_sun_format undoes
    it with d = (d >> 3) | (d << 13), then divides by 1000 and truncates beyond 7 m; this does
    the same (max_depth=None keeps every depth).
    """
    raw = read_depth_raw(path).astype(np.uint32)
    mm = ((raw >> 3) | (raw << 13)) & 0xFFFF
    depth = (mm.astype(np.float64) / 1000.0).astype(np.float32)
    if max_depth is not None:
        depth[depth > max_depth] = 0.0
    if not np.any(depth):
        raise InputError(path, "depth image is all zero (no valid depth)")
    return depth


def read_nyu_depth(path: str | Path, max_depth: float = 7.0) -> np.ndarray:
    """NYU Depth v2 raw depth PGM (P5, 16-bit, big-endian per the PGM spec) -> [H x W] float32 metres.

    The samples are Kinect v1 disparities. Open3D's tutorial parses the PGM big-endian and its
    RGBDImage.create_from_nyu_format then swaps the two bytes of every sample again before applying
    the Kinect disparity model depth_m = 351.3 / (1092.5 - d) (non-positive -> invalid), rounding to
    millimetres and truncating beyond 7 m. This reproduces it exactly (max_depth=None keeps all).
    """
    path = Path(path)
    data = read_bytes(path)
    if bytes(data[:2]) != b"P5":
        raise InputError(path, "not a binary PGM (P5) file; NYU raw depth is a 16-bit PGM")
    raw = read_depth_raw(path)  # cv2 decodes 16-bit PGM big-endian samples to native uint16
    d = raw.byteswap().astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        xx = 351.3 / (1092.5 - d)
    depth = np.where(xx > 0.0, np.floor(xx * 1000.0 + 0.5), 0.0) / 1000.0
    depth = depth.astype(np.float32)
    if max_depth is not None:
        depth[depth > max_depth] = 0.0
    if not np.any(depth):
        raise InputError(path, "depth image is all zero (no valid depth)")
    return depth


MAX_DEPTH_SCALE = 1000.0  # keeps raw * scale far inside float32 (16-bit raw depth)


def check_depth_scale(depth_scale: float, path: str | Path | None) -> None:
    """InputError unless 0 < depth_scale <= MAX_DEPTH_SCALE (metres per raw unit). Scales that are merely
    wrong (10 for 0.001) are left to `check_depth_range`, whose message suggests the right one."""
    if not (isinstance(depth_scale, (int, float, np.floating)) and np.isfinite(depth_scale)
            and 0 < depth_scale <= MAX_DEPTH_SCALE):
        raise InputError(path, f"invalid depth scale {depth_scale!r}: must be a positive number up to "
                         f"{MAX_DEPTH_SCALE:g} (metres per raw unit)")


def check_depth_range(depth: np.ndarray, depth_scale: float, path: str | Path) -> float:
    """Median valid depth (m) of [H x W] metres; InputError when outside DEPTH_RANGE_M (wrong scale)."""
    valid = depth[depth > 0]
    if valid.size == 0:
        raise InputError(path, "depth image is all zero (no valid depth)")
    med = float(np.median(valid))
    lo, hi = DEPTH_RANGE_M
    if not lo <= med <= hi:
        k = -round(float(np.log10(med)))
        hint = f"{depth_scale * 10.0 ** k:g} would put it at {med * 10.0 ** k:.3g} m"
        raise InputError(path, f"depth scale {depth_scale:g} puts the scene at {med:.3g} m "
                         f"(expected {lo:g}-{hi:g} m; {hint})", fix="depth_scale")
    return med


def resolve_intrinsics(intrinsics: Intrinsics | str | Path, width: int, height: int) -> Intrinsics:
    """Intrinsics object or file (cam_K.txt / Open3D JSON) for images of width x height."""
    if isinstance(intrinsics, Intrinsics):
        return intrinsics
    if isinstance(intrinsics, (str, Path)):
        return load_intrinsics(Path(intrinsics), width, height)
    raise InputError(None, f"intrinsics must be an Intrinsics or a file path, got {type(intrinsics).__name__}")


def depth_camera_intrinsics(depth_camera: DepthCamera, shape: tuple[int, ...], depth_path: Path) -> Intrinsics:
    """The depth camera's intrinsics for a depth image of `shape` ([H, W]); InputError naming the depth image when
    the camera is calibrated for another size, or the camera's file when it cannot be of this size."""
    h, w = int(shape[0]), int(shape[1])
    try:
        return depth_camera.for_size(w, h)
    except ValueError as e:
        raise InputError(depth_path if depth_camera.size is not None else depth_camera.source or depth_path,
                         str(e)) from None


DEPTH_FORMATS = ("uint16", "sun", "nyu")


def load_frame(color_path: str | Path, depth_path: str | Path, intrinsics: Intrinsics | str | Path,
               depth_scale: float = 0.001, mask_path: str | Path | None = None, name: str | None = None,
               depth_format: str = "uint16", check_range: bool = True,
               depth_camera: DepthCamera | None = None) -> RGBDFrame:
    """Load one RGB-D frame.

    color_path: any image cv2 decodes (returned RGB). depth_path: 16-bit depth with `depth_scale`
    metres per raw unit (depth_format="uint16"), or a SUN RGB-D PNG ("sun") / NYU raw PGM ("nyu"),
    whose own conversions fix the scale (depth_scale is then ignored). intrinsics: an Intrinsics or a
    cam_K.txt / Open3D JSON file (cam_K.txt takes the colour image's size). mask_path: optional mask
    (> 127 = object) of the same size. name defaults to the colour file stem.
    With check_range, a median depth outside 0.05-20 m is refused as a wrong depth scale.
    depth_camera: the depth images' own camera when they are not registered to the colour images; the depth
    is then reprojected into the colour camera (its size must be the depth camera's, when it has one).
    """
    color_path, depth_path = Path(color_path), Path(depth_path)
    if depth_format not in DEPTH_FORMATS:
        raise ValueError(f"depth_format must be one of {DEPTH_FORMATS}, got {depth_format!r}")
    color = read_image_rgb(color_path)
    if depth_format == "sun":
        depth, depth_scale = read_sun_depth(depth_path), 0.001
    elif depth_format == "nyu":
        depth, depth_scale = read_nyu_depth(depth_path), 0.001
    else:
        depth = read_depth(depth_path, depth_scale)
    h, w = color.shape[:2]
    if depth_camera is None and depth.shape != (h, w):
        raise InputError(depth_path, f"depth is {depth.shape[1]}x{depth.shape[0]} but colour image "
                         f"{color_path.name} is {w}x{h}")
    if depth_camera is not None:
        depth_camera_intrinsics(depth_camera, depth.shape, depth_path)  # before the work: InputError naming a file
    if check_range:
        check_depth_range(depth, depth_scale, depth_path)
    intr = resolve_intrinsics(intrinsics, w, h)
    if (intr.width, intr.height) != (w, h):
        src = intrinsics if isinstance(intrinsics, (str, Path)) else color_path
        raise InputError(src, f"intrinsics are for {intr.width}x{intr.height} images but {color_path.name} is {w}x{h}")
    if depth_camera is not None:
        from gscan.io.align import align_depth_to_color  # numba: loaded only for unregistered depth

        depth = align_depth_to_color(depth, depth_camera, intr)
    mask = None
    if mask_path is not None:
        mask_path = Path(mask_path)
        mask = read_mask(mask_path)
        if mask.shape != (h, w):
            raise InputError(mask_path, f"mask is {mask.shape[1]}x{mask.shape[0]} but the frame is {w}x{h}")
    return RGBDFrame(name=name if name is not None else frame_name(color_path), color=color, depth=depth,
                     intrinsics=intr, mask=mask, source=color_path)


@dataclass
class YcbvMeta:
    """Contents of a YCB-Video `-meta.mat`.

    K: [3 x 3] calibration; depth_scale: metres per raw depth unit (1 / factor_depth);
    poses: class index (cls_indexes, 1-based YCB id order) -> [4 x 4] T_cam_obj (metres).
    """

    K: np.ndarray
    depth_scale: float
    poses: dict[int, np.ndarray]

    def __iter__(self):
        """Unpack as (K, depth_scale, poses)."""
        return iter((self.K, self.depth_scale, self.poses))


def read_ycbv_meta(path: str | Path) -> YcbvMeta:
    """Read a YCB-Video `NNNNNN-meta.mat` (scipy.io.loadmat). Iterable as (K, depth_scale, poses)."""
    import scipy.io

    path = Path(path)
    read_bytes(path)  # existence / permission / empty checks with a clear message
    try:
        m = scipy.io.loadmat(str(path))
        K = np.asarray(m["intrinsic_matrix"], dtype=np.float64).reshape(3, 3)
        factor = float(np.asarray(m["factor_depth"]).ravel()[0])
        cls = np.asarray(m["cls_indexes"]).ravel().astype(int)
        P = np.asarray(m["poses"], dtype=np.float64)
    except Exception as e:  # noqa: BLE001 - loadmat raises many types on garbage (MatReadError, ValueError, ...)
        raise InputError(path, f"not a YCB-Video meta file ({e.__class__.__name__}: {e})") from None
    if P.ndim == 2:
        P = P[:, :, None]
    if P.shape[:2] != (3, 4) or P.shape[2] != len(cls):
        raise InputError(path, f"poses have shape {P.shape} for {len(cls)} objects; expected 3x4xK")
    if not (np.isfinite(factor) and factor > 0) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"invalid factor_depth {factor} or intrinsic_matrix")
    poses: dict[int, np.ndarray] = {}
    for k, c in enumerate(cls):
        T = np.eye(4)
        T[:3, :4] = P[:, :, k]
        poses[int(c)] = T
    return YcbvMeta(K=K, depth_scale=1.0 / factor, poses=poses)

