"""Rendered frames written as the recordings cameras and ROS write (for tests and benchmarks).

- `write_realsense_bag`: a ROS 1 bag in librealsense's recorder layout (file format version 4, the topics
  and message types of src/media/ros/ros_file_format.h and ros_writer.cpp), written with rosbags' ROS 1
  writer; pyrealsense2's playback device opens it (`rs.config.enable_device_from_file`).
- `write_rosbag2`: a rosbag2 folder (metadata.yaml + .db3 or .mcap) written with rosbags' rosbag2 writer,
  in realsense2_camera's ROS 2 topic layout (/camera/camera/color/image_raw, .../depth/image_rect_raw,
  .../aligned_depth_to_color/image_raw, sibling camera_info topics, /tf_static).
- `write_mcap`: the same messages in a bare MCAP file written with the `mcap` package's writer (schemas
  "ros2msg", messages CDR-encoded, as rosbag2's MCAP storage plugin writes them).
  Both can write the images as image_transport's CompressedImage topics instead (`transport="compressed"`:
  colour .../image_raw/compressed as PNG, "rgb8; png compressed bgr8"; depth .../compressedDepth as
  "16UC1; compressedDepth png", a 12-byte header and a 16-bit PNG), as `ros2 bag record` of a camera
  driver's compressed topics stores them.

Frames are given as an iterable (written one by one, so long recordings need no memory): each a
`RecordingFrame` with an RGB colour image, raw uint16 depth (units of `depth_units` metres) and a time.
Depth may come from another camera than colour (`depth_camera`: its intrinsics and T_color_depth).
"""
from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gscan.geometry.transforms import inv_T
from gscan.io.camera import DepthCamera, Intrinsics

REALSENSE_FILE_VERSION = 4
STATIC_NS = 1  # librealsense writes its static messages at ros::TIME_MIN (0 s + 1 ns)
STREAM_INFO_MSG = "uint32 fps\nstring encoding\nbool is_recommended\n"  # realsense_msgs/StreamInfo
EXTRINSICS_MSG = "std_msgs/Header header\nfloat64[9] rotation\nfloat64[3] translation\n"  # realsense2_camera_msgs
# rotation of an optical frame (x right, y down, z forward) in its ROS body frame (x forward, y left, z up)
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
ROS_NS = "/camera/camera"


@dataclass
class RecordingFrame:
    """color: [H x W x 3] uint8 RGB; depth: [Hd x Wd] uint16 raw depth; t_ns: capture time (ns since the epoch).

    color or depth None leaves that message out; depth_t_ns: the depth image's time when it differs from t_ns.
    """

    color: np.ndarray | None
    depth: np.ndarray | None
    t_ns: int
    depth_t_ns: int | None = None


def depth_to_raw(depth_m: np.ndarray, depth_units: float = 0.001) -> np.ndarray:
    """[H x W] metres -> [H x W] uint16 raw units (rounded, 0 stays invalid)."""
    return np.clip(np.rint(np.asarray(depth_m, dtype=np.float64) / depth_units), 0, 65535).astype(np.uint16)


def _rot_to_quat(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return float(x), float(y), float(z), float(w)


class _Msgs:
    """Message constructors of a rosbags typestore (ROS 1 Noetic or ROS 2 Humble field names)."""

    def __init__(self, ros1: bool):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.ts.register(get_types_from_msg(STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
        self.ts.register(get_types_from_msg(EXTRINSICS_MSG, "realsense2_camera_msgs/msg/Extrinsics"))
        self.T = self.ts.types

    def header(self, t_ns: int, frame_id: str, seq: int = 0) -> Any:
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))
        H = self.T["std_msgs/msg/Header"]
        return H(seq=seq, stamp=stamp, frame_id=frame_id) if self.ros1 else H(stamp=stamp, frame_id=frame_id)

    def image(self, header: Any, pixels: np.ndarray, encoding: str) -> Any:
        h, w = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        return self.T["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                                               step=int(data.size // h), data=data)

    def compressed_image(self, header: Any, pixels: np.ndarray, encoding: str) -> Any:
        """image_transport's CompressedImage of an RGB (rgb8) or 16-bit depth (16UC1) image, PNG-coded."""
        import cv2

        depth = pixels.dtype == np.uint16
        ok, png = cv2.imencode(".png", pixels if depth else cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR))
        assert ok
        if depth:  # compressed_depth_image_transport's ConfigHeader: format PNG (0), depthQuantA, depthQuantB
            data = np.concatenate([np.frombuffer(struct.pack("<iff", 0, 0.0, 0.0), np.uint8), png.reshape(-1)])
            fmt = f"{encoding}; compressedDepth png"
        else:
            data, fmt = png.reshape(-1), f"{encoding}; png compressed bgr8"
        return self.T["sensor_msgs/msg/CompressedImage"](header=header, format=fmt, data=data)

    def camera_info(self, header: Any, intr: Intrinsics, distortion_model: str) -> Any:
        ROI = self.T["sensor_msgs/msg/RegionOfInterest"]
        P = np.hstack([intr.K, np.zeros((3, 1))]).ravel()
        kw = {"header": header, "height": intr.height, "width": intr.width, "distortion_model": distortion_model,
              "binning_x": 0, "binning_y": 0, "roi": ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)}
        arrays = {"d": np.zeros(5), "k": intr.K.ravel(), "r": np.eye(3).ravel(), "p": P}
        kw.update({k.upper() if self.ros1 else k: v for k, v in arrays.items()})
        return self.T["sensor_msgs/msg/CameraInfo"](**kw)

    def transform(self, T: np.ndarray) -> Any:
        x, y, z, w = _rot_to_quat(T[:3, :3])
        V3, Q = self.T["geometry_msgs/msg/Vector3"], self.T["geometry_msgs/msg/Quaternion"]
        return self.T["geometry_msgs/msg/Transform"](
            translation=V3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])), rotation=Q(x=x, y=y, z=z, w=w))

    def serialize(self, msg: Any, typename: str) -> bytes:
        return bytes(self.ts.serialize_ros1(msg, typename) if self.ros1 else self.ts.serialize_cdr(msg, typename))


def write_realsense_bag(path: str | Path, frames: Iterable[RecordingFrame], color_intrinsics: Intrinsics,
                        depth_camera: DepthCamera | None = None, depth_units: float = 0.001, fps: int = 30,
                        color_encoding: str = "rgb8",
                        depth_units_option: bool = True, camera_info: bool = True, compress: bool = False,
                        streams: tuple[str, ...] = ("Depth", "Color"), chunk_bytes: int | None = None) -> Path:
    """A RealSense .bag of `frames` (see the module docstring); returns its path.

    depth_camera: the depth stream's camera, of the depth images' size (None: depth registered to colour).
    depth_units_option=False leaves out the Depth Units option (bad-input tests); camera_info=False the CameraInfo
    topics; streams the streams recorded ("Depth", "Color"); compress chunks the bag with LZ4 as the recorder's
    compression option does; chunk_bytes: the size at which a chunk is closed (None: rosbags' 1 MiB).
    """
    from rosbags.rosbag1 import Writer

    path = Path(path)
    depth_camera = depth_camera or DepthCamera(color_intrinsics)
    depth_intrinsics, T_cd = depth_camera.intrinsics, depth_camera.T_color_depth
    m = _Msgs(ros1=True)
    T = m.T
    w = Writer(path)
    if compress:
        w.set_compression(Writer.CompressionFormat.LZ4)
    if chunk_bytes is not None:
        w.chunk_threshold = chunk_bytes
    conns: dict[str, Any] = {}

    def put(topic: str, typ: str, t_ns: int, msg: Any, extra: bytes = b"") -> None:
        if topic not in conns:
            conns[topic] = w.add_connection(topic, typ, typestore=m.ts)
        w.write(conns[topic], t_ns, m.serialize(msg, typ) + extra)

    KV = T["diagnostic_msgs/msg/KeyValue"]
    with w:
        put("/file_version", "std_msgs/msg/UInt32", STATIC_NS, T["std_msgs/msg/UInt32"](data=REALSENSE_FILE_VERSION))
        for k, v in (("Name", "Intel RealSense D435"), ("Serial Number", "000000000000"),
                     ("Firmware Version", "5.13.0.50"), ("Product Id", "0B07"), ("Product Line", "D400")):
            put("/device_0/info", "diagnostic_msgs/msg/KeyValue", STATIC_NS, KV(key=k, value=v))
        infos = (("/device_0/sensor_0", "Depth_0", "mono16", depth_intrinsics, np.eye(4), "Stereo Module"),
                   ("/device_0/sensor_1", "Color_0", color_encoding, color_intrinsics, T_cd, "RGB Camera"))
        for sensor, stream, enc, intr, T_s_ref, sensor_name in infos:
            if stream.split("_")[0] not in streams:
                continue
            put(f"{sensor}/info", "diagnostic_msgs/msg/KeyValue", STATIC_NS, KV(key="Name", value=sensor_name))
            put(f"{sensor}/{stream}/info", "realsense_msgs/msg/StreamInfo", STATIC_NS,
                T["realsense_msgs/msg/StreamInfo"](fps=fps, encoding=enc, is_recommended=True))
            if camera_info:
                model = "Brown Conrady" if stream.startswith("Depth") else "Inverse Brown Conrady"
                put(f"{sensor}/{stream}/info/camera_info", "sensor_msgs/msg/CameraInfo", STATIC_NS,
                    m.camera_info(m.header(0, ""), intr, model))
            put(f"{sensor}/{stream}/tf/0", "geometry_msgs/msg/Transform", STATIC_NS, m.transform(T_s_ref))
        if depth_units_option:
            put("/device_0/sensor_0/option/Depth_Units/value", "std_msgs/msg/Float32", STATIC_NS,
                T["std_msgs/msg/Float32"](data=float(depth_units)))
            put("/device_0/sensor_0/option/Depth_Units/description", "std_msgs/msg/String", STATIC_NS,
                T["std_msgs/msg/String"](data="Number of meters represented by a single depth unit"))
        t0 = None
        for i, f in enumerate(frames):
            t0 = f.t_ns if t0 is None else t0
            for sensor, stream, enc, pixels, units, t_ns in (
                    ("/device_0/sensor_0", "Depth_0", "mono16", f.depth, depth_units, f.depth_t_ns or f.t_ns),
                    ("/device_0/sensor_1", "Color_0", color_encoding, f.color, 0.0, f.t_ns)):
                if pixels is None or stream.split("_")[0] not in streams:
                    continue
                log_ns = t_ns - t0 + 1_000_000  # the recorder's clock starts with the recording
                stamp_ms = t_ns / 1e6  # the frame timestamp (ms), which librealsense stores in the header stamp
                # header version "1": librealsense's Image carries its depth units after the pixels
                img = np.asarray(pixels, dtype="<u2") if enc == "mono16" else pixels
                msg = m.image(m.header(round(stamp_ms * 1e6), "1", seq=i), img, enc)
                put(f"{sensor}/{stream}/image/data", "sensor_msgs/msg/Image", log_ns, msg, struct.pack("<f", units))
                md = f"{sensor}/{stream}/image/metadata"
                put(md, "diagnostic_msgs/msg/KeyValue", log_ns, KV(key="system_time", value=f"{stamp_ms:.6f}"))
                put(md, "diagnostic_msgs/msg/KeyValue", log_ns, KV(key="timestamp_domain", value="Global Time"))
                put(md, "diagnostic_msgs/msg/KeyValue", log_ns, KV(key="Frame Counter", value=str(i)))
    return path


def _ros2_messages(frames: Iterable[RecordingFrame], color_intrinsics: Intrinsics, depth_camera: DepthCamera | None,
                   topics: tuple[str, ...], extrinsics: str, m: _Msgs, color_encoding: str = "rgb8",
                   transport: str = "raw") -> Iterable[tuple[str, str, int, Any]]:
    """(topic, type, log time, message) of a realsense2_camera recording, static ones first."""
    depth_camera = depth_camera or DepthCamera(color_intrinsics)
    depth_intrinsics, T_color_depth = depth_camera.intrinsics, depth_camera.T_color_depth
    cframe, dframe = "camera_color_optical_frame", "camera_depth_optical_frame"
    first = True
    for f in frames:
        if first:
            first = False
            if extrinsics == "tf_static":
                # camera_link -> camera_depth_frame -> camera_depth_optical_frame, and the colour chain, such that
                # the two optical frames are T_color_depth apart
                T_opt = np.eye(4)
                T_opt[:3, :3] = R_BODY_OPTICAL
                T_link_dopt = T_opt
                T_link_copt = T_link_dopt @ inv_T(T_color_depth)
                TS = m.T["geometry_msgs/msg/TransformStamped"]
                tfs = [TS(header=m.header(f.t_ns, "camera_link"), child_frame_id="camera_depth_frame",
                          transform=m.transform(np.eye(4))),
                       TS(header=m.header(f.t_ns, "camera_depth_frame"), child_frame_id=dframe,
                          transform=m.transform(T_opt)),
                       TS(header=m.header(f.t_ns, "camera_link"), child_frame_id="camera_color_frame",
                          transform=m.transform(T_link_copt @ inv_T(T_opt))),
                       TS(header=m.header(f.t_ns, "camera_color_frame"), child_frame_id=cframe,
                          transform=m.transform(T_opt))]
                yield "/tf_static", "tf2_msgs/msg/TFMessage", f.t_ns, m.T["tf2_msgs/msg/TFMessage"](transforms=tfs)
            elif extrinsics == "realsense":
                R = T_color_depth[:3, :3]
                yield (f"{ROS_NS}/extrinsics/depth_to_color", "realsense2_camera_msgs/msg/Extrinsics", f.t_ns,
                       m.T["realsense2_camera_msgs/msg/Extrinsics"](header=m.header(f.t_ns, dframe),
                                                                     rotation=R.T.ravel().copy(),
                                                                     translation=T_color_depth[:3, 3].copy()))
        for topic in topics:
            t_ns = f.t_ns if topic == "color" else (f.depth_t_ns or f.t_ns)
            if topic == "color":
                frame, intr, img, enc = cframe, color_intrinsics, f.color, color_encoding
                base = f"{ROS_NS}/color"
                name = "image_raw"
            elif topic == "depth":
                frame, intr, img, enc = dframe, depth_intrinsics, f.depth, "16UC1"
                base, name = f"{ROS_NS}/depth", "image_rect_raw"
            else:  # "aligned": depth already registered to colour (f.depth must then be colour-sized)
                frame, intr, img, enc = cframe, color_intrinsics, f.depth, "16UC1"
                base, name = f"{ROS_NS}/aligned_depth_to_color", "image_raw"
            if img is None:
                continue
            hdr = m.header(t_ns, frame)
            if transport == "compressed":
                sub = "compressed" if topic == "color" else "compressedDepth"
                yield (f"{base}/{name}/{sub}", "sensor_msgs/msg/CompressedImage", t_ns,
                       m.compressed_image(hdr, np.asarray(img), enc))
            else:
                yield f"{base}/{name}", "sensor_msgs/msg/Image", t_ns, m.image(hdr, np.asarray(img), enc)
            yield f"{base}/camera_info", "sensor_msgs/msg/CameraInfo", t_ns, m.camera_info(hdr, intr, "plumb_bob")


def write_rosbag2(path: str | Path, frames: Iterable[RecordingFrame], color_intrinsics: Intrinsics,
                  depth_camera: DepthCamera | None = None, storage: str = "sqlite3",
                  topics: tuple[str, ...] = ("color", "depth"),
                  extrinsics: str = "tf_static", color_encoding: str = "rgb8", transport: str = "raw") -> Path:
    """A rosbag2 folder (realsense2_camera topics) of `frames`; returns the path of its storage file
    (`<folder>/<folder name>.db3` or `.mcap`). topics: any of "color", "depth" (depth camera,
    image_rect_raw), "aligned" (depth registered to colour: aligned_depth_to_color). extrinsics:
    "tf_static", "realsense" (extrinsics/depth_to_color) or "none". depth_camera: the depth topic's camera (None:
    the colour camera's). color_encoding: the colour messages' encoding label (another one than rgb8 makes a
    recording of an encoding gscan does not read; the RGB pixels are kept). transport: "raw" (sensor_msgs Image)
    or "compressed" (CompressedImage, see the module docstring)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    m = _Msgs(ros1=False)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    conns: dict[str, Any] = {}
    with Writer(path, version=9, storage_plugin=plugin) as w:
        for topic, typ, t_ns, msg in _ros2_messages(frames, color_intrinsics, depth_camera, topics, extrinsics, m,
                                                      color_encoding, transport):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=m.ts)
            w.write(conns[topic], t_ns, m.serialize(msg, typ))
    return path / f"{path.name}.{'mcap' if storage == 'mcap' else 'db3'}"


def write_mcap(path: str | Path, frames: Iterable[RecordingFrame], color_intrinsics: Intrinsics,
               depth_camera: DepthCamera | None = None, topics: tuple[str, ...] = ("color", "depth"),
               extrinsics: str = "tf_static", color_encoding: str = "rgb8", compressed: bool = True,
               transport: str = "raw") -> Path:
    """A bare MCAP file of `frames` (the messages of `write_rosbag2`, `transport` as there) written with the mcap
    package's writer, its chunks zstd-compressed (the writer's default) or not (`compressed` False: records as
    they are stored)."""
    from mcap.writer import CompressionType, Writer

    path = Path(path)
    m = _Msgs(ros1=False)
    schemas: dict[str, int] = {}
    channels: dict[str, int] = {}
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD if compressed else CompressionType.NONE)
        w.start(profile="ros2", library="gscan.synth")
        for topic, typ, t_ns, msg in _ros2_messages(frames, color_intrinsics, depth_camera, topics, extrinsics, m,
                                                      color_encoding, transport):
            if typ not in schemas:
                text, _ = m.ts.generate_msgdef(typ, ros_version=2)
                schemas[typ] = w.register_schema(name=typ, encoding="ros2msg", data=text.encode())
            if topic not in channels:
                channels[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=schemas[typ])
            w.add_message(channels[topic], log_time=t_ns, data=m.serialize(msg, typ), publish_time=t_ns)
        w.finish()
    return path
