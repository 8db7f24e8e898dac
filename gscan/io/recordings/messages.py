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

sensor_msgs CompressedImage (Header, string format, uint8[] data) is read in both wire formats too; its
pixels are decoded only when the frame is read. The layouts, by the `format` string:

- image_transport `compressed`: "<encoding>; png compressed bgr8" (or jpeg; "jpeg" alone in old drivers):
  a PNG or JPEG file, decoded by OpenCV (librealsense 2.59 writes colour so, losslessly as PNG);
- image_transport `compressedDepth`: "16UC1; compressedDepth png" (librealsense 2.59's depth): a 12-byte
  header (int32 format, float32 depthQuantA, depthQuantB) and a 16-bit PNG; for 32FC1 the PNG holds
  quantised inverse depth, depth = depthQuantA / (value - depthQuantB);
- librealsense's zstd: "<encoding>; zstd; <W>x<H> step=<S>": the raw pixels compressed with zstd
  (colour formats it has no PNG for, e.g. YUYV).
The image size is read from the PNG / JPEG header (or the format string) without decoding the pixels.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass, replace

import cv2
import numpy as np

from gscan.io.images import image_too_large
from gscan.io.recordings.source import unwrap, zstd_decompress

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
    depth_units: librealsense's per-frame metres per depth unit (0 when absent); compression: "" (raw pixels),
    "image" (a PNG / JPEG file), "depth" (compressedDepth) or "zstd" (see the module docstring), with data the
    compressed bytes and encoding the image's encoding before compression.
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
    compression: str = ""

    def problem(self, channels_bytes: int) -> str | None:
        """Why the pixels cannot be read as width x height pixels of `channels_bytes` bytes each (None when they
        can)."""
        if self.height <= 0 or self.width <= 0:
            return f"image is {self.width}x{self.height}"
        too_large = image_too_large(self.width, self.height)  # the limit every image gscan reads is held to
        if too_large:
            return too_large
        if self.compression:  # the decoded pixels are checked when the frame is read
            return None
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


def _cdr_header(buf: bytes | memoryview) -> tuple[memoryview, str, int, str, int]:
    """The std_msgs/Header every image message starts with, from CDR bytes: (the bytes, the struct byte order,
    stamp in ns, frame id, offset after it, past the 4-byte encapsulation). MessageError without an encapsulation
    header; struct.error / IndexError when truncated (the caller names the message)."""
    mv = memoryview(buf)
    if len(mv) < 4:
        raise MessageError("message shorter than its CDR encapsulation header")
    e = "<" if mv[1] & 1 else ">"
    sec, nsec = struct.unpack_from(e + "iI", mv, 4)
    frame_id, off = _cdr_string(mv, 8, e)
    return mv, e, sec * 1_000_000_000 + nsec, frame_id, off


def parse_cdr_image(buf: bytes | memoryview) -> ImageMsg:
    """A ROS 2 sensor_msgs/msg/Image from its CDR bytes (little- or big-endian encapsulation)."""
    try:
        mv, e, stamp, frame_id, off = _cdr_header(buf)
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
    return ImageMsg(stamp, frame_id, height, width, encoding, bool(big), step, data)


_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_ZSTD_FORMAT = re.compile(r"^(\d+)x(\d+)\s+step=(\d+)$")
DEPTH_HEADER_BYTES = 12  # compressed_depth_image_transport's ConfigHeader: int32 format, float32 quantA, quantB


def compressed_size(data: memoryview) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR or a JPEG's start-of-frame segment; MessageError for other data."""
    try:
        if bytes(data[:8]) == _PNG:
            w, h = struct.unpack_from(">II", data, 16)
            return int(w), int(h)
        if bytes(data[:2]) == b"\xff\xd8":
            i = 2
            while i + 4 <= len(data):
                if data[i] != 0xFF:
                    break
                marker = data[i + 1]
                if marker in _JPEG_SOF:
                    h, w = struct.unpack_from(">HH", data, i + 5)
                    return int(w), int(h)
                if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
                    i += 2
                    continue
                (n,) = struct.unpack_from(">H", data, i + 2)
                i += 2 + n
            raise MessageError("JPEG data without a frame header")
    except struct.error:
        raise MessageError("compressed image header truncated") from None
    raise MessageError(f"compressed data is neither PNG nor JPEG (starts {bytes(data[:8]).hex()})")


def _compressed(stamp_ns: int, frame_id: str, fmt: str, data: memoryview) -> ImageMsg:
    """An ImageMsg of CompressedImage fields: its encoding, size and compression from `fmt` and the data's
    header (see the module docstring)."""
    parts = [p.strip() for p in fmt.split(";")]
    low = fmt.lower()
    if "compresseddepth" in low:
        if "rvl" in low:
            raise MessageError(f"compressedDepth format '{fmt}' (RVL) is not read; PNG is")
        encoding = parts[0] if len(parts) > 1 else "16UC1"
        w, h = compressed_size(data[DEPTH_HEADER_BYTES:])
        return ImageMsg(stamp_ns, frame_id, h, w, encoding, False, 0, data, compression="depth")
    if len(parts) >= 3 and parts[1].lower() == "zstd":
        m = _ZSTD_FORMAT.match(parts[2])
        if m is None:
            raise MessageError(f"zstd image format '{fmt}' does not give the size ('WxH step=S')")
        w, h, step = (int(g) for g in m.groups())
        return ImageMsg(stamp_ns, frame_id, h, w, parts[0], False, step, data, compression="zstd")
    w, h = compressed_size(data)
    encoding = parts[0] if len(parts) > 1 else "bgr8"  # a bare "jpeg" / "png": image_transport's bgr8
    return ImageMsg(stamp_ns, frame_id, h, w, encoding, False, 0, data, compression="image")


def parse_ros1_compressed(buf: bytes | memoryview) -> ImageMsg:
    """A ROS 1 sensor_msgs/CompressedImage from its serialised bytes."""
    mv = memoryview(buf)
    try:
        _seq, sec, nsec, n = struct.unpack_from("<IIII", mv, 0)
        off = 16
        frame_id = bytes(mv[off:off + n]).decode("utf-8", "replace")
        off += n
        (n,) = struct.unpack_from("<I", mv, off)
        fmt = bytes(mv[off + 4:off + 4 + n]).decode("ascii", "replace")
        off += 4 + n
        (n,) = struct.unpack_from("<I", mv, off)
        off += 4
    except struct.error as e:
        raise MessageError(f"truncated sensor_msgs/CompressedImage ({e})") from None
    if off + n > len(mv):
        raise MessageError(f"compressed data runs past the message end ({off + n} > {len(mv)} bytes)")
    return _compressed(sec * 1_000_000_000 + nsec, frame_id, fmt, mv[off:off + n])


def parse_cdr_compressed(buf: bytes | memoryview) -> ImageMsg:
    """A ROS 2 sensor_msgs/msg/CompressedImage from its CDR bytes."""
    try:
        mv, e, stamp, frame_id, off = _cdr_header(buf)
        fmt, off = _cdr_string(mv, off, e)
        off = (off + 3) & ~3
        (n,) = struct.unpack_from(e + "I", mv, 4 + off)
        off += 4
    except (struct.error, IndexError) as err:
        raise MessageError(f"truncated sensor_msgs/msg/CompressedImage ({err})") from None
    if 4 + off + n > len(mv):
        raise MessageError(f"compressed data runs past the message end ({4 + off + n} > {len(mv)} bytes)")
    return _compressed(stamp, frame_id, fmt, mv[4 + off:4 + off + n])


def parse_image(wire: str, compressed: bool, data: bytes | memoryview) -> ImageMsg:
    """An Image (compressed: a CompressedImage) message of the wire format "ros1" | "cdr" (a CDR message
    compressed alone with zstd is decompressed first)."""
    if wire == "cdr":
        try:
            data = unwrap(data)
        except ValueError as e:
            raise MessageError(str(e)) from None
    if compressed:
        return parse_ros1_compressed(data) if wire == "ros1" else parse_cdr_compressed(data)
    return parse_ros1_image(data) if wire == "ros1" else parse_cdr_image(data)


def decompressed(msg: ImageMsg) -> ImageMsg:
    """The message with its pixels decoded (itself when they are raw); MessageError when they do not decode to
    the size its header gives."""
    if not msg.compression:
        return msg
    if msg.compression == "zstd":
        try:
            raw = zstd_decompress(msg.data)
        except ValueError as e:
            raise MessageError(str(e)) from None
        return replace(msg, data=memoryview(raw), compression="")
    payload = msg.data[DEPTH_HEADER_BYTES:] if msg.compression == "depth" else msg.data
    arr = cv2.imdecode(np.frombuffer(payload, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise MessageError("compressed image does not decode")
    if arr.shape[:2] != (msg.height, msg.width):
        raise MessageError(f"compressed image decodes to {arr.shape[1]}x{arr.shape[0]}, its header says "
                           f"{msg.width}x{msg.height}")
    if msg.compression == "depth":
        if arr.dtype != np.uint16 or arr.ndim != 2:
            raise MessageError(f"compressedDepth image is {arr.dtype} with {arr.shape[2:] or 1} channels, "
                               "not 16-bit single-channel")
        if msg.encoding.lower() == FLOAT_DEPTH:  # quantised inverse depth
            a, b = struct.unpack_from("<ff", msg.data, 4)
            inv = arr.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.where(arr > 0, np.float32(a) / (inv - np.float32(b)), np.float32(0.0)).astype(np.float32)
            return replace(msg, encoding=FLOAT_DEPTH, is_bigendian=False, step=msg.width * 4,
                           data=z.reshape(-1).view(np.uint8).data, compression="")
        return replace(msg, encoding="16uc1", is_bigendian=False, step=msg.width * 2,
                       data=arr.reshape(-1).view(np.uint8).data, compression="")
    if arr.dtype != np.uint8:
        raise MessageError(f"compressed colour image is {arr.dtype}, not 8-bit")
    channels = 1 if arr.ndim == 2 else arr.shape[2]
    encoding = {1: "mono8", 3: "bgr8", 4: "bgra8"}.get(channels)  # OpenCV decodes to BGR order
    if encoding is None:
        raise MessageError(f"compressed colour image has {channels} channels")
    return replace(msg, encoding=encoding, is_bigendian=False, step=msg.width * channels,
                   data=np.ascontiguousarray(arr).reshape(-1).data, compression="")


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
    msg = decompressed(msg)
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
    msg = decompressed(msg)
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
