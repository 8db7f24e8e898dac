"""The RealSense recording layouts of librealsense's recorder and realsense-viewer: the ROS 1 `.bag` (SDK up to
2.57, file format versions 2-4) and the rosbag2 `.db3` (SDK 2.58 and later).

The `.bag`:
Topics (librealsense src/media/ros/ros_file_format.h), all under /device_0:
  /sensor_S/<Type>_<i>/image/data          sensor_msgs/Image frames (Depth: mono16 raw units, Color: rgb8 ...)
  /sensor_S/<Type>_<i>/info/camera_info    sensor_msgs/CameraInfo (K, size, distortion), one static message
  /sensor_S/<Type>_<i>/tf/<group>          geometry_msgs/Transform: the extrinsics from the group's reference
                                           stream (the first one registered, usually Depth) to this stream
  /sensor_S/option/Depth_Units/value       std_msgs/Float32: metres per depth unit ("Depth Units" in older
                                           files; /sensor_S/property KeyValue in version 2)
Static messages are written at time 0 (+1 ns), frames at their recording time; a frame's header stamp is
the camera's frame timestamp. A depth Image whose header version (frame_id) is "1" also carries its own
depth units (`gscan.io.recordings.messages`), which librealsense prefers to the option, as gscan does.

The `.db3` (ROS 2 CDR messages; 2.58 compresses every message alone with zstd, `gscan.io.recordings.source`
undoes that), under the same /device_0/sensor_S/<Type>_<i> prefixes:
  .../image/data                           sensor_msgs/Image (2.58: Depth mono16, Color as streamed)
  .../image/data/compressed                sensor_msgs/CompressedImage (2.59: colour as PNG, or zstd for
  .../image/data/compressedDepth           formats PNG cannot hold, e.g. YUYV; depth as compressedDepth PNG)
  .../image/camera_info                    sensor_msgs/CameraInfo beside every frame (2.59)
  .../camera_info                          std_msgs/String "width=..;height=..;fx=..;ppx=..;fy=..;ppy=..;
                                           model=..;coeffs=.." (both; read when no CameraInfo is recorded;
                                           its numbers written with 6 decimals)
  .../image/metadata                       std_msgs/String "Frame number=..;timestamp=<ms>;...": the
                                           camera's timestamp (the image header holds the recording time)
  .../tf/ref_<k>                           std_msgs/String "rotation=<9, column-major>;translation=<3>":
                                           the extrinsics from the reference stream to this one
  /device_0/sensor_S/option/Depth_Units/value   std_msgs/String, metres per depth unit ("%f": 6 decimals)
Frames are paired by the camera's timestamps, as librealsense's playback does; when colour and depth's are in
different domains (clocks) or missing, by their recording times (the image headers').
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.geometry.transforms import inv_T
from gscan.io.camera import Intrinsics, implausible_intrinsics
from gscan.io.recordings.source import MessageSource
from gscan.io.recordings.streams import StreamSetup, camera_info_intrinsics, recorded_depth_camera, transform_msg_T

log = logging.getLogger(__name__)

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
_DATA = re.compile(r"^/device_(\d+)/sensor_(\d+)/([A-Za-z]+)_(\d+)/image/data(/compressed|/compressedDepth)?$")
_TF = re.compile(r"^(?P<prefix>/device_\d+/sensor_\d+/[A-Za-z]+_\d+)/tf/(?P<group>(?:ref_)?\d+)$")
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
STRING = "std_msgs/msg/String"


def is_realsense(topics: dict[str, str]) -> bool:
    """The recording uses librealsense's topic layout (its /file_version topic and stream image topics)."""
    return "/file_version" in topics and any(_DATA.match(t) for t in topics)


def _prefix(topic: str) -> str:
    return topic[: topic.index("/image/data")]


def pick_stream(path: Path, topics: dict[str, str], stream_type: str, chosen: str | None, option: str) -> str:
    """The image data topic of the `stream_type` ("Color" | "Depth") stream, or the one chosen with `option`."""
    images = sorted(t for t in topics if _DATA.match(t))
    if chosen is not None:
        if chosen not in images:
            raise InputError(path, f"{option} {chosen}: no such image topic (image topics: {', '.join(images)})")
        return chosen
    found = [t for t in images if _DATA.match(t).group(3) == stream_type]  # type: ignore[union-attr]
    if not found:
        what = "colour" if stream_type == "Color" else "depth"
        raise InputError(path, f"no {what} stream ({stream_type}_N/image/data) in the recording "
                         f"(image topics: {', '.join(images) or 'none'})")
    if len(found) > 1:
        raise InputError(path, f"several {stream_type} streams ({', '.join(found)}); choose one with {option}")
    return found[0]


def _first(src: MessageSource, topic: str) -> object:
    for t, _, data in src.messages([topic]):
        return src.decode(t, data)
    raise InputError(src.path, f"topic {topic} holds no message")


def _depth_units(src: MessageSource, topics: dict[str, str], sensor: str) -> float | None:
    """The depth sensor's Depth Units option (metres per raw unit), None when the file has none."""
    for name in ("Depth_Units", "Depth Units"):
        topic = f"{sensor}/option/{name}/value"
        if topic in topics:
            msg = _first(src, topic)
            try:  # std_msgs Float32 in a .bag, a String in a .db3
                value = float(msg.data)  # type: ignore[attr-defined]
            except (TypeError, ValueError):
                raise InputError(src.path, f"topic {topic}: depth units {msg.data!r} are not a number") from None  # type: ignore[attr-defined]
            return float(str(np.float32(value)))  # the float32 option as written (0.001, not 0.0010000000474974513)
    prop = f"{sensor}/property"
    if prop in topics:  # file format version 2
        for t, _, data in src.messages([prop]):
            kv = src.decode(t, data)
            if kv.key == "Depth Units":
                return float(kv.value)
    return None


def _key_values(text: str) -> dict[str, str]:
    """librealsense's "key=value;key=value" strings as a dict."""
    return {k.strip(): v.strip() for k, _, v in (item.partition("=") for item in text.split(";")) if k.strip()}


def _floats(values: str, n: int, what: str) -> list[float]:
    out = [float(v) for v in values.split(",")]
    if len(out) != n or not all(np.isfinite(out)):
        raise ValueError(f"{what} holds {len(out)} values, {n} finite ones expected")
    return out


def _string_extrinsics(text: str) -> np.ndarray:
    """T_stream_ref [4 x 4] of a .db3 tf string "rotation=r0,..,r8;translation=x,y,z" (rs2_extrinsics: the
    rotation column-major); the rotation, written with 6 decimals, is made orthonormal again (nearest rotation)."""
    kv = _key_values(text)
    R = np.asarray(_floats(kv.get("rotation", ""), 9, "rotation"), dtype=np.float64).reshape(3, 3).T
    U, _, Vt = np.linalg.svd(R)
    if np.linalg.det(U @ Vt) < 0 or not np.allclose(R, U @ Vt, atol=1e-4):
        raise ValueError("rotation is not a rotation matrix")
    T = np.eye(4)
    T[:3, :3] = U @ Vt
    T[:3, 3] = _floats(kv.get("translation", ""), 3, "translation")
    return T


def _transform(src: MessageSource, topics: dict[str, str], topic: str) -> np.ndarray:
    msg = _first(src, topic)
    return _string_extrinsics(msg.data) if topics[topic] == STRING else transform_msg_T(msg)  # type: ignore[attr-defined]


def _extrinsics(src: MessageSource, topics: dict[str, str], color_prefix: str, depth_prefix: str) -> np.ndarray:
    """T_color_depth [4 x 4] from the two streams' tf messages in a common extrinsics group."""
    groups: dict[str, dict[str, str]] = {}
    for t in topics:
        m = _TF.match(t)
        if m:
            groups.setdefault(m["group"], {})[m["prefix"]] = t
    for g in sorted(groups, key=lambda g: (len(g), g)):
        if color_prefix in groups[g] and depth_prefix in groups[g]:
            try:
                T_c_ref = _transform(src, topics, groups[g][color_prefix])
                T_d_ref = _transform(src, topics, groups[g][depth_prefix])
            except (ValueError, AttributeError) as e:
                raise InputError(src.path, f"topic {groups[g][color_prefix]}: malformed extrinsics ({e})") from None
            return T_c_ref @ inv_T(T_d_ref)
    raise InputError(src.path, f"no extrinsics between {depth_prefix} and {color_prefix} "
                     f"(expected {depth_prefix}/tf/<group> and {color_prefix}/tf/<group> of one group)")


def _string_intrinsics(text: str, topic: str, path: Path) -> Intrinsics:
    """The intrinsics of a .db3 camera_info string ("width=..;height=..;fx=..;ppx=..;fy=..;ppy=..;model=..;
    coeffs=.."); distortion is not applied (logged when not zero), as for a CameraInfo."""
    kv = _key_values(text)
    try:
        w, h = int(kv["width"]), int(kv["height"])
        K = np.array([[float(kv["fx"]), 0.0, float(kv["ppx"])], [0.0, float(kv["fy"]), float(kv["ppy"])],
                      [0.0, 0.0, 1.0]])
        coeffs = [float(c) for c in kv.get("coeffs", "").split(",") if c.strip()]
    except (KeyError, ValueError) as e:
        raise InputError(path, f"topic {topic}: malformed camera_info string {text[:120]!r} ({e})") from None
    if not np.all(np.isfinite(K)) or w <= 0 or h <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"topic {topic}: camera_info holds no calibration ({text[:120]!r})")
    why = implausible_intrinsics(K, w, h)
    if why:
        raise InputError(path, f"topic {topic}: camera_info {why}")
    if any(abs(c) > 1e-6 for c in coeffs):
        log.warning("%s: topic %s: %s distortion coefficients %s are not applied (pinhole model)", path, topic,
                    kv.get("model", "unnamed"), coeffs)
    return Intrinsics.from_matrix(K, w, h)


def _intrinsics(src: MessageSource, topics: dict[str, str], image_topic: str) -> Intrinsics:
    """A stream's intrinsics: its CameraInfo (.bag: info/camera_info; .db3 2.59: image/camera_info), else the
    .db3's camera_info string."""
    prefix = _prefix(image_topic)
    for info in (f"{prefix}/info/camera_info", f"{prefix}/image/camera_info"):
        if topics.get(info) == CAMERA_INFO:
            return camera_info_intrinsics(_first(src, info), info, src.path)
    info = f"{prefix}/camera_info"
    if topics.get(info) == STRING:
        return _string_intrinsics(str(_first(src, info).data), info, src.path)  # type: ignore[attr-defined]
    raise InputError(src.path, f"no CameraInfo for {image_topic} (none of the topics {prefix}/info/camera_info, "
                     f"{prefix}/image/camera_info, {prefix}/camera_info)")


def _camera_stamps(src: MessageSource, topics: dict[str, str], image_topic: str) -> tuple[dict[int, int], str] | None:
    """({log time (ns): the camera's timestamp (ns)}, the timestamps' domain) of a .db3 stream's frames, from its
    image/metadata strings ("timestamp=<ms>", "timestamp_domain=..."); None for a .bag (its image headers carry
    the camera's timestamps) or when the stream's metadata holds no timestamp."""
    topic = f"{_prefix(image_topic)}/image/metadata"
    if src.wire == "ros1" or topics.get(topic) != STRING:
        return None
    stamps: dict[int, int] = {}
    domains: set[str] = set()
    for t, log_ns, data in src.messages([topic]):
        kv = _key_values(str(src.decode(t, data).data))
        try:
            ms = float(kv.get("timestamp", "nan"))
        except ValueError:
            ms = float("nan")
        if np.isfinite(ms):
            stamps.setdefault(log_ns, round(ms * 1e6))
            domains.add(kv.get("timestamp_domain", ""))
    return (stamps, " / ".join(sorted(domains))) if stamps else None


def _pairing_stamps(src: MessageSource, topics: dict[str, str], color: str, depth: str) -> dict[str, dict[int, int]]:
    """The camera timestamps of both streams of a .db3 when both have them in one domain (then the frames are
    paired by them); otherwise none (paired by the recording times in the image headers), said in the log."""
    if src.wire == "ros1":
        return {}
    cs, ds = _camera_stamps(src, topics, color), _camera_stamps(src, topics, depth)
    if cs is None or ds is None:
        log.warning("%s: %s carries no camera timestamps; colour and depth are paired by their recording times",
                    src.path, color if cs is None else depth)
        return {}
    if cs[1] != ds[1]:
        log.warning("%s: colour timestamps are %s, depth's %s: colour and depth are paired by their recording "
                    "times", src.path, cs[1] or "of no domain", ds[1] or "of no domain")
        return {}
    return {color: cs[0], depth: ds[0]}


def realsense_setup(src: MessageSource, color_topic: str | None = None, depth_topic: str | None = None) -> StreamSetup:
    """The colour and depth streams of a RealSense recording (topics chosen, or the one Color and one Depth
    stream)."""
    topics = src.topics()
    color = pick_stream(src.path, topics, "Color", color_topic, "--color-topic")
    depth = pick_stream(src.path, topics, "Depth", depth_topic, "--depth-topic")
    if color == depth:
        raise InputError(src.path, f"--color-topic and --depth-topic are the same topic {color}")
    intr = {topic: _intrinsics(src, topics, topic) for topic in (color, depth)}
    sensor = _prefix(depth).rsplit("/", 1)[0]
    T = _extrinsics(src, topics, _prefix(color), _prefix(depth))
    compressed = frozenset(t for t in (color, depth) if topics[t] == COMPRESSED_IMAGE)
    stamps = _pairing_stamps(src, topics, color, depth)
    kind = "RealSense bag" if src.wire == "ros1" else "RealSense rosbag2"
    return StreamSetup(kind, color, depth, intr[color], recorded_depth_camera(intr[depth], T, src.path),
                       _depth_units(src, topics, sensor), compressed, stamps)
