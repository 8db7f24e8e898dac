"""ROS recordings (ROS 1 bags, rosbag2): sensor_msgs Image (or CompressedImage) topics with their CameraInfo,
extrinsics from TF.

Topics are found by type, as image_transport and the camera drivers lay them out (realsense2_camera:
/camera/camera/color/image_raw, /camera/camera/depth/image_rect_raw,
/camera/camera/aligned_depth_to_color/image_raw, each with a sibling camera_info topic):

- images: sensor_msgs Image topics, and CompressedImage ones (image_transport's `compressed` PNG / JPEG and
  `compressedDepth` PNG, e.g. .../image_raw/compressed, .../image_rect_raw/compressedDepth) unless the raw
  topic they were compressed from is recorded too (then that one is read).
- colour: image topics whose encoding is colour (rgb8, bgr8, rgba8, bgra8, yuyv, uyvy); grey (mono8)
  topics only when chosen with --color-topic. Depth: 16UC1 / mono16 (millimetres, REP 118) or 32FC1
  (metres). Several candidates: those whose name says colour ("color", "colour", "rgb") or depth
  ("depth") are kept, then, for depth, the ones already registered to the colour camera (same optical
  frame, e.g. aligned_depth_to_color); a choice that is still not unique is refused, naming the options.
- intrinsics: the CameraInfo topic beside each image topic (`<namespace>/camera_info`; for a compressed topic,
  beside the raw topic it was compressed from), first message.
- depth-to-colour extrinsics: none needed when both images are in one optical frame (header frame_id);
  otherwise the chain of transforms between the two frames on /tf_static (tf2_msgs/TFMessage), or
  realsense2_camera's `extrinsics/depth_to_color` message (rotation column-major, as librealsense's).
"""
from __future__ import annotations

import logging
from collections import deque
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.geometry.transforms import inv_T
from gscan.io.recordings.messages import (
    COLOR_ENCODINGS,
    FLOAT_DEPTH,
    ImageMsg,
    MessageError,
    encoding_kind,
    parse_image,
)
from gscan.io.recordings.source import MessageSource
from gscan.io.recordings.streams import StreamSetup, camera_info_intrinsics, recorded_depth_camera, transform_msg_T

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
TRANSPORTS = ("compressed", "compressedDepth")  # image_transport's sub-topics read
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
EXTRINSICS = ("realsense2_camera_msgs/msg/Extrinsics", "realsense2_camera/msg/Extrinsics")
COLOR_WORDS = ("color", "colour", "rgb")


def first_image(src: MessageSource, topic: str, compressed: bool) -> ImageMsg | None:
    """The first message of an image topic, parsed (None when the topic is empty or its message is unreadable)."""
    for _, _, data in src.messages([topic]):
        try:
            return parse_image(src.wire, compressed, data)
        except MessageError:
            return None
    return None


def _raw_topic(topic: str) -> str:
    """The topic a compressed image topic was compressed from (image_transport: <raw>/compressed)."""
    base, _, last = topic.rpartition("/")
    return base if last in TRANSPORTS and base else topic


def camera_info_topic(image_topic: str, compressed: bool = False) -> str:
    """image_transport's convention: the CameraInfo topic beside an image topic (beside its raw topic when it is
    a compressed one)."""
    ns = (_raw_topic(image_topic) if compressed else image_topic).rsplit("/", 1)[0]
    return f"{ns}/camera_info"


def image_topics(topics: dict[str, str]) -> tuple[list[str], frozenset[str]]:
    """The image topics to choose from and which of them are compressed: Image topics, and CompressedImage ones
    of image_transport whose raw topic is not recorded."""
    raw = [t for t, ty in topics.items() if ty == IMAGE]
    compressed = frozenset(t for t, ty in topics.items() if ty == COMPRESSED_IMAGE
                           and t.rpartition("/")[2] in TRANSPORTS and topics.get(_raw_topic(t)) != IMAGE)
    return sorted(raw) + sorted(compressed), compressed


def _listing(topics: list[str]) -> str:
    return ", ".join(topics) if topics else "none"


def _encodings_listing(firsts: dict[str, ImageMsg | None]) -> str:
    """The Image topics with the encoding of their first message, an encoding gscan does not read said so."""
    def one(topic: str) -> str:
        msg = firsts[topic]
        if msg is None:
            return topic
        kind = encoding_kind(msg.encoding)
        return f"{topic} ({msg.encoding}{'' if kind else ': an encoding gscan does not read'})"

    return _listing([one(t) for t in sorted(firsts)])


def _narrow(cands: list[str], words: tuple[str, ...]) -> list[str]:
    named = [t for t in cands if any(w in t.lower() for w in words)]
    return named if named else cands


def _choose_color(path: Path, firsts: dict[str, ImageMsg | None], chosen: str | None) -> str:
    images = sorted(firsts)
    if chosen is not None:
        if chosen not in firsts:
            raise InputError(path, f"--color-topic {chosen}: no such sensor_msgs/Image topic "
                             f"(Image topics: {_listing(images)})")
        return chosen
    cands = [t for t in images if firsts[t] is not None and encoding_kind(firsts[t].encoding) == "color"]  # type: ignore[union-attr]
    if not cands:
        raise InputError(path, f"no colour image topic (Image topics: {_encodings_listing(firsts)}; "
                         f"colour encodings read: {', '.join(COLOR_ENCODINGS)}; "
                         "grey ones can be chosen with --color-topic)")
    cands = _narrow(cands, COLOR_WORDS)
    if len(cands) > 1:
        raise InputError(path, f"several colour image topics ({', '.join(cands)}); choose one with --color-topic")
    return cands[0]


def _choose_depth(path: Path, firsts: dict[str, ImageMsg | None], chosen: str | None, color: str,
                  color_first: ImageMsg) -> str:
    images = sorted(firsts)
    if chosen is not None:
        if chosen not in firsts:
            raise InputError(path, f"--depth-topic {chosen}: no such sensor_msgs/Image topic "
                             f"(Image topics: {_listing(images)})")
        return chosen
    cands = [t for t in images if t != color and firsts[t] is not None
             and encoding_kind(firsts[t].encoding) == "depth"]  # type: ignore[union-attr]
    if not cands:
        raise InputError(path, f"no depth image topic (16UC1, mono16 or 32FC1; Image topics: {_listing(images)})")
    cands = _narrow(cands, ("depth",))
    if len(cands) > 1:  # prefer depth already registered to the colour camera (aligned_depth_to_color)
        frame = color_first.frame_id
        registered = [t for t in cands if frame and firsts[t].frame_id == frame  # type: ignore[union-attr]
                      and (firsts[t].width, firsts[t].height) == (color_first.width, color_first.height)]  # type: ignore[union-attr]
        cands = registered if len(registered) == 1 else cands
    if len(cands) > 1:
        raise InputError(path, f"several depth image topics ({', '.join(cands)}); choose one with --depth-topic")
    return cands[0]


def _tf_edges(src: MessageSource, topics: dict[str, str]) -> dict[tuple[str, str], np.ndarray]:
    """(parent, child) -> T_parent_child from the static transforms (topics of type TFMessage named tf_static)."""
    edges: dict[tuple[str, str], np.ndarray] = {}
    tf_topics = [t for t, ty in topics.items() if ty == TF_MESSAGE and t.rstrip("/").endswith("tf_static")]
    for t, _, data in src.messages(tf_topics):
        for ts in src.decode(t, data).transforms:
            parent, child = ts.header.frame_id.lstrip("/"), ts.child_frame_id.lstrip("/")
            try:
                edges.setdefault((parent, child), transform_msg_T(ts.transform))
            except (ValueError, AttributeError) as e:
                log.warning("%s: %s: transform %s -> %s ignored (%s)", src.path, t, parent, child, e)
    return edges


def tf_chain(edges: dict[tuple[str, str], np.ndarray], target: str, source: str) -> np.ndarray | None:
    """T_target_source [4 x 4] through the transform tree (either direction of every edge), None when the
    two frames are not connected."""
    adj: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (p, c), T in edges.items():
        adj.setdefault(p, []).append((c, T))        # a point in c maps into p by T_p_c
        adj.setdefault(c, []).append((p, inv_T(T)))
    if source not in adj or target not in adj:
        return None
    # BFS from target: T_target_f for every reachable frame f
    seen = {target: np.eye(4)}
    queue = deque([target])
    while queue:
        f = queue.popleft()
        for g, T_f_g in adj[f]:
            if g not in seen:
                seen[g] = seen[f] @ T_f_g
                queue.append(g)
    return seen.get(source)


def _realsense_extrinsics(src: MessageSource, topics: dict[str, str]) -> np.ndarray | None:
    """realsense2_camera's depth_to_color Extrinsics (rotation column-major 3x3, translation m) as T_color_depth."""
    for t, ty in sorted(topics.items()):
        if ty in EXTRINSICS and t.endswith("depth_to_color"):
            for tt, _, data in src.messages([t]):
                msg = src.decode(tt, data)
                T = np.eye(4)
                T[:3, :3] = np.asarray(msg.rotation, dtype=np.float64).reshape(3, 3).T
                T[:3, 3] = np.asarray(msg.translation, dtype=np.float64)
                if np.all(np.isfinite(T)):
                    return T
    return None


def ros_setup(src: MessageSource, color_topic: str | None = None, depth_topic: str | None = None) -> StreamSetup:
    """The colour and depth streams of a ROS 1 bag or rosbag2 (see the module docstring)."""
    topics = src.topics()
    images, compressed = image_topics(topics)
    if not images:
        other = sorted(t for t, ty in topics.items() if ty == COMPRESSED_IMAGE)
        hint = (f" (CompressedImage topics {', '.join(other)} are not image_transport's "
                f"{' or '.join(TRANSPORTS)} sub-topics)") if other else ""
        raise InputError(src.path, f"no sensor_msgs/Image or CompressedImage topic in the recording{hint}")
    firsts = {t: first_image(src, t, t in compressed) for t in images}
    color = _choose_color(src.path, firsts, color_topic)
    cfirst = firsts[color]
    if cfirst is None:
        raise InputError(src.path, f"topic {color}: no readable image message")
    depth = _choose_depth(src.path, firsts, depth_topic, color, cfirst)
    dfirst = firsts[depth]
    if dfirst is None:
        raise InputError(src.path, f"topic {depth}: no readable image message")
    if color == depth:
        raise InputError(src.path, f"--color-topic and --depth-topic are the same topic {color}")
    intr = {}
    for topic in (color, depth):
        info = camera_info_topic(topic, topic in compressed)
        if topics.get(info) != CAMERA_INFO:
            raise InputError(src.path, f"no CameraInfo for {topic} (topic {info} missing)")
        msg = None
        for t, _, data in src.messages([info]):
            msg = src.decode(t, data)
            break
        if msg is None:
            raise InputError(src.path, f"no CameraInfo for {topic} (topic {info} holds no message)")
        intr[topic] = camera_info_intrinsics(msg, info, src.path)
    kind = "ROS 1 bag" if src.wire == "ros1" else "rosbag2"
    scale = 1.0 if dfirst.encoding.lower() == FLOAT_DEPTH else 0.001
    cframe, dframe = cfirst.frame_id.lstrip("/"), dfirst.frame_id.lstrip("/")
    if cframe == dframe:
        T = np.eye(4)
        if not cframe and (intr[color].width, intr[color].height) != (intr[depth].width, intr[depth].height):
            raise InputError(src.path, f"{depth} and {color} have no frame_id and differ in size: "
                             "cannot tell how depth maps onto colour")
    else:
        T_cd = tf_chain(_tf_edges(src, topics), cframe, dframe)
        if T_cd is None:
            T_cd = _realsense_extrinsics(src, topics)
        if T_cd is None:
            raise InputError(src.path, f"depth {depth} (frame '{dframe}') and colour {color} (frame '{cframe}') are "
                             "in different camera frames and the recording holds no transform between them "
                             "(/tf_static)")
        T = T_cd
    return StreamSetup(kind, color, depth, intr[color], recorded_depth_camera(intr[depth], T, src.path), scale,
                       compressed & {color, depth})
