"""Pinhole camera model, RGB-D frames, back-projection and robust keypoint lifting.

Conventions: pixel (u, v) = (column, row) with the centre of the top-left pixel at (0, 0);
camera frame x right, y down, z forward (OpenCV); depth in metres, 0 = invalid.
"""
from __future__ import annotations

import json
import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from gscan.errors import InputError, not_a_file

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of `width` x `height` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        vals = np.array([self.fx, self.fy, self.cx, self.cy], dtype=float)
        if not np.all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"invalid image size {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """[3 x 3] calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, K: np.ndarray, width: int, height: int) -> Intrinsics:
        K = np.asarray(K, dtype=float).reshape(3, 3)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    def scaled(self, s: float) -> Intrinsics:
        """Intrinsics of the image resized by factor `s` (pixel-centre convention)."""
        return Intrinsics(self.fx * s, self.fy * s, (self.cx + 0.5) * s - 0.5, (self.cy + 0.5) * s - 0.5,
                          max(1, round(self.width * s)), max(1, round(self.height * s)))

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> Intrinsics:
        return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), int(d["width"]), int(d["height"]))


def _bad(path: Path, reason: str) -> InputError:
    return InputError(path, reason)


MAX_FOCAL_PX = 1e5  # about 170x a RealSense's focal length at 640x480


def implausible_intrinsics(K: np.ndarray, width: int, height: int) -> str | None:
    """Why a [3 x 3] calibration cannot be one of width x height images (None when it can): focal lengths
    outside 1-1e5 px, or a principal point beyond twice the image size."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (1.0 <= fx <= MAX_FOCAL_PX and 1.0 <= fy <= MAX_FOCAL_PX):
        return f"implausible focal length fx={fx:g} fy={fy:g} px (expected 1-{MAX_FOCAL_PX:g})"
    if cx > 2 * width or cy > 2 * height:
        return f"principal point ({cx:g}, {cy:g}) lies far outside the {width}x{height} image"
    return None


def load_intrinsics(path: str | Path, width: int | None = None, height: int | None = None) -> Intrinsics:
    """Read intrinsics from `cam_K.txt` (3x3 text) or an Open3D `PinholeCameraIntrinsic` JSON.

    A cam_K.txt carries no image size: `width`/`height` must then be given (readers pass the
    size of the first colour image). Raises InputError naming the file on any problem.
    """
    path = Path(path)
    if not path.is_file():
        raise not_a_file(path, "intrinsics file")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Windows editors) is not a number
    except (OSError, UnicodeDecodeError) as e:
        raise _bad(path, f"cannot read intrinsics ({e.__class__.__name__})") from None
    if path.suffix.lower() == ".json" or text.lstrip().startswith("{"):
        try:
            d = json.loads(text)
            if "intrinsic_matrix" in d:  # Open3D: column-major 3x3
                K = np.asarray(d["intrinsic_matrix"], dtype=float).reshape(3, 3).T
                w, h = int(d.get("width", width or 0)), int(d.get("height", height or 0))
            elif "cam_K" in d:  # BOP camera entry: row-major 3x3
                K = np.asarray(d["cam_K"], dtype=float).reshape(3, 3)
                w, h = int(d.get("width", width or 0)), int(d.get("height", height or 0))
            elif "fx" in d:
                K = np.array([[d["fx"], 0, d["cx"]], [0, d["fy"], d["cy"]], [0, 0, 1]], dtype=float)
                w, h = int(d.get("width", width or 0)), int(d.get("height", height or 0))
            else:
                raise ValueError("no intrinsic_matrix, cam_K or fx/fy/cx/cy key")
        except (ValueError, TypeError, KeyError, OverflowError, RecursionError) as e:
            raise _bad(path, f"malformed intrinsics JSON: {e.__class__.__name__}: {e}"[:300]) from None
    else:
        try:
            K = np.array([[float(x) for x in line.replace(",", " ").split()]
                          for line in text.splitlines() if line.strip()])
            K = K.reshape(3, 3)
        except ValueError:
            raise _bad(path, "malformed cam_K.txt: expected a 3x3 matrix of numbers") from None
        w, h = int(width or 0), int(height or 0)
    if (width and w and width != w) or (height and h and height != h):
        raise _bad(path, f"intrinsics are for {w}x{h} images but the images are {width}x{height}")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 2] < 0 or K[1, 2] < 0:
        raise _bad(path, f"invalid intrinsics values fx={K[0, 0]} fy={K[1, 1]} cx={K[0, 2]} cy={K[1, 2]}")
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or np.any(K[1, 0] != 0) or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise _bad(path, "not a pinhole calibration matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if w <= 0 or h <= 0:
        raise _bad(path, "intrinsics carry no image size and none was given")
    why = implausible_intrinsics(K, w, h)
    if why:
        raise _bad(path, why)
    return Intrinsics.from_matrix(K, w, h)


@dataclass(frozen=True)
class DepthCamera:
    """The depth camera of a sensor whose depth images are not registered to its colour images (a Kinect v1,
    a RealSense recorded without alignment): its own intrinsics (the depth images' size) and T_color_depth
    [4 x 4], which maps depth-camera points into the colour camera (metres). Frames read with one have their
    depth reprojected into the colour camera (`gscan.io.align.align_depth_to_color`)."""

    intrinsics: Intrinsics
    T_color_depth: np.ndarray = field(default_factory=lambda: np.eye(4))

    def to_dict(self) -> dict:
        return {"intrinsics": self.intrinsics.to_dict(), "T_color_depth": np.asarray(self.T_color_depth).tolist()}


@dataclass
class RGBDFrame:
    """One RGB-D image.

    color: [H x W x 3] uint8 RGB; depth: [H x W] float32 metres (0 = invalid);
    mask: optional [H x W] bool object mask; name: frame name (file stem).
    """

    name: str
    color: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics
    mask: np.ndarray | None = None
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        h, w = self.depth.shape[:2]
        if self.color.shape[:2] != (h, w):
            raise InputError(self.source, f"colour {self.color.shape[1]}x{self.color.shape[0]} and depth {w}x{h} "
                             "sizes differ")
        if (self.intrinsics.width, self.intrinsics.height) != (w, h):
            raise InputError(self.source, f"intrinsics are for {self.intrinsics.width}x{self.intrinsics.height} "
                             f"but the frame is {w}x{h}")


@lru_cache(maxsize=8)
def pixel_rays(intr: Intrinsics) -> np.ndarray:
    """[H x W x 3] ray directions with z = 1 for every pixel centre (cached per intrinsics, read-only)."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    rays.setflags(write=False)
    return rays


def backproject(depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """[H x W] depth (m) -> [H x W x 3] camera-frame points (zeros where depth is 0)."""
    return (pixel_rays(intr) * depth[..., None]).astype(np.float32)


def backproject_pixels(pixels: np.ndarray, z: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """[N x 2] pixels (u, v) and [N] depths -> [N x 3] camera-frame points."""
    pixels = np.asarray(pixels, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    x = (pixels[:, 0] - intr.cx) / intr.fx * z
    y = (pixels[:, 1] - intr.cy) / intr.fy * z
    return np.stack([x, y, z], axis=1)


def project(points: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """[N x 3] camera-frame points -> [N x 2] pixels (u, v). Points need z > 0."""
    p = np.asarray(points, dtype=np.float64)
    return np.stack([p[:, 0] / p[:, 2] * intr.fx + intr.cx, p[:, 1] / p[:, 2] * intr.fy + intr.cy], axis=1)


def point_cloud(frame: RGBDFrame, mask: np.ndarray | None = None, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Valid points of a frame: ([N x 3] camera-frame metres, [N x 3] colours in [0, 1]).

    `mask` ([H x W] bool) restricts the pixels; `stride` subsamples rows and columns.
    """
    valid = frame.depth > 0
    if mask is not None:
        valid &= mask
    sl = (slice(None, None, stride), slice(None, None, stride))
    pts = backproject(frame.depth, frame.intrinsics)[sl][valid[sl]]
    cols = frame.color[sl][valid[sl]].astype(np.float32) / 255.0
    return pts, cols


def lift_keypoints(pixels: np.ndarray, depth: np.ndarray, intr: Intrinsics, window: int = 2,
                   max_rel_spread: float = 0.03, min_valid_frac: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Lift 2D keypoints to 3D with robust depth.

    For each keypoint the depth is the median of the valid depths in the (2*window+1)^2
    window around its rounded pixel. A keypoint is rejected when fewer than
    `min_valid_frac` of the window is valid, or when the window spans a depth
    discontinuity (valid depths spread beyond `max_rel_spread` of the median, measured
    between the 10th and 90th percentile).

    Keypoints with non-finite coordinates or whose rounded pixel lies outside the image
    are rejected.

    pixels: [N x 2] (u, v). Returns ([N x 3] points, zeros where rejected; [N] bool valid).
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    n = len(pixels)
    H, W = depth.shape
    pts = np.zeros((n, 3))
    if n == 0:
        return pts, np.zeros(0, dtype=bool)
    r = window
    finite = np.all(np.isfinite(pixels), axis=1)
    ur = np.rint(np.where(finite, pixels[:, 0], -1.0))
    vr = np.rint(np.where(finite, pixels[:, 1], -1.0))
    inside = finite & (ur >= 0) & (ur <= W - 1) & (vr >= 0) & (vr <= H - 1)
    u = np.clip(ur, 0, W - 1).astype(int)
    v = np.clip(vr, 0, H - 1).astype(int)
    from gscan.io.lift_kernel import window_stats

    med, lo, hi = np.empty(n), np.empty(n), np.empty(n)
    count = np.empty(n, np.int64)
    window_stats(np.ascontiguousarray(depth), u, v, r, med, lo, hi, count)
    frac = count / (2 * r + 1) ** 2
    ok = inside & (frac >= min_valid_frac) & np.isfinite(med) & (med > 0)
    ok &= np.where(ok, (hi - lo) <= max_rel_spread * np.where(ok, med, 1.0), False)
    pts[ok] = backproject_pixels(pixels[ok], med[ok], intr)
    return pts, ok


class FrameIteration(ABC):
    """Iteration of a sequence of named frames (folders and recordings): over `names`, by `self[name]`, which
    raises InputError for an unusable frame (and records it in the sequence's problems)."""

    names: list[str]

    @abstractmethod
    def __getitem__(self, name: str) -> RGBDFrame: ...

    def __iter__(self) -> Iterator[RGBDFrame]:
        """Every frame in order; raises InputError on the first unusable one (see iter_frames)."""
        return self.iter_frames(skip_bad=False)

    def iter_frames(self, skip_bad: bool = True) -> Iterator[RGBDFrame]:
        """Frames in order; with skip_bad, unusable frames are logged, recorded in problems and skipped."""
        for name in self.names:
            try:
                yield self[name]
            except InputError as e:
                if not skip_bad:
                    raise
                log.warning("skipping frame %s: %s", name, e)
