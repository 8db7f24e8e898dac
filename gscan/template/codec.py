"""Encoding of the template database's stored values (gscan.template.db): arrays by `np.save` (dtype and
shape kept, bit-exact), colour as JPEG q90 or PNG, depth as a 16-bit PNG in millimetres, masks as an 8-bit
PNG, poses as [4 x 4] float64 arrays, meta values as JSON. A stored value that does not decode raises
`BadBlob` (the database turns it into an InputError naming its file).
"""
from __future__ import annotations

import io
import json
import math
from typing import Any, overload

import cv2
import numpy as np

from gscan.errors import GscanError
from gscan.features import DESCRIPTOR_KINDS
from gscan.geometry.transforms import MAX_TRANSLATION_M, is_rigid
from gscan.io.images import image_size


def encode_array(a: np.ndarray | None) -> bytes | None:
    if a is None:
        return None
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


class BadBlob(Exception):
    """A stored value that does not decode (the database's reads turn it into an InputError naming the file)."""


class TooLarge(BadBlob):
    """A stored image above the pixel limit (`gscan.io.images.max_image_pixels`): refused before decoding."""


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "[" + " x ".join("N" if s is None else str(s) for s in shape) + "]"


@overload
def decode_array(b: bytes, shape: tuple[int | None, ...] | None = None) -> np.ndarray: ...
@overload
def decode_array(b: None, shape: tuple[int | None, ...] | None = None) -> None: ...
@overload
def decode_array(b: bytes | None, shape: tuple[int | None, ...] | None = None) -> np.ndarray | None: ...
def decode_array(b: bytes | None, shape: tuple[int | None, ...] | None = None) -> np.ndarray | None:
    """A stored array (None stays None); `shape` (None = any size along that axis) is checked when given.

    The `.npy` header is read first: its declared shape must be `shape` and its data exactly the rest of the
    blob, so a header that declares a huge array is refused before anything is allocated."""
    if b is None:
        return None
    f = io.BytesIO(b)
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            dshape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            dshape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except (ValueError, EOFError, OSError, TypeError, SyntaxError) as e:
        raise BadBlob(f"undecodable array blob: {e}") from None
    if dtype.hasobject or dtype.kind not in "iuf":
        raise BadBlob(f"stored array is {dtype}, not numbers")
    if shape is not None and (len(dshape) != len(shape)
                              or any(s is not None and s != n for s, n in zip(shape, dshape, strict=True))):
        raise BadBlob(f"stored array is {dtype} {tuple(dshape)}, expected {_shape_text(shape)}")
    declared = dtype.itemsize * math.prod(int(n) for n in dshape)  # Python ints: no overflow
    if declared != len(b) - f.tell():
        raise BadBlob(f"stored array declares {tuple(dshape)} {dtype} ({declared} bytes) but holds "
                      f"{len(b) - f.tell()} bytes")
    try:
        a = np.load(io.BytesIO(b), allow_pickle=False)  # no larger than the blob itself now
    except (ValueError, EOFError, OSError, TypeError) as e:
        raise BadBlob(f"undecodable array blob: {e}") from None
    if a.dtype.kind not in "iuf":
        raise BadBlob(f"stored array is {a.dtype}, not numbers")
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise BadBlob(f"stored {a.shape} array holds NaN or infinite values")
    return a


def decode_json(text: str) -> Any:
    try:
        return json.loads(text)
    except (ValueError, TypeError, RecursionError) as e:
        raise BadBlob(f"undecodable JSON value: {e.__class__.__name__}") from None


def encode_color(rgb: np.ndarray, codec: str) -> bytes:
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"colour must be [H x W x 3] uint8, got {rgb.dtype} {rgb.shape}")
    params = [cv2.IMWRITE_JPEG_QUALITY, 90] if codec == "jpg" else []
    ok, buf = cv2.imencode("." + codec, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise GscanError(f"cannot encode colour as {codec}")
    return buf.tobytes()


def depth_to_mm_u16(depth: np.ndarray) -> np.ndarray:
    """[H x W] float metres -> [H x W] uint16 millimetres (0 invalid, out of range -> 0)."""
    mm = np.rint(np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0) * 1000.0)
    mm[(mm < 0) | (mm > 65535)] = 0
    return mm.astype(np.uint16)


def encode_depth(depth: np.ndarray) -> bytes:
    return cv2.imencode(".png", depth_to_mm_u16(depth))[1].tobytes()


def encode_mask(mask: np.ndarray) -> bytes:
    return cv2.imencode(".png", np.where(np.asarray(mask, dtype=bool), 255, 0).astype(np.uint8))[1].tobytes()


def decode_image(b: bytes, dtype: type, channels: int, size_wh: tuple[int, int]) -> np.ndarray:
    """A stored image, which must be `dtype` with `channels` channels (1: [H x W]) and `size_wh` pixels; its
    header is read first, so an image of another size is never decoded (the database checks that `size_wh`,
    its view's intrinsics, is within the pixel limit)."""
    if b:
        try:
            w, h, _ = image_size(bytes(b), limit=False)
        except ValueError as e:
            raise TooLarge(f"stored image: {e}") from None
        except Exception:  # noqa: BLE001 - PIL raises many types for a header it cannot read
            raise BadBlob("undecodable image blob (unreadable header)") from None
        if (w, h) != tuple(size_wh):
            raise BadBlob(f"stored image is {w}x{h}, expected {size_wh[0]}x{size_wh[1]} (its intrinsics)")
    img = cv2.imdecode(np.frombuffer(b, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if b else None  # b"" asserts in cv2
    if img is None:
        raise BadBlob("undecodable image blob")
    shape = (size_wh[1], size_wh[0]) + (() if channels == 1 else (channels,))
    if img.dtype != dtype or img.shape != shape:
        raise BadBlob(f"stored image is {img.dtype} {img.shape}, expected {np.dtype(dtype)} {shape}")
    return img


@overload
def decode_T(b: bytes) -> np.ndarray: ...
@overload
def decode_T(b: None) -> None: ...
@overload
def decode_T(b: bytes | None) -> np.ndarray | None: ...
def decode_T(b: bytes | None) -> np.ndarray | None:
    """A stored [4 x 4] transform (None stays None)."""
    if b is None:
        return None
    T = decode_array(b, (4, 4)).astype(np.float64)
    if not is_rigid(T):
        raise BadBlob(f"stored transform is not a rigid pose within {MAX_TRANSLATION_M:g} m")
    return T


@overload
def check_T(T: np.ndarray) -> np.ndarray: ...
@overload
def check_T(T: None) -> None: ...
@overload
def check_T(T: np.ndarray | None) -> np.ndarray | None: ...
def check_T(T: np.ndarray | None) -> np.ndarray | None:
    if T is None:
        return None
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"transform must be a finite [4 x 4] matrix, got shape {T.shape}")
    return T


# -- decoded records that cannot be a template's (each raises BadBlob)
def check_keypoints(pixels: np.ndarray, points: np.ndarray, descriptors: np.ndarray, scales: np.ndarray | None,
                    kind: str, what: str) -> None:
    """One view's keypoint arrays: equal lengths, a known descriptor kind with its length and dtype."""
    if len({len(pixels), len(points), len(descriptors)} | ({len(scales)} if scales is not None else set())) > 1:
        raise BadBlob(f"{what}: keypoint arrays of different lengths")
    if kind not in DESCRIPTOR_KINDS:
        raise BadBlob(f"{what}: unknown descriptor kind {kind!r}")
    dim, dtype = DESCRIPTOR_KINDS[kind]
    if descriptors.shape[1] != dim or descriptors.dtype != dtype:
        raise BadBlob(f"{what}: {kind} descriptors are {descriptors.dtype} x {descriptors.shape[1]}, "
                      f"expected {np.dtype(dtype)} x {dim}")


def check_mesh(vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray | None) -> None:
    """Integer triangles indexing the vertices, one uint8 colour per vertex (or none)."""
    if triangles.dtype.kind not in "iu" or (triangles.size and (triangles.min() < 0
                                                                or triangles.max() >= len(vertices))):
        raise BadBlob(f"mesh triangles index outside its {len(vertices)} vertices")
    check_colors(colors, len(vertices), "mesh")


def check_colors(colors: np.ndarray | None, n: int, what: str) -> None:
    if colors is not None and (colors.dtype != np.uint8 or len(colors) != n):
        raise BadBlob(f"{what} colours are {colors.dtype} x {len(colors)}, expected uint8 x {n}")
