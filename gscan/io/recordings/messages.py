"""sensor_msgs Image messages read straight from their serialised bytes, and their pixels as arrays.

Images are the bulk of a recording, so they are parsed here without a message library: the fields
are read with `struct` and the pixel data is a view into the message buffer (no copy until the
frame is decoded). Two wire formats:

- ROS 1 (`.bag`): Header (uint32 seq, uint32 sec, uint32 nsec, string frame_id), uint32 height,
  uint32 width, string encoding, uint8 is_bigendian, uint32 step, uint8[] data; strings and arrays
  carry a uint32 length, no padding. librealsense's recorder writes the Header's third field as a
  version string and, when it is "1", appends a float32 `depth_units` after the data (its
  `sensor_msgs/Image` has the standard definition and MD5 otherwise).
- CDR (ROS 2: `.db3`, `.mcap`): a 4-byte encapsulation header (its second byte 1 = little endian),
  then the same fields with ROS 2's Header (int32 sec, uint32 nanosec, string frame_id), strings
  NUL-terminated with the NUL counted in their length, and primitives aligned to their size
  relative to the end of the encapsulation header.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

from gscan.io.images import image_too_large

#: Colour encodings read, with their channel count (sensor_msgs/image_encodings, librealsense's names).
COLOR_ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "8uc3": 3, "yuyv": 2, "yuv422_yuy2": 2,
                   "uyvy": 2, "yuv422": 2}
#: Grey encodings, read as colour only when the topic is chosen explicitly (infrared streams are grey).
GREY_ENCODINGS = {"mono8": 1, "8uc1": 1}
#: Depth encodings: 16-bit raw units (scaled by the depth scale) or 32-bit float metres (REP 118).
DEPTH_ENCODINGS = {"16uc1": 2, "mono16": 2, "z16": 2, "32fc1": 4}
FLOAT_DEPTH = "32fc1"


@dataclass
class ImageMsg:
    """One sensor_msgs/Image, its pixels still in the message buffer.

    stamp_ns: header stamp (ns); data: step * height bytes (a view, valid while the buffer lives);
    depth_units: librealsense's per-frame metres per depth unit (0 when absent).
    """

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str
    is_bigendian: bool
    step: int
    data: memoryview
    depth_units: float = 0.0

    def problem(self, channels_bytes: int) -> str | None:
        """Why the pixels cannot be read as width x height pixels of `channels_bytes` bytes each (None when they
        can)."""
        if self.height <= 0 or self.width <= 0:
            return f"image is {self.width}x{self.height}"
        too_large = image_too_large(self.width, self.height)  # the limit every image gscan reads is held to
        if too_large:
            return too_large
        if self.step < self.width * channels_bytes:
            return f"row step {self.step} is shorter than {self.width} pixels of {channels_bytes} bytes"
        if len(self.data) < self.step * self.height:
            return f"holds {len(self.data)} bytes of pixels, {self.step * self.height} expected (truncated message)"
        return None


class MessageError(ValueError):
    """A message whose bytes do not parse as the type it claims to be."""


def parse_ros1_image(buf: bytes | memoryview) -> ImageMsg:
    """A ROS 1 sensor_msgs/Image from its serialised bytes (librealsense's trailing depth_units included)."""
    mv = memoryview(buf)
    try:
        _seq, sec, nsec, n = struct.unpack_from("<IIII", mv, 0)
        off = 16
        frame_id = bytes(mv[off:off + n]).decode("utf-8", "replace")
        off += n
        height, width, n = struct.unpack_from("<III", mv, off)
        off += 12
        encoding = bytes(mv[off:off + n]).decode("ascii", "replace")
        off += n
        big, step, n = struct.unpack_from("<BII", mv, off)
        off += 9
        if off + n > len(mv):
            raise MessageError(f"pixel data runs past the message end ({off + n} > {len(mv)} bytes)")
        data = mv[off:off + n]
        off += n
        units = struct.unpack_from("<f", mv, off)[0] if frame_id == "1" and off + 4 <= len(mv) else 0.0
    except struct.error as e:
        raise MessageError(f"truncated sensor_msgs/Image ({e})") from None
    return ImageMsg(sec * 1_000_000_000 + nsec, frame_id, height, width, encoding, bool(big), step, data,
                    float(units) if np.isfinite(units) else 0.0)


def _cdr_string(mv: memoryview, off: int, e: str) -> tuple[str, int]:
    off = (off + 3) & ~3
    (n,) = struct.unpack_from(e + "I", mv, 4 + off)
    off += 4
    if 4 + off + n > len(mv):
        raise MessageError("string runs past the message end")
    s = bytes(mv[4 + off:4 + off + n]).rstrip(b"\0").decode("utf-8", "replace")
    return s, off + n


def parse_cdr_image(buf: bytes | memoryview) -> ImageMsg:
    """A ROS 2 sensor_msgs/msg/Image from its CDR bytes (little- or big-endian encapsulation)."""
    mv = memoryview(buf)
    if len(mv) < 4:
        raise MessageError("message shorter than its CDR encapsulation header")
    e = "<" if mv[1] & 1 else ">"
    try:
        sec, nsec = struct.unpack_from(e + "iI", mv, 4)
        frame_id, off = _cdr_string(mv, 8, e)
        off = (off + 3) & ~3
        height, width = struct.unpack_from(e + "II", mv, 4 + off)
        encoding, off = _cdr_string(mv, off + 8, e)
        big = mv[4 + off]
        off = (off + 1 + 3) & ~3
        step, n = struct.unpack_from(e + "II", mv, 4 + off)
        off += 8
        if 4 + off + n > len(mv):
            raise MessageError(f"pixel data runs past the message end ({4 + off + n} > {len(mv)} bytes)")
        data = mv[4 + off:4 + off + n]
    except (struct.error, IndexError) as err:
        raise MessageError(f"truncated sensor_msgs/msg/Image ({err})") from None
    return ImageMsg(sec * 1_000_000_000 + nsec, frame_id, height, width, encoding, bool(big), step, data)


def encoding_kind(encoding: str) -> str | None:
    """"color" | "grey" | "depth" for the encodings gscan reads, None for others."""
    enc = encoding.lower()
    if enc in COLOR_ENCODINGS:
        return "color"
    if enc in GREY_ENCODINGS:
        return "grey"
    if enc in DEPTH_ENCODINGS:
        return "depth"
    return None


def _rows(msg: ImageMsg, bpp: int, dtype: np.dtype) -> np.ndarray:
    """[H x W x bpp/itemsize] view of the pixels (rows cut to width, padding dropped)."""
    a = np.frombuffer(msg.data, dtype=np.uint8, count=msg.step * msg.height).reshape(msg.height, msg.step)
    a = a[:, :msg.width * bpp]
    return a.view(dtype).reshape(msg.height, msg.width, -1)


def color_pixels(msg: ImageMsg) -> np.ndarray:
    """[H x W x 3] uint8 RGB copy of a colour (or grey) image message; MessageError for other encodings."""
    enc = msg.encoding.lower()
    ch = COLOR_ENCODINGS.get(enc) or GREY_ENCODINGS.get(enc)
    if ch is None:
        raise MessageError(f"encoding '{msg.encoding}' is not a colour image")
    bad = msg.problem(ch)
    if bad:
        raise MessageError(bad)
    px = _rows(msg, ch, np.dtype(np.uint8))
    if enc in ("rgb8",):
        return px.copy()
    if enc in ("bgr8", "8uc3"):
        return cv2.cvtColor(px, cv2.COLOR_BGR2RGB)
    if enc == "rgba8":
        return np.ascontiguousarray(px[:, :, :3])
    if enc == "bgra8":
        return cv2.cvtColor(px, cv2.COLOR_BGRA2RGB)
    if enc in ("yuyv", "yuv422_yuy2"):
        return cv2.cvtColor(px, cv2.COLOR_YUV2RGB_YUYV)
    if enc in ("uyvy", "yuv422"):
        return cv2.cvtColor(px, cv2.COLOR_YUV2RGB_UYVY)
    return cv2.cvtColor(px[:, :, 0], cv2.COLOR_GRAY2RGB)


def depth_raw(msg: ImageMsg) -> np.ndarray:
    """[H x W] copy of a depth message's values: uint16 raw units, or float32 metres for 32FC1."""
    enc = msg.encoding.lower()
    nbytes = DEPTH_ENCODINGS.get(enc)
    if nbytes is None:
        raise MessageError(f"encoding '{msg.encoding}' is not a depth image")
    bad = msg.problem(nbytes)
    if bad:
        raise MessageError(bad)
    order = ">" if msg.is_bigendian else "<"
    dtype = np.dtype(order + ("f4" if enc == FLOAT_DEPTH else "u2"))
    px = _rows(msg, nbytes, dtype)[:, :, 0]
    return px.astype(np.float32 if enc == FLOAT_DEPTH else np.uint16)  # native order, contiguous copy


def depth_metres(msg: ImageMsg, depth_scale: float) -> np.ndarray:
    """[H x W] float32 metres (0 = invalid): raw * depth_scale for 16-bit depth (the same float32 product as
    gscan.io.images.read_depth, so a recording and a folder of its frames give identical depth); float
    depth taken as metres with NaN / inf / negative values set to 0."""
    raw = depth_raw(msg)
    if raw.dtype == np.float32:
        raw[~np.isfinite(raw) | (raw < 0)] = 0.0
        return raw
    depth = raw.astype(np.float32)
    depth *= np.float32(depth_scale)
    return depth
