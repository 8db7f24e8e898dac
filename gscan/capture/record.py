"""Record a capture folder from a RealSense camera or recording: the frames that moved enough, or every Nth.

The folder is the capture layout `gscan scan` reads: `cam_K.txt` (the colour intrinsics), `rgb/NNNNNN.png`
(RGB), `depth/NNNNNN.png` (uint16 millimetres, aligned to colour), plus `capture.json` (device, streams,
depth scale, the keep rule, each kept frame's device frame number and timestamp, the colour frames left out
for want of their depth, with the reason, and a recording's frames its playback skipped: `RealSenseCamera`).
It is valid at every moment: cam_K.txt is written before the first frame, and each frame's two images are
written to hidden temporary files and renamed into place, depth before colour (a frame exists once its colour
image does).
So a capture stopped at any point (`stop` set, Ctrl+C) is a capture of the frames kept so far.

Which frames are kept: every Nth (`every`), or those whose viewing direction moved by `min_angle_deg`
since the last kept one (`gscan.capture.motion`). The first frame is always kept.
"""
from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from gscan.capture.camera import CameraFrame, RealSenseCamera
from gscan.capture.folder import check_capture_output
from gscan.capture.motion import Coverage, MotionParams, MotionTracker, MotionUpdate
from gscan.errors import InputError
from gscan.io.camera import Intrinsics
from gscan.io.output import missing_folders, remove_empty_folders

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CaptureOptions:
    """every: keep every Nth frame (None: keep by motion); motion: the motion cue's parameters;
    max_frames: stop once this many frames are kept (None: until the recording ends or `stop` is set)."""

    every: int | None = None
    motion: MotionParams = field(default_factory=MotionParams)
    max_frames: int | None = None


@dataclass
class FrameUpdate:
    """What the preview shows after each frame: the frame, whether it was kept, the motion and the coverage."""

    frame: CameraFrame
    intrinsics: Intrinsics
    seen: int
    kept: int
    kept_now: bool
    motion: MotionUpdate
    coverage: Coverage
    center: np.ndarray | None  # the object centre in the first kept camera (m), once a frame is kept
    R_up_first: np.ndarray | None = None  # [3 x 3] the first kept camera's axes into the coverage's up frame


@dataclass
class CaptureResult:
    output: Path
    seen: int
    kept: list[str]
    interrupted: bool
    device: str
    profile: str
    covered: int
    directions: int
    share: float = 0.0  # covered / directions (`gscan.geometry.coverage`)
    missing: list[str] = field(default_factory=list)  # the regions not yet seen, with what to do
    # colour frames delivered without their depth, not made frames: device frame number -> the reason
    left_out: dict[int, str] = field(default_factory=dict)
    # a recording's frames its playback never delivered, by the names `gscan scan REC.bag` gives them
    skipped: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        return {"output": str(self.output), "frames_seen": self.seen, "frames": len(self.kept),
                "names": list(self.kept), "left_out": {str(n): why for n, why in self.left_out.items()},
                "skipped": list(self.skipped),
                "stopped": self.interrupted, "device": self.device,
                "profile": self.profile, "coverage": {"covered": self.covered, "directions": self.directions,
                                                      "share": round(self.share, 4), "missing": list(self.missing)}}


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _png(img: np.ndarray, path: Path) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"cannot encode {path.name}")
    return buf.tobytes()


class CaptureWriter:
    """Writes the capture layout into `output` (see the module docstring)."""

    def __init__(self, output: Path, intrinsics: Intrinsics):
        self.output = output
        self.made = missing_folders(output / "x")  # what to remove when nothing gets written
        for d in ("rgb", "depth"):
            (output / d).mkdir(parents=True, exist_ok=True)
        text = "\n".join(" ".join(f"{x:.10g}" for x in row) for row in intrinsics.K) + "\n"
        _write_atomic(output / "cam_K.txt", text.encode())
        self.names: list[str] = []

    def add(self, frame: CameraFrame) -> str:
        name = f"{len(self.names):06d}"
        depth = _png(frame.depth_mm, self.output / "depth" / f"{name}.png")
        color = _png(cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR), self.output / "rgb" / f"{name}.png")
        dt, ct = self.output / "depth" / f".{name}.png.tmp", self.output / "rgb" / f".{name}.png.tmp"
        dt.write_bytes(depth)
        ct.write_bytes(color)
        os.replace(dt, self.output / "depth" / f"{name}.png")
        os.replace(ct, self.output / "rgb" / f"{name}.png")
        self.names.append(name)
        return name

    def discard(self) -> None:
        """Remove what was written (no frame was kept): cam_K.txt, the empty rgb/ and depth/, made folders."""
        (self.output / "cam_K.txt").unlink(missing_ok=True)
        remove_empty_folders([self.output / "rgb", self.output / "depth"] + self.made)


def run_capture(camera: RealSenseCamera, output: str | Path, options: CaptureOptions = CaptureOptions(),
                stop: threading.Event | None = None,
                on_frame: Callable[[FrameUpdate], None] | None = None) -> CaptureResult:
    """Stream `camera` (not yet entered) into the capture folder `output` until the recording ends, `stop` is set,
    `max_frames` are kept or Ctrl+C (KeyboardInterrupt) comes; returns what was written.

    Raises InputError naming the folder when it exists and is not empty or cannot be written, and for a
    camera or recording that delivers no frame (nothing is left behind then).
    """
    output = Path(output)
    check_capture_output(output, camera.recording)
    stop = stop or threading.Event()
    interrupted = False
    seen = 0
    frames_meta: dict[str, dict] = {}
    with camera:
        assert camera.intrinsics is not None
        intr = camera.intrinsics
        tracker = MotionTracker(intr, options.motion)
        writer: CaptureWriter | None = None
        try:
            for frame in camera.frames():
                if stop.is_set():
                    interrupted = True
                    break
                depth_m = frame.depth_mm.astype(np.float32) * np.float32(0.001)
                up = tracker.update(frame.color, depth_m)
                keep = (seen % options.every == 0) if options.every else tracker.wants(up)
                seen += 1
                if keep:
                    tracker.keep()
                    if writer is None:
                        writer = CaptureWriter(output, intr)
                    name = writer.add(frame)
                    frames_meta[name] = {"number": frame.number, "timestamp_ms": frame.timestamp_ms,
                                         "angle_deg": round(up.angle_deg, 2), "tracking_lost": up.lost}
                if on_frame is not None:
                    on_frame(FrameUpdate(frame, intr, seen, len(frames_meta), keep, up, tracker.coverage,
                                       tracker.center, tracker.R_up_first))
                if options.max_frames is not None and len(frames_meta) >= options.max_frames:
                    break
                if stop.is_set():
                    interrupted = True
                    break
        except KeyboardInterrupt:
            interrupted = True
        if writer is None:
            if interrupted:
                raise KeyboardInterrupt
            raise InputError(camera.recording, f"no frame delivered ({seen} seen)")
        rule = {"every": options.every} if options.every else {"min_angle_deg": options.motion.min_angle_deg}
        left_out = dict(sorted(camera.left_out.items()))
        meta = {"device": camera.device, "source": str(camera.recording) if camera.recording else "live",
                "profile": camera.profile, "depth_scale_m": camera.depth_scale, "depth_units": "mm",
                "keep": rule, "frames_seen": seen, "frames": frames_meta,
                "left_out": {str(n): why for n, why in left_out.items()}, "skipped": camera.skipped}
        _write_atomic(output / "capture.json", (json.dumps(meta, indent=1) + "\n").encode())
    cov = tracker.coverage.map()
    log.info("%s: kept %d of %d frames, %d of %d directions covered", output, len(writer.names), seen, cov.covered,
             len(cov.counts))
    return CaptureResult(output, seen, list(writer.names), interrupted, camera.device, camera.profile, cov.covered,
                         len(cov.counts), cov.share, cov.missing(), left_out, list(camera.skipped))
