"""Write a RealSense recording with pyrealsense2's own recorder, from frames fed to a software device.

    python _rs_record.py FRAMES.npz OUT.db3|OUT.bag

Run as a script so that the recording can be written by whichever pyrealsense2 is importable (the installed one,
or another SDK version put first on PYTHONPATH): the SDK decides the layout (.bag up to 2.57, rosbag2 .db3 from
2.58). FRAMES.npz holds colors [N x H x W x 3] uint8 RGB, depths [N x Hd x Wd] uint16 raw units, K_color and
K_depth [3 x 3], T_color_depth [4 x 4], depth_units (metres per unit), period_ms, t0_ms and color_format (rgb8,
bgr8, rgba8 or yuyv: what the colour sensor streams; the RGB pixels are converted to it); optional: color_clock_ms
(the colour frames' timestamps on another clock: their offset, with the system-time domain) and pause_s (between
frames; 0.01 by default). Prints the SDK version.
"""
from __future__ import annotations

import importlib.metadata
import sys
import time

import cv2
import numpy as np
import pyrealsense2 as rs

BYTES = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "yuyv": 2}


def color_bytes(rgb: np.ndarray, fmt: str) -> np.ndarray:
    """[H x W x 3] RGB -> the pixels a colour sensor streaming `fmt` delivers ([H x W x bytes per pixel])."""
    if fmt == "rgb8":
        return rgb
    if fmt == "bgr8":
        return np.ascontiguousarray(rgb[:, :, ::-1])
    if fmt == "rgba8":
        return np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)])
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_YUYV)


def _intrinsics(K: np.ndarray, w: int, h: int) -> object:
    i = rs.intrinsics()
    i.width, i.height = w, h
    i.fx, i.fy, i.ppx, i.ppy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    i.model = rs.distortion.none
    i.coeffs = [0.0] * 5
    return i


def _stream(kind: object, uid: int, w: int, h: int, fmt: object, bpp: int, intr: object) -> object:
    s = rs.video_stream()
    s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt, s.intrinsics = (
        kind, 0, uid, w, h, 30, bpp, fmt, intr)
    return s


def record(frames: dict, out: str) -> None:
    colors, depths = frames["colors"], frames["depths"]
    fmt = str(frames["color_format"])
    units = float(frames["depth_units"])
    (h, w), (hd, wd), bpp = colors.shape[1:3], depths.shape[1:3], BYTES[fmt]
    dev = rs.software_device()
    depth_sensor, color_sensor = dev.add_sensor("Depth"), dev.add_sensor("Color")
    dp = depth_sensor.add_video_stream(_stream(rs.stream.depth, 0, wd, hd, rs.format.z16, 2,
                                               _intrinsics(frames["K_depth"], wd, hd)))
    cp = color_sensor.add_video_stream(_stream(rs.stream.color, 1, w, h, getattr(rs.format, fmt), bpp,
                                               _intrinsics(frames["K_color"], w, h)))
    depth_sensor.add_read_only_option(rs.option.depth_units, units)
    T = np.asarray(frames["T_color_depth"], dtype=np.float64)
    ex = rs.extrinsics()
    ex.rotation = [float(v) for v in T[:3, :3].T.ravel()]  # rs2_extrinsics: column-major
    ex.translation = [float(v) for v in T[:3, 3]]
    dp.register_extrinsics_to(cp, ex)
    recorder = rs.recorder(out, dev)
    depth_sensor.open(dp)
    color_sensor.open(cp)
    sync = rs.syncer()
    depth_sensor.start(sync)
    color_sensor.start(sync)
    keep = []  # the SDK reads a frame's pixels after on_video_frame returns
    clock = frames.get("color_clock_ms")
    for i, (rgb, raw) in enumerate(zip(colors, depths, strict=True)):
        t_ms = float(frames["t0_ms"]) + i * float(frames["period_ms"])
        for sensor, profile, px, nbytes in ((depth_sensor, dp, np.ascontiguousarray(raw), 2),
                                            (color_sensor, cp, color_bytes(rgb, fmt), bpp)):
            keep.append(px)
            other_clock = sensor is color_sensor and clock is not None
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride = px, nbytes, px.shape[1] * nbytes
            f.timestamp = t_ms + float(clock) if other_clock else t_ms
            f.domain = rs.timestamp_domain.system_time if other_clock else rs.timestamp_domain.hardware_clock
            f.frame_number = i
            f.profile = profile.as_video_stream_profile()
            if sensor is depth_sensor:
                f.depth_units = units
            sensor.on_video_frame(f)
        time.sleep(float(frames.get("pause_s", 0.01)))  # the recorder writes from its own thread
    time.sleep(0.2)
    depth_sensor.stop()
    color_sensor.stop()
    depth_sensor.close()
    color_sensor.close()
    del recorder  # closes the file


if __name__ == "__main__":
    with np.load(sys.argv[1]) as data:
        record({k: data[k] for k in data.files}, sys.argv[2])
    print(importlib.metadata.version("pyrealsense2"))
