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
from gscan.geometry.transforms import MAX_TRANSLATION_M, is_rigid

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


def _read_calibration(path: Path, width: int | None = None, height: int | None = None) -> tuple[np.ndarray, int, int]:
    """[3 x 3] pinhole calibration of a cam_K.txt / intrinsics JSON and the image size it carries (0 x 0 for a
    cam_K.txt without `width`/`height`), checked as a pinhole matrix; InputError naming the file."""
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
    why = not_a_pinhole(K)
    if why:
        raise _bad(path, why)
    return K, w, h


def not_a_pinhole(K: np.ndarray) -> str | None:
    """Why [3 x 3] K is not a pinhole calibration [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (None when it is)."""
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 2] < 0 or K[1, 2] < 0:
        return f"invalid intrinsics values fx={K[0, 0]} fy={K[1, 1]} cx={K[0, 2]} cy={K[1, 2]}"
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or np.any(K[1, 0] != 0) or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        return "not a pinhole calibration matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"
    return None


def load_intrinsics(path: str | Path, width: int | None = None, height: int | None = None) -> Intrinsics:
    """Read intrinsics from `cam_K.txt` (3x3 text) or an Open3D `PinholeCameraIntrinsic` JSON.

    A cam_K.txt carries no image size: `width`/`height` must then be given (readers pass the
    size of the first colour image). Raises InputError naming the file on any problem.
    """
    path = Path(path)
    K, w, h = _read_calibration(path, width, height)
    if (width and w and width != w) or (height and h and height != h):
        raise _bad(path, f"intrinsics are for {w}x{h} images but the images are {width}x{height}")
    if w <= 0 or h <= 0:
        raise _bad(path, "intrinsics carry no image size and none was given")
    why = implausible_intrinsics(K, w, h)
    if why:
        raise _bad(path, why)
    return Intrinsics.from_matrix(K, w, h)


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


class DepthCamera:
    """The depth camera of a sensor whose depth images are not registered to its colour images (a Kinect v1,
    a RealSense recorded without alignment): its calibration K [3 x 3], the depth image size it is for, and
    T_color_depth [4 x 4], a rigid transform mapping depth-camera points into the colour camera (metres).
    Frames read with one have their depth reprojected into the colour camera (`gscan.io.align`).

    `DepthCamera(intrinsics, T_color_depth=None)`: intrinsics is an `Intrinsics` (depth images of its size), or
    a bare [3 x 3] K, as a cam_K.txt holds it, which fits depth images of any size (`for_size` resolves it
    against a depth image's size); T_color_depth None: the colour camera's centre and axes. `source`: the file
    it was loaded from (`load_depth_camera`), named in errors; not part of its value. Immutable; ValueError for
    a K that is not a pinhole calibration or a T_color_depth that is not a rigid 4 x 4 transform.
    """

    __slots__ = ("K", "T_color_depth", "size", "source")
    K: np.ndarray
    size: tuple[int, int] | None
    T_color_depth: np.ndarray
    source: Path | None

    def __init__(self, intrinsics: Intrinsics | np.ndarray, T_color_depth: np.ndarray | None = None, *,
                 source: str | Path | None = None):
        if isinstance(intrinsics, Intrinsics):
            K, size = intrinsics.K, (intrinsics.width, intrinsics.height)
        else:
            K, size = np.asarray(intrinsics, dtype=np.float64), None
            if K.shape != (3, 3):
                raise ValueError(f"depth camera intrinsics must be an Intrinsics or a 3x3 matrix, not shape {K.shape}")
            why = not_a_pinhole(K)
            if why:
                raise ValueError(why)
        T = np.eye(4) if T_color_depth is None else np.asarray(T_color_depth, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_color_depth must be a 4x4 matrix, not shape {T.shape}")
        if not is_rigid(T, max_translation=MAX_TRANSLATION_M):
            raise ValueError(f"T_color_depth is not a rigid transform in metres (rotation orthonormal, last row "
                             f"0 0 0 1, translation within {MAX_TRANSLATION_M:g} m)")
        for name, value in (("K", _frozen(K)), ("size", size), ("T_color_depth", _frozen(T)),
                            ("source", None if source is None else Path(source))):
            object.__setattr__(self, name, value)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"DepthCamera is immutable (cannot set {name})")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, DepthCamera):
            return NotImplemented
        return (self.size == other.size and np.array_equal(self.K, other.K)
                and np.array_equal(self.T_color_depth, other.T_color_depth))

    __hash__ = None  # type: ignore[assignment]  # arrays: equal by value, not hashable

    def __repr__(self) -> str:
        size = "any size" if self.size is None else f"{self.size[0]}x{self.size[1]}"
        return (f"DepthCamera(fx={self.K[0, 0]:g}, fy={self.K[1, 1]:g}, cx={self.K[0, 2]:g}, cy={self.K[1, 2]:g}, "
                f"{size}, t_color_depth={np.round(self.T_color_depth[:3, 3], 6).tolist()})")

    @property
    def intrinsics(self) -> Intrinsics:
        """Its intrinsics; ValueError for a camera of no particular image size (use `for_size`)."""
        if self.size is None:
            raise ValueError("the depth camera fits depth images of any size: its intrinsics need one (for_size)")
        return Intrinsics.from_matrix(self.K, *self.size)

    def for_size(self, width: int, height: int) -> Intrinsics:
        """Its intrinsics for depth images of width x height; ValueError (the reason) when it cannot be of that
        size: calibrated for another size, or (of no particular size) a principal point or focal length
        implausible for it (`implausible_intrinsics`)."""
        if self.size is not None:
            if self.size != (width, height):
                raise ValueError(f"depth is {width}x{height} but the depth camera's intrinsics are for "
                                 f"{self.size[0]}x{self.size[1]} images")
            return self.intrinsics
        why = implausible_intrinsics(self.K, width, height)
        if why:
            raise ValueError(why)
        return Intrinsics.from_matrix(self.K, width, height)

    def sized(self, width: int, height: int) -> DepthCamera:
        """The same camera for depth images of width x height (`for_size`; ValueError when it cannot be)."""
        return DepthCamera(self.for_size(width, height), self.T_color_depth, source=self.source)

    def to_dict(self) -> dict:
        """Its values as JSON: {"K": 3x3, "size": [width, height] or None, "T_color_depth": 4x4}."""
        return {"K": self.K.tolist(), "size": None if self.size is None else list(self.size),
                "T_color_depth": self.T_color_depth.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> DepthCamera:
        """The camera of `to_dict`'s values."""
        K = np.asarray(d["K"], dtype=np.float64)
        size = d.get("size")
        return cls(Intrinsics.from_matrix(K, int(size[0]), int(size[1])) if size else K, d.get("T_color_depth"))


def load_depth_camera(intrinsics: str | Path, T_color_depth: str | Path | None = None) -> DepthCamera:
    """The depth camera of depth images not registered to colour, from its files: `intrinsics`, a cam_K.txt (which
    fits depth images of any size, resolved against each depth image's) or an intrinsics JSON (Open3D, BOP or
    fx/fy/cx/cy; with width/height it is for images of that size alone), and `T_color_depth`, the depth camera's
    pose in the colour camera (a `.json` `{"T": 4x4}` or bare 4x4 list, else 4 (or 3) rows of 4 numbers; metres;
    None: the colour camera's centre and axes). InputError naming the file on any problem."""
    from gscan.io.poses import read_pose_file, read_pose_txt

    path = Path(intrinsics)
    K, w, h = _read_calibration(path)
    intr: Intrinsics | np.ndarray = K
    if w > 0 and h > 0:
        why = implausible_intrinsics(K, w, h)
        if why:
            raise _bad(path, why)
        intr = Intrinsics.from_matrix(K, w, h)
    T = None
    if T_color_depth is not None:
        pose = Path(T_color_depth)
        if not pose.is_file():
            raise not_a_file(pose, "pose file")
        T = read_pose_file(pose) if pose.suffix.lower() == ".json" else read_pose_txt(pose)
    return DepthCamera(intr, T, source=path)


def depth_camera_of(intrinsics: str | Path | None, T_color_depth: str | Path | None = None) -> DepthCamera | None:
    """The depth camera the `--depth-intrinsics` / `--depth-to-color` options (or a request's fields) name:
    `load_depth_camera`, or None without intrinsics (the depth is registered to colour); a pose alone is refused,
    naming its file."""
    if intrinsics is None:
        if T_color_depth is not None:
            raise InputError(T_color_depth, "a depth-to-colour pose needs the depth camera's intrinsics too "
                             "(--depth-intrinsics)")
        return None
    return load_depth_camera(intrinsics, T_color_depth)


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
