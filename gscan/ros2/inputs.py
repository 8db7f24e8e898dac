"""The node's inputs without rclpy: image messages as arrays, CameraInfo checked, colour and depth paired by stamp,
the newest pair handed to the worker.

Messages are duck-typed (the attributes of sensor_msgs/Image and CameraInfo), so this module imports no ROS
package. The pixels are parsed by `gscan.io.recordings.messages`, the readers of recorded images.
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from gscan.errors import InputError
from gscan.io.camera import Intrinsics, RGBDFrame
from gscan.io.recordings.messages import ImageMsg, MessageError, color_pixels, depth_metres
from gscan.io.recordings.streams import camera_info_intrinsics


class InputProblem(ValueError):
    """A message the node cannot use: `topic` names its topic, the message says why (one line)."""

    def __init__(self, topic: str, reason: str):
        self.topic = topic
        self.reason = " ".join(reason.split())
        super().__init__(f"topic {topic}: {self.reason}")


def stamp_ns(msg: Any) -> int:
    """A message's header stamp in ns."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def image_msg(msg: Any) -> ImageMsg:
    """An rclpy sensor_msgs/Image as the recordings' ImageMsg (its pixels a view of the message's data)."""
    return ImageMsg(stamp_ns(msg), str(msg.header.frame_id), int(msg.height), int(msg.width), str(msg.encoding),
                    bool(msg.is_bigendian), int(msg.step), memoryview(msg.data).cast("B"))


def camera_intrinsics(msg: Any, topic: str) -> Intrinsics:
    """The pinhole intrinsics of a CameraInfo; InputProblem naming the topic when it has none (zero focal length,
    no size, an implausible calibration)."""
    try:
        return camera_info_intrinsics(msg, topic, None)  # type: ignore[arg-type]  # no file: the topic is named
    except InputError as e:
        raise InputProblem(topic, e.reason.removeprefix(f"topic {topic}: ")) from None


def rgbd_frame(color: Any, depth: Any, intr: Intrinsics, depth_scale: float, color_topic: str,
               depth_topic: str) -> RGBDFrame:
    """The RGBDFrame of a colour and a depth message (rclpy Images) with the colour camera's intrinsics; named after
    the colour image's stamp (ns). InputProblem naming the topic for a wrong encoding or size."""
    try:
        rgb = color_pixels(image_msg(color))
    except MessageError as e:
        raise InputProblem(color_topic, str(e)) from None
    try:
        d = depth_metres(image_msg(depth), depth_scale)
    except MessageError as e:
        raise InputProblem(depth_topic, str(e)) from None
    h, w = rgb.shape[:2]
    if d.shape != (h, w):
        raise InputProblem(depth_topic, f"depth is {d.shape[1]}x{d.shape[0]} but colour is {w}x{h} (the node needs "
                           "depth registered to colour, e.g. aligned_depth_to_color)")
    if (intr.width, intr.height) != (w, h):
        raise InputProblem(color_topic, f"image is {w}x{h} but its CameraInfo is for {intr.width}x{intr.height}")
    return RGBDFrame(str(stamp_ns(color)), rgb, d, intr)


@dataclass
class Pair:
    """A colour and a depth message taken as one frame; received_s: time.monotonic() when it was paired."""

    color: Any
    depth: Any
    received_s: float


class Pairer:
    """Pairs colour and depth messages by stamp: a new message is paired with the other stream's waiting message
    nearest in stamp, within `tolerance_ns`; the paired messages and every older waiting one are dropped then.
    Each stream keeps at most `queue` waiting messages (the oldest go first): memory stays bounded whatever
    arrives. Not thread-safe (the executor's thread calls it)."""

    def __init__(self, tolerance_ns: int, queue: int):
        self.tolerance_ns = tolerance_ns
        self._waiting: dict[str, deque[tuple[int, Any]]] = {"color": deque(maxlen=queue),
                                                            "depth": deque(maxlen=queue)}
        self.unpaired = 0  # messages dropped without a partner

    def add(self, stream: str, msg: Any, now_s: float) -> Pair | None:
        """Offer a message of `stream` ("color" | "depth"); the pair it completes, or None."""
        t = stamp_ns(msg)
        other = self._waiting["depth" if stream == "color" else "color"]
        best = min(range(len(other)), key=lambda i: abs(other[i][0] - t), default=None)
        if best is None or abs(other[best][0] - t) > self.tolerance_ns:
            mine = self._waiting[stream]
            if len(mine) == mine.maxlen:
                self.unpaired += 1
            mine.append((t, msg))
            return None
        partner = other[best][1]
        for q in self._waiting.values():  # everything older than this frame can no longer be paired usefully
            while q and q[0][0] <= t:
                if q[0][1] is not partner:
                    self.unpaired += 1
                q.popleft()
        for i, (_, m) in enumerate(other):
            if m is partner:
                del other[i]
                break
        return Pair(msg, partner, now_s) if stream == "color" else Pair(partner, msg, now_s)


class LatestSlot:
    """One frame waiting for the worker: a new pair replaces a waiting one, which is counted as dropped (the node
    falls behind by dropping old frames, never by queueing them). Thread-safe."""

    def __init__(self) -> None:
        self._cv = threading.Condition()
        self._pair: Pair | None = None
        self._busy = False
        self._closed = False
        self.dropped = 0

    def put(self, pair: Pair) -> None:
        with self._cv:
            if self._pair is not None:
                self.dropped += 1
            self._pair = pair
            self._cv.notify_all()

    def take(self, timeout_s: float | None = None) -> Pair | None:
        """The waiting pair (marks the worker busy), or None when closed or after timeout_s."""
        with self._cv:
            self._busy = False
            self._cv.notify_all()
            self._cv.wait_for(lambda: self._pair is not None or self._closed, timeout_s)
            pair, self._pair = self._pair, None
            self._busy = pair is not None
            return pair

    def done(self) -> None:
        """The worker finished its pair."""
        with self._cv:
            self._busy = False
            self._cv.notify_all()

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until no pair waits and the worker is not busy; False after timeout_s."""
        with self._cv:
            return self._cv.wait_for(lambda: self._pair is None and not self._busy, timeout_s)

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()


def pose_fields(T: np.ndarray) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """(position x, y, z; orientation quaternion x, y, z, w) of a [4 x 4] rigid transform."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
