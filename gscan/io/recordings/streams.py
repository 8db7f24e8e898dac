"""What a recording's colour and depth streams are: topics, intrinsics, depth scale, the depth camera."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from dataclasses import field as dc_field
from pathlib import Path
from typing import Any

import numpy as np

from gscan.errors import InputError
from gscan.io.camera import DepthCamera, Intrinsics, implausible_intrinsics
from gscan.io.recordings.messages import ImageMsg, parse_image

log = logging.getLogger(__name__)

IDENTITY_ATOL = 1e-6  # rotation entries and translation (m) below which an extrinsic is the identity


@dataclass
class StreamSetup:
    """The colour and depth streams a recording's frames are read from.

    depth_camera: the depth stream's camera (its intrinsics, and T_color_depth mapping its points into the colour
    camera: identity when both topics are in one optical frame); depth_scale: metres per raw unit of 16-bit depth
    (None when the recording does not say; float depth is in metres). kind names the recording in messages.
    compressed: the topics whose messages are sensor_msgs CompressedImage; stamps: topic -> {log time (ns):
    the camera's timestamp of the frame logged then (ns)}, for recordings whose image headers carry the
    recording time instead (librealsense's rosbag2, which keeps the camera's in its metadata topics).
    """

    kind: str
    color_topic: str
    depth_topic: str
    color_intrinsics: Intrinsics
    depth_camera: DepthCamera
    depth_scale: float | None
    compressed: frozenset[str] = frozenset()
    stamps: dict[str, dict[int, int]] = dc_field(default_factory=dict)

    def parse(self, wire: str, topic: str, data: bytes | memoryview) -> ImageMsg:
        """A message of the colour or depth topic parsed (its pixels not decoded); MessageError when it does not
        parse."""
        return parse_image(wire, topic in self.compressed, data)

    @property
    def registered(self) -> bool:
        """Depth is already pixel-aligned with colour: identity extrinsics and the same intrinsics."""
        return is_identity(self.depth_camera.T_color_depth) and same_intrinsics(self.color_intrinsics,
                                                                               self.depth_camera.intrinsics)


def recorded_depth_camera(intrinsics: Intrinsics, T_color_depth: np.ndarray, path: Path | None) -> DepthCamera:
    """The depth camera a recording describes; InputError naming the recording when its depth-to-colour
    extrinsics are not a rigid transform."""
    try:
        return DepthCamera(intrinsics, T_color_depth)
    except ValueError as e:
        raise InputError(path, f"depth-to-colour extrinsics: {e}") from None


def is_identity(T: np.ndarray) -> bool:
    return bool(np.allclose(T, np.eye(4), rtol=0.0, atol=IDENTITY_ATOL))


def same_intrinsics(a: Intrinsics, b: Intrinsics) -> bool:
    if (a.width, a.height) != (b.width, b.height):
        return False
    pa = np.array([a.fx, a.fy, a.cx, a.cy])
    pb = np.array([b.fx, b.fy, b.cx, b.cy])
    return bool(np.allclose(pa, pb, rtol=1e-9, atol=1e-9))


def field(msg: Any, *names: str) -> Any:
    """The first of `names` that `msg` has (ROS 1 and ROS 2 spell some fields differently: K / k)."""
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(f"message has none of the fields {names}")


def stamp_ns(header: Any) -> int:
    """A std_msgs Header's stamp in nanoseconds (ROS 1 and ROS 2 spellings)."""
    st = header.stamp
    return int(field(st, "sec", "secs")) * 1_000_000_000 + int(field(st, "nanosec", "nsecs"))


def camera_info_intrinsics(msg: Any, topic: str, path: Path) -> Intrinsics:
    """Pinhole intrinsics of a sensor_msgs CameraInfo; InputError naming the file and topic when unusable.

    Distortion coefficients are not applied (gscan's camera model is a pinhole); non-zero ones are logged.
    """
    try:
        K = np.asarray(field(msg, "k", "K"), dtype=np.float64).reshape(3, 3)
        w, h = int(msg.width), int(msg.height)
        D = np.asarray(field(msg, "d", "D"), dtype=np.float64).ravel()
        model = str(getattr(msg, "distortion_model", ""))
    except (AttributeError, ValueError, TypeError) as e:
        raise InputError(path, f"topic {topic}: malformed CameraInfo ({e})") from None
    if not np.all(np.isfinite(K)) or w <= 0 or h <= 0:
        raise InputError(path, f"topic {topic}: CameraInfo holds no calibration (K={K.ravel().tolist()}, {w}x{h})")
    why = implausible_intrinsics(K, w, h)
    if why or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"topic {topic}: CameraInfo {why or 'has non-positive focal lengths'}")
    if D.size and np.any(np.abs(D[np.isfinite(D)]) > 1e-6):
        log.warning("%s: topic %s: %s distortion coefficients %s are not applied (pinhole model)",
                    path, topic, model or "unnamed", np.round(D, 5).tolist())
    return Intrinsics.from_matrix(K, w, h)


def quat_to_R(x: float, y: float, z: float, w: float) -> np.ndarray:
    """[3 x 3] rotation of the quaternion (x, y, z, w), normalised first; ValueError when it is zero."""
    q = np.array([w, x, y, z], dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError("zero or non-finite quaternion")
    w, x, y, z = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def transform_msg_T(msg: Any) -> np.ndarray:
    """[4 x 4] of a geometry_msgs Transform (rotation quaternion, translation in metres)."""
    q, t = msg.rotation, msg.translation
    T = np.eye(4)
    T[:3, :3] = quat_to_R(float(q.x), float(q.y), float(q.z), float(q.w))
    T[:3, 3] = [float(t.x), float(t.y), float(t.z)]
    if not np.all(np.isfinite(T)):
        raise ValueError("non-finite translation")
    return T
