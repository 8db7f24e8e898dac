"""The RealSense `.bag` layout (librealsense's recorder and realsense-viewer; file format versions 2-4).

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
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.geometry.transforms import inv_T
from gscan.io.recordings.source import MessageSource
from gscan.io.recordings.streams import StreamSetup, camera_info_intrinsics, recorded_depth_camera, transform_msg_T

_DATA = re.compile(r"^/device_(\d+)/sensor_(\d+)/([A-Za-z]+)_(\d+)/image/data$")
_TF = re.compile(r"^(?P<prefix>/device_\d+/sensor_\d+/[A-Za-z]+_\d+)/tf/(?P<group>\d+)$")


def is_realsense(topics: dict[str, str]) -> bool:
    """The recording uses librealsense's topic layout (its /file_version topic and stream image topics)."""
    return "/file_version" in topics and any(_DATA.match(t) for t in topics)


def _prefix(topic: str) -> str:
    return topic[: -len("/image/data")]


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
            value = float(_first(src, topic).data)  # type: ignore[attr-defined]
            return float(str(np.float32(value)))  # the float32 option as written (0.001, not 0.0010000000474974513)
    prop = f"{sensor}/property"
    if prop in topics:  # file format version 2
        for t, _, data in src.messages([prop]):
            kv = src.decode(t, data)
            if kv.key == "Depth Units":
                return float(kv.value)
    return None


def _extrinsics(src: MessageSource, topics: dict[str, str], color_prefix: str, depth_prefix: str) -> np.ndarray:
    """T_color_depth [4 x 4] from the two streams' tf messages in a common extrinsics group."""
    groups: dict[str, dict[str, str]] = {}
    for t in topics:
        m = _TF.match(t)
        if m:
            groups.setdefault(m["group"], {})[m["prefix"]] = t
    for g in sorted(groups, key=int):
        if color_prefix in groups[g] and depth_prefix in groups[g]:
            try:
                T_c_ref = transform_msg_T(_first(src, groups[g][color_prefix]))
                T_d_ref = transform_msg_T(_first(src, groups[g][depth_prefix]))
            except (ValueError, AttributeError) as e:
                raise InputError(src.path, f"topic {groups[g][color_prefix]}: malformed extrinsics ({e})") from None
            return T_c_ref @ inv_T(T_d_ref)
    raise InputError(src.path, f"no extrinsics between {depth_prefix} and {color_prefix} "
                     f"(expected {depth_prefix}/tf/0 and {color_prefix}/tf/0)")


def realsense_setup(src: MessageSource, color_topic: str | None = None, depth_topic: str | None = None) -> StreamSetup:
    """The colour and depth streams of a RealSense bag (topics chosen, or the one Color and one Depth stream)."""
    topics = src.topics()
    color = pick_stream(src.path, topics, "Color", color_topic, "--color-topic")
    depth = pick_stream(src.path, topics, "Depth", depth_topic, "--depth-topic")
    if color == depth:
        raise InputError(src.path, f"--color-topic and --depth-topic are the same topic {color}")
    intr = {}
    for topic in (color, depth):
        info = f"{_prefix(topic)}/info/camera_info"
        if info not in topics:
            raise InputError(src.path, f"no CameraInfo for {topic} (topic {info} missing)")
        intr[topic] = camera_info_intrinsics(_first(src, info), info, src.path)
    sensor = _prefix(depth).rsplit("/", 1)[0]
    T = _extrinsics(src, topics, _prefix(color), _prefix(depth))
    return StreamSetup("RealSense bag", color, depth, intr[color], recorded_depth_camera(intr[depth], T, src.path),
                       _depth_units(src, topics, sensor))
