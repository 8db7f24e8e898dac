"""A RealSense camera, or a RealSense recording played back, as a stream of colour + aligned depth frames.

Both go through one pyrealsense2 pipeline; only the device differs: a connected camera
(`rs.config.enable_stream` with the chosen size and rate) or the playback device of a `.bag` or `.db3`
(`rs.config.enable_device_from_file`, played as fast as it is read unless `real_time`). Depth is aligned to
the colour camera with the device's intrinsics and depth-to-colour extrinsics, and converted to millimetres
with its depth scale, so frames come out as the capture layout stores them.

Alignment (`align`): "gscan" (default) reprojects depth with `gscan.io.align`, the same code that
reads recordings, so a capture played from a .bag holds the depth `gscan scan REC.bag` reads (to the
millimetre); "librealsense" uses `rs.align`, which keeps each point's depth-camera z instead of its z in the
colour camera: off by the depth-to-colour rotation (see BENCHMARKS.md, section Recordings). Depth that comes
registered to colour is taken as it is.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from gscan.errors import InputError
from gscan.io.align import align_depth_to_color
from gscan.io.camera import DepthCamera, Intrinsics
from gscan.io.recordings.pairing import pair_frames
from gscan.io.recordings.streams import is_identity, recorded_depth_camera, same_intrinsics

log = logging.getLogger(__name__)

LIVE_DEFAULT = (640, 480, 30)  # width, height, fps of a live capture when not chosen
# a recording's playback reports "stopped" once its reader is at the end, while its last framesets may still be on
# their way through the pipeline (seen after the stop even unloaded): they are waited for until none came this long
END_GRACE_S = 2.0


@dataclass(frozen=True)
class CameraOptions:
    """width / height / fps: the streams to open (None: the recording's own; a live camera uses LIVE_DEFAULT);
    real_time: play a recording at its recorded pace (default: as fast as frames are consumed; a frame whose
    colour and depth the playback delivers in two framesets, which happens on a loaded machine, is paired again by
    timestamp, `LonePairer`);
    timeout_s: how long a live camera may deliver nothing before it is given up; align: "gscan" | "librealsense"
    (see the module docstring)."""

    width: int | None = None
    height: int | None = None
    fps: int | None = None
    real_time: bool = False
    timeout_s: float = 5.0
    align: str = "gscan"


@dataclass
class CameraFrame:
    """color: [H x W x 3] uint8 RGB; depth_mm: [H x W] uint16 millimetres aligned to colour (0 = invalid);
    number: the colour frame's number from the device; timestamp_ms: its timestamp."""

    number: int
    timestamp_ms: float
    color: np.ndarray
    depth_mm: np.ndarray


@dataclass
class LoneFrame:
    """A colour or depth frame as librealsense delivered it: number, timestamp (ms), data, colour format."""

    number: int
    timestamp_ms: float
    pixels: np.ndarray  # the frame's data, copied (librealsense reuses its buffers)
    fmt: Any = None


class LonePairer:
    """Pairs a colour frame and a depth frame delivered in separate framesets (librealsense's playback does so on a
    loaded machine, most often for a recording's first frame): the last lone frame of each stream is held, and the
    two make one frame when their timestamps are at most `tolerance_ms` apart (half the frame period, as
    `gscan.io.recordings.pairing` pairs a recording's streams). A lone frame replaced by a newer one of its stream,
    or passed by a whole frameset, is dropped (logged); a colour frame dropped so is written into `left_out`
    (its device frame number: the reason; a reason already there is kept)."""

    def __init__(self, tolerance_ms: float, left_out: dict[int, str] | None = None) -> None:
        self.tolerance_ms = tolerance_ms
        self.colour: LoneFrame | None = None
        self.depth: LoneFrame | None = None
        self.left_out = {} if left_out is None else left_out

    def _drop(self, kind: str, held: LoneFrame, why: str) -> None:
        log.debug("lone %s frame %d dropped: %s", kind, held.number, why)
        if kind == "colour":
            self.left_out.setdefault(held.number, f"no depth frame came with it ({why})")

    def add(self, kind: str, lone: LoneFrame) -> tuple[LoneFrame, LoneFrame] | None:
        """Hold a lone frame of `kind` ("colour" | "depth"); (colour, depth) when it completes a pair."""
        held = self.colour if kind == "colour" else self.depth
        if held is not None:
            self._drop(kind, held, f"none within {self.tolerance_ms:.1f} ms")
        if kind == "colour":
            self.colour = lone
        else:
            self.depth = lone
        if self.colour is None or self.depth is None:
            return None
        if abs(self.colour.timestamp_ms - self.depth.timestamp_ms) > self.tolerance_ms:
            # keep the newer one: the older cannot meet a partner later than the newer's
            if self.colour.timestamp_ms < self.depth.timestamp_ms:
                self._drop("colour", self.colour, f"none within {self.tolerance_ms:.1f} ms")
                self.colour = None
            else:
                self.depth = None
            return None
        pair = (self.colour, self.depth)
        self.colour = self.depth = None
        return pair

    def passed(self, why: str = "a whole frameset followed it") -> None:
        """A whole frameset came (or the stream ended: `why`): lone frames held have lost their partner."""
        for kind, held in (("colour", self.colour), ("depth", self.depth)):
            if held is not None:
                self._drop(kind, held, why)
        self.colour = self.depth = None


def skipped_frames(expected_ms: dict[str, float], delivered_ms: list[float], tolerance_ms: float = 1.0
                   ) -> list[str] | None:
    """The recording's colour frames (name -> camera timestamp, ms: as `gscan scan REC.bag` names and reads them)
    that the playback never delivered (`delivered_ms`: the colour timestamps it delivered; paired one to one within
    `tolerance_ms`, as a recording's streams are: `pair_frames`), in name order; None when the two cannot be
    compared: fewer than half the frames delivered match a recorded one (the SDK reads its timestamps from another
    clock than gscan's reader found)."""
    names = list(expected_ms)
    recorded = np.rint(np.array(list(expected_ms.values()), np.float64) * 1e6).astype(np.int64)
    got = np.unique(np.rint(np.asarray(delivered_ms, np.float64) * 1e6).astype(np.int64))  # ns, each frame once
    if len(recorded) == 0 or len(got) == 0:
        return None
    pairs = pair_frames(recorded, got, tolerance_ms * 1e-3)
    if 2 * len(pairs) < len(got):
        return None
    return sorted(n for i, n in enumerate(names) if i not in pairs)


def _rs() -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as e:  # pragma: no cover - pyrealsense2 is a dependency
        raise InputError(None, f"pyrealsense2 is not installed ({e})") from None
    return rs


def _recorded_colour_ms(recording: Path) -> dict[str, float]:
    """The recording's colour frames as gscan's reader names them -> camera timestamp (ms); empty when gscan's
    reader cannot read it (the playback's skips are then not told)."""
    from gscan.io import open_sequence

    reader = logging.getLogger("gscan.io")  # its frames left out are the capture's to say (`left_out`)
    level = reader.level
    reader.setLevel(logging.ERROR)
    try:
        seq = open_sequence(recording)
    except InputError as e:
        log.info("%s: frames not listed (%s): the playback's skips cannot be told", recording, e)
        return {}
    finally:
        reader.setLevel(level)
    try:
        stamps = getattr(seq, "timestamps", {})
        return {n: 1000.0 * t for n, t in stamps.items()}
    finally:
        close = getattr(seq, "close", None)
        if close is not None:
            close()


def _why(e: BaseException) -> str:
    return " ".join(str(e).split()) or e.__class__.__name__


class RealSenseCamera:
    """`with RealSenseCamera(recording=None | path, options) as cam: for f in cam.frames(): ...`.

    After entering: `intrinsics` (colour), `depth_scale` (metres per raw unit), `device` (name and serial),
    `profile` (the streams), `registered` (depth already in the colour camera: not re-aligned).
    """

    def __init__(self, recording: str | Path | None = None, options: CameraOptions = CameraOptions()):
        self.recording = None if recording is None else Path(recording)
        self.options = options
        self.intrinsics: Intrinsics | None = None
        self.depth_scale = 0.0
        self.device = ""
        self.profile = ""
        self.registered = False  # depth comes registered to colour (then it is not re-aligned)
        self.depth_camera: DepthCamera | None = None  # the depth stream's camera (T_color_depth: its pose in colour)
        self._pipe: Any = None
        self._playback: Any = None
        self._align: Any = None
        # colour frames delivered and not made frames of (device frame number: the reason; `frames`)
        self.left_out: dict[int, str] = {}
        # a recording's colour frames its playback never delivered (their names, as `gscan scan REC.bag` gives
        # them: `skipped_frames`), once it has ended; empty when none or when that cannot be told
        self.skipped: list[str] = []

    def _where(self) -> Path | None:
        return self.recording

    def check(self) -> None:
        """InputError when there is nothing to stream: the recording is missing, or no camera is connected."""
        if self.recording is not None:
            if not self.recording.is_file():
                raise InputError(self.recording, "recording not found" if not self.recording.exists()
                                 else "not a file (a RealSense .bag or .db3)")
        elif len(_rs().context().query_devices()) == 0:
            raise InputError(None, "no RealSense camera connected (--from REC.bag or REC.db3 plays a recording "
                             "instead)")

    def __enter__(self) -> RealSenseCamera:
        rs = _rs()
        o = self.options
        self.check()
        cfg = rs.config()
        if self.recording is not None:
            cfg.enable_device_from_file(str(self.recording), repeat_playback=False)
            w, h, fps = o.width or 0, o.height or 0, o.fps or 0
        else:
            w, h, fps = o.width or LIVE_DEFAULT[0], o.height or LIVE_DEFAULT[1], o.fps or LIVE_DEFAULT[2]
        cfg.enable_stream(rs.stream.depth, w, h, rs.format.z16, fps)
        cfg.enable_stream(rs.stream.color, w, h, rs.format.any if self.recording else rs.format.rgb8, fps)
        pipe = rs.pipeline()
        try:
            if self.recording is not None:
                # the playback pace is set on the resolved device before streaming starts (pipe.start reuses it):
                # set after start, the first framesets are played in real time and may be dropped meanwhile
                cfg.resolve(rs.pipeline_wrapper(pipe)).get_device().as_playback().set_real_time(bool(o.real_time))
            started = pipe.start(cfg)
        except RuntimeError as e:
            what = "the recording" if self.recording else "the camera"
            size = (f" at {w}x{h}" if w else "") + (f"{',' if w else ' at'} {fps} fps" if fps else "")
            raise InputError(self._where(), f"{what} cannot stream colour and depth{size} ({_why(e)})") from None
        self._pipe = pipe
        try:
            dev = started.get_device()
            if self.recording is not None:
                self._playback = dev.as_playback()
            self.depth_scale = float(dev.first_depth_sensor().get_depth_scale())
            cp = started.get_stream(rs.stream.color).as_video_stream_profile()
            dp = started.get_stream(rs.stream.depth).as_video_stream_profile()
            ci = cp.get_intrinsics()
            self.intrinsics = Intrinsics(float(ci.fx), float(ci.fy), float(ci.ppx), float(ci.ppy), int(ci.width),
                                         int(ci.height))
            name = dev.get_info(rs.camera_info.name) if dev.supports(rs.camera_info.name) else "RealSense"
            serial = dev.get_info(rs.camera_info.serial_number) if dev.supports(rs.camera_info.serial_number) else ""
            self.device = f"{name} {serial}".strip()
            self.profile = (f"colour {ci.width}x{ci.height} {str(cp.format()).split('.')[-1]} @ {cp.fps()} fps, depth "
                            f"{dp.width()}x{dp.height()} @ {dp.fps()} fps")
            if not self.depth_scale > 0:
                raise InputError(self._where(), "the depth sensor reports no depth scale (Depth Units)")
            di, ex = dp.get_intrinsics(), dp.get_extrinsics_to(cp)
            depth_intr = Intrinsics(float(di.fx), float(di.fy), float(di.ppx), float(di.ppy), int(di.width),
                                    int(di.height))
            T_color_depth = np.eye(4)
            T_color_depth[:3, :3] = np.asarray(ex.rotation, dtype=np.float64).reshape(3, 3).T  # column-major
            T_color_depth[:3, 3] = np.asarray(ex.translation, dtype=np.float64)
            self.depth_camera = recorded_depth_camera(depth_intr, T_color_depth, self._where())
            # depth registered to colour (one camera model, no offset) is taken as it is: rs.align would still
            # splat every pixel over its neighbours (a one-pixel erosion towards the nearer surface)
            self.registered = is_identity(T_color_depth) and same_intrinsics(depth_intr, self.intrinsics)
        except BaseException:
            self.close()
            raise
        if o.align not in ("gscan", "librealsense"):
            raise ValueError(f"align must be 'gscan' or 'librealsense', not {o.align!r}")
        self._align = rs.align(rs.stream.color) if o.align == "librealsense" and not self.registered else None
        log.info("%s: %s", self.recording or self.device, self.profile)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        if self._pipe is not None:
            try:
                self._pipe.stop()
            except RuntimeError as e:  # already stopped (end of a recording)
                log.debug("pipeline stop: %s", e)
            self._pipe = None

    def _ended(self) -> bool:
        rs = _rs()
        return self._playback is not None and self._playback.current_status() == rs.playback_status.stopped

    def frames(self) -> Iterator[CameraFrame]:
        """Aligned framesets as they come, until the recording ends (a live camera streams until the caller stops).

        A colour frame whose depth lies more than half a frame period from it (the SDK's syncer hands on the last
        depth frame when a recording lost some: a depth image of another moment), or which no depth frame came
        with, is not made a frame: it is written into `left_out` with the reason (as `gscan scan REC.bag` leaves
        it out), unless its own depth frame still comes (alone, or with the colour frame delivered again)."""
        rs = _rs()
        assert self._pipe is not None, "enter the camera first"
        last_number = None
        waited = time.monotonic()
        stopped_at: float | None = None  # when the playback was first seen stopped
        fps = self._pipe.get_active_profile().get_stream(rs.stream.color).fps() or 30
        tolerance_ms = 500.0 / fps  # half the colour frame period, as a recording's streams are paired
        # lone colour or depth frames are paired again where gscan aligns (rs.align needs a whole frameset)
        lone = LonePairer(tolerance_ms, self.left_out) if self._align is None else None
        delivered: list[float] = []  # every colour frame's timestamp (ms), whatever became of it
        while True:
            try:
                ok, fs = self._pipe.try_wait_for_frames(200)
            except RuntimeError as e:
                raise InputError(self._where(), f"streaming failed ({_why(e)})") from None
            if not ok:
                if self._ended():
                    now = time.monotonic()
                    stopped_at = now if stopped_at is None else stopped_at
                    if now - max(stopped_at, waited) > END_GRACE_S:
                        if lone is not None:
                            lone.passed("the recording ended")
                        self._count_skipped(delivered)
                        return
                    continue
                if time.monotonic() - waited > self.options.timeout_s:
                    if self._playback is not None:  # (librealsense's playback can hang on a recording's gap)
                        log.warning("%s: the playback delivered nothing for %g s before the recording's end: "
                                    "the frames after that are not read", self.recording, self.options.timeout_s)
                        self._count_skipped(delivered)
                        return
                    raise InputError(None, f"the camera delivered no frame for {self.options.timeout_s:g} s")
                continue
            waited = time.monotonic()
            c, d = fs.get_color_frame(), fs.get_depth_frame()
            if c:
                delivered.append(float(c.get_timestamp()))
            if c and d:
                apart = abs(float(c.get_timestamp()) - float(d.get_timestamp()))
                if apart > tolerance_ms and c.get_frame_timestamp_domain() == d.get_frame_timestamp_domain():
                    number = int(c.get_frame_number())
                    if number == last_number:
                        continue
                    self.left_out[number] = (f"no depth frame within {tolerance_ms:.1f} ms of this colour frame "
                                             f"(the SDK paired depth frame {d.get_frame_number()}, {apart:.1f} ms "
                                             f"away)")
                    log.info("colour frame %d: %s", number, self.left_out[number])
                    if lone is None:
                        continue
                    d = None  # its own depth frame may still come alone (then it is paired, and not left out)
            if c and d:
                if self._align is not None:
                    fs = self._align.process(fs)
                    c, d = fs.get_color_frame(), fs.get_depth_frame()
                if lone is not None:
                    lone.passed()
                cf = LoneFrame(int(c.get_frame_number()), float(c.get_timestamp()), np.asanyarray(c.get_data()),
                           c.get_profile().format())
                df = LoneFrame(int(d.get_frame_number()), float(d.get_timestamp()), np.asanyarray(d.get_data()))
            elif lone is not None and (c or d):
                f = c or d
                held = LoneFrame(int(f.get_frame_number()), float(f.get_timestamp()),
                             np.array(np.asanyarray(f.get_data()), copy=True), f.get_profile().format())
                pair = lone.add("colour" if c else "depth", held)
                if pair is None:
                    continue
                cf, df = pair
            else:
                if c and int(c.get_frame_number()) != last_number:  # rs.align needs a whole frameset
                    self.left_out[int(c.get_frame_number())] = "no depth frame came with it"
                continue
            if cf.number == last_number:  # the same colour frame delivered again with a newer depth frame
                continue
            last_number = cf.number
            self.left_out.pop(cf.number, None)
            yield self._frame(cf, df, rs)

    def _count_skipped(self, delivered_ms: list[float]) -> None:
        """At the recording's end: `skipped`, the recorded colour frames the playback never delivered (its
        pipeline can drop some on a loaded machine, and does at the recorded pace when frames are read slower)."""
        recorded = _recorded_colour_ms(self.recording) if self.recording is not None else {}
        self.skipped = skipped_frames(recorded, delivered_ms) or []
        if self.skipped:
            log.info("%s: the playback skipped %d recorded frames (%s)", self.recording, len(self.skipped),
                     ", ".join(self.skipped))

    def _frame(self, c: LoneFrame, d: LoneFrame, rs: Any) -> CameraFrame:
        """The CameraFrame of a colour and a depth frame: RGB colour, depth in millimetres aligned to colour."""
        color = _to_rgb(c.pixels, c.fmt, rs)
        raw = d.pixels
        factor = self.depth_scale * 1000.0
        if self.registered or self._align is not None:
            if abs(factor - 1.0) < 1e-6:  # millimetre units already (D400 default)
                mm = raw.astype(np.uint16, copy=True)
            else:
                mm = np.clip(np.rint(raw.astype(np.float64) * factor), 0, 65535).astype(np.uint16)
        else:
            depth = raw.astype(np.float32)
            depth *= np.float32(self.depth_scale)  # metres, as the recording reader computes them
            assert self.intrinsics is not None and self.depth_camera is not None
            aligned = align_depth_to_color(depth, self.depth_camera, self.intrinsics)
            mm = np.clip(np.rint(aligned.astype(np.float64) * 1000.0), 0, 65535).astype(np.uint16)
        return CameraFrame(c.number, c.timestamp_ms, color, mm)


def _to_rgb(px: np.ndarray, fmt: Any, rs: Any) -> np.ndarray:
    if fmt == rs.format.rgb8:
        return px.copy()
    if fmt == rs.format.bgr8:
        return cv2.cvtColor(px, cv2.COLOR_BGR2RGB)
    if fmt == rs.format.rgba8:
        return np.ascontiguousarray(px[:, :, :3])
    if fmt == rs.format.bgra8:
        return cv2.cvtColor(px, cv2.COLOR_BGRA2RGB)
    if fmt == rs.format.yuyv:
        return cv2.cvtColor(px.reshape(px.shape[0], -1, 2), cv2.COLOR_YUV2RGB_YUYV)
    if fmt == rs.format.uyvy:
        return cv2.cvtColor(px.reshape(px.shape[0], -1, 2), cv2.COLOR_YUV2RGB_UYVY)
    if px.ndim == 2 and px.dtype == np.uint8:
        return cv2.cvtColor(px, cv2.COLOR_GRAY2RGB)
    raise InputError(None, f"colour stream format {fmt} is not supported")
