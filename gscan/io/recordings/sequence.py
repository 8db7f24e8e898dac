"""A recording opened as an RGB-D sequence: colour and depth paired by timestamp, frames streamed one by one.

Opening reads the recording once without decoding a pixel: the stream setup (topics, intrinsics, depth
scale, extrinsics: `gscan.io.recordings.realsense` / `.ros`), then every colour and depth message's
header (timestamp, size, encoding). Colour frames are paired with depth frames by header stamp
(`gscan.io.recordings.pairing`: closest first, one to one, within half the faster stream's frame period;
log times when a stream carries no stamps). A frame is a paired colour message; its name is its index
among the colour topic's messages, `000000`, `000001`, ... (stable and sortable). Colour frames that
cannot be used (no depth partner in time, wrong size or encoding) are listed in `problems` by name and
left out; a recording with no usable frame is refused.

Frames are read on demand: indexing by name continues a stream through the file when frames are asked for
in order (the common case, one pass), and restarts it from the frame's time otherwise (the formats are
indexed by time). At most the messages between a frame's colour and depth message are buffered, so memory
does not grow with the recording's length. Depth is reprojected into the colour camera
(`gscan.io.align`) unless the recording's depth is registered to colour already.
"""
from __future__ import annotations

import itertools
import logging
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import numpy as np

from gscan.errors import InputError
from gscan.io.align import align_depth_to_color
from gscan.io.camera import FrameIteration, Intrinsics, RGBDFrame, load_intrinsics
from gscan.io.images import check_depth_range, check_depth_scale
from gscan.io.recordings.kinds import recording_format
from gscan.io.recordings.messages import (
    COLOR_ENCODINGS,
    DEPTH_ENCODINGS,
    GREY_ENCODINGS,
    ImageMsg,
    MessageError,
    color_pixels,
    depth_metres,
    encoding_kind,
)
from gscan.io.recordings.pairing import pair_frames, pair_tolerance
from gscan.io.recordings.realsense import is_realsense, realsense_setup
from gscan.io.recordings.ros import ros_setup
from gscan.io.recordings.source import DamagedRecords, MessageSource, open_source
from gscan.io.recordings.streams import StreamSetup

log = logging.getLogger(__name__)

MsgKey = tuple[int, int]  # (log time ns, occurrence among the topic's messages at that log time)


@dataclass
class _Pair:
    name: str
    color: MsgKey
    depth: MsgKey
    stamp_ns: int  # the colour frame's timestamp


def _size_problem(msg: ImageMsg, intr: Intrinsics, info_topic_of: str) -> str | None:
    if (msg.width, msg.height) != (intr.width, intr.height):
        return (f"image is {msg.width}x{msg.height} but the CameraInfo of {info_topic_of} is for "
                f"{intr.width}x{intr.height}")
    return None


class RecordingSequence(FrameIteration):
    """An opened recording (see the module docstring); the same attributes and indexing as
    `gscan.io.sequence.Sequence`, plus `timestamps` (name -> colour timestamp, s), `setup` (the streams),
    `aligned` (depth is reprojected into the colour camera) and `pair_tolerance_s`.

    Keeps the file open; `close()` (or a `with` block) releases it.
    """

    def __init__(self, path: Path, fmt: str, src: MessageSource, setup: StreamSetup, intrinsics: Intrinsics,
                 depth_scale: float, scale_override: bool, pairs: list[_Pair], problems: dict[str, str],
                 tolerance_s: float):
        self.root = path
        self.name = path.stem if path.is_file() else path.name
        self.format = fmt
        self.setup = setup
        self.kind = setup.kind
        self.intrinsics = intrinsics
        self.depth_scale = depth_scale
        self.names: list[str] = [p.name for p in pairs]
        self.timestamps: dict[str, float] = {p.name: p.stamp_ns * 1e-9 for p in pairs}
        self.problems: dict[str, str] = problems
        self.pair_tolerance_s = tolerance_s
        self.aligned = not setup.registered  # registered depth takes the colour intrinsics (and an override) as is
        self.gt_T_cam_obj: dict[str, np.ndarray] | None = None
        self.gt_T_world_cam: dict[str, np.ndarray] | None = None
        self.gt_instances: dict[str, list[tuple[int, np.ndarray]]] | None = None
        self.gt_problems: dict[str, str] = {}  # a recording carries no ground truth: none unreadable either
        self.has_masks = False
        self.obj_id: int | None = None
        # the recording's damaged records, one line each (topic, messages the file's index lists and those read,
        # where they are missing); empty for an intact recording
        self.damage: list[str] = []
        self._src: MessageSource | None = src
        self._scale_override = scale_override
        self._pairs = {p.name: (k, p) for k, p in enumerate(pairs)}
        self._pair_of: dict[tuple[str, MsgKey], int] = {}
        for k, p in enumerate(pairs):
            self._pair_of[("c", p.color)] = k
            self._pair_of[("d", p.depth)] = k
        self._lock = threading.Lock()
        self._it: Iterator[tuple[str, int, bytes | memoryview]] | None = None
        self._next = -1
        self._last: dict[str, tuple[int, int]] = {}
        self._buffer: dict[tuple[str, MsgKey], bytes | memoryview] = {}

    def __len__(self) -> int:
        return len(self.names)

    def fingerprints(self) -> dict[str, dict[str, str] | None]:
        """What each frame is, cheaply, as `gscan.io.sequence.Sequence.fingerprints` says for folders: {name:
        {"recording": "<file bytes>:<colour and depth message keys and stamp>"}} for the paired frames, None for
        the frames left out (`problems`). A recording written again differs in its size or its messages' log
        times; the pixels themselves are not read."""
        files = sorted(self.root.rglob("*")) if self.root.is_dir() else [self.root]
        size = sum(f.stat().st_size for f in files if f.is_file())
        out: dict[str, dict[str, str] | None] = dict.fromkeys(self.problems)
        for name, (_, p) in self._pairs.items():
            out[name] = {"recording": f"{size}:{p.color[0]}.{p.color[1]}/{p.depth[0]}.{p.depth[1]}/{p.stamp_ns}"}
        return out

    def __repr__(self) -> str:
        return (f"RecordingSequence({self.name!r}, format={self.format!r}, frames={len(self)}, "
                f"problems={len(self.problems)}, aligned={self.aligned})")

    def frame_intrinsics(self, key: int | str) -> Intrinsics:
        return self.intrinsics

    def close(self) -> None:
        with self._lock:
            self._it = None
            self._buffer.clear()
            if self._src is not None:
                self._src.close()
                self._src = None

    def __enter__(self) -> RecordingSequence:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def __del__(self) -> None:
        try:  # not contextlib: at interpreter shutdown module globals may already be gone
            if self._src is not None:
                self._src.close()
        except Exception:  # noqa: BLE001 - nothing to do about a reader torn down half-way
            pass

    # ------------------------------------------------------------------ reading
    def _parse(self, topic: str, data: bytes | memoryview) -> ImageMsg:
        assert self._src is not None
        return self.setup.parse(self._src.wire, topic, data)

    def _restart(self, start_ns: int) -> None:
        assert self._src is not None
        self._it = self._src.messages([self.setup.color_topic, self.setup.depth_topic], start_ns)
        self._last.clear()
        self._buffer.clear()

    def _messages_of(self, k: int, p: _Pair) -> tuple[bytes | memoryview, bytes | memoryview]:
        """The raw colour and depth messages of pair k, streaming on from pair k - 1 or restarting at pair k."""
        if self._src is None:
            raise InputError(self.root, "recording is closed")
        if self._it is None or k != self._next:
            self._restart(min(p.color[0], p.depth[0]))
        need = {("c", p.color), ("d", p.depth)}
        got = {key: self._buffer.pop(key) for key in need if key in self._buffer}
        assert self._it is not None
        while len(got) < 2:
            item = next(self._it, None)
            if item is None:
                self._it = None
                raise InputError(self.root, f"frame {p.name}: its messages were not found again (the file changed "
                                 "while it was read?)")
            topic, log_ns, data = item
            last = self._last.get(topic)
            occ = last[1] + 1 if last is not None and last[0] == log_ns else 0
            self._last[topic] = (log_ns, occ)
            key = ("c" if topic == self.setup.color_topic else "d", (log_ns, occ))
            if key in need:
                got[key] = data
            elif self._pair_of.get(key, -1) > k:  # a later frame's message, read early: keep it
                self._buffer[key] = data
        for key in [key for key in self._buffer if self._pair_of[key] <= k]:
            del self._buffer[key]
        self._next = k + 1
        return got[("c", p.color)], got[("d", p.depth)]

    def _decode(self, p: _Pair, craw: bytes | memoryview, draw: bytes | memoryview) -> RGBDFrame:
        try:
            cmsg, dmsg = self._parse(self.setup.color_topic, craw), self._parse(self.setup.depth_topic, draw)
            color = color_pixels(cmsg)
            scale = self.depth_scale if self._scale_override or not dmsg.depth_units > 0 else dmsg.depth_units
            depth = depth_metres(dmsg, scale)
        except MessageError as e:
            raise InputError(self.root, f"frame {p.name}: {e}") from None
        if color.shape[:2] != (self.intrinsics.height, self.intrinsics.width):
            raise InputError(self.root, f"frame {p.name}: colour is {color.shape[1]}x{color.shape[0]}, "
                             f"its intrinsics {self.intrinsics.width}x{self.intrinsics.height}")
        if self.aligned:
            depth = align_depth_to_color(depth, self.setup.depth_camera, self.intrinsics)
        return RGBDFrame(p.name, color, depth, self.intrinsics, None, self.root)

    def __getitem__(self, key: int | str) -> RGBDFrame:
        """Frame `key` (index or name): RGB colour, depth in metres in the colour camera.

        Raises InputError naming the recording and the frame when it turns out unusable (also recorded in problems).
        """
        name = self.names[key] if isinstance(key, (int, np.integer)) else key
        if name not in self._pairs:
            raise KeyError(name)
        k, p = self._pairs[name]
        with self._lock:
            try:
                craw, draw = self._messages_of(k, p)
                return self._decode(p, craw, draw)
            except InputError as e:
                self.problems[name] = str(e)
                raise

    def raw(self, key: int | str) -> tuple[np.ndarray, np.ndarray]:
        """Frame `key` as recorded: ([H x W x 3] uint8 RGB colour, [Hd x Wd] float32 depth in metres in the depth
        camera, before any reprojection)."""
        name = self.names[key] if isinstance(key, (int, np.integer)) else key
        if name not in self._pairs:
            raise KeyError(name)
        k, p = self._pairs[name]
        with self._lock:
            craw, draw = self._messages_of(k, p)
            try:
                dmsg = self._parse(self.setup.depth_topic, draw)
                scale = self.depth_scale if self._scale_override or not dmsg.depth_units > 0 else dmsg.depth_units
                return color_pixels(self._parse(self.setup.color_topic, craw)), depth_metres(dmsg, scale)
            except MessageError as e:
                raise InputError(self.root, f"frame {p.name}: {e}") from None



@dataclass
class _Index:
    keys: list[MsgKey]
    stamps: list[int]
    logs: list[int]
    problems: list[str | None]
    depth_units: list[float]


def _index(src: MessageSource, setup: StreamSetup, color_intr: Intrinsics) -> tuple[_Index, _Index]:
    """One pass over the colour and depth messages: their keys, timestamps (the header's, or the camera's from
    `setup.stamps`) and what is wrong with each."""
    c, d = setup.color_topic, setup.depth_topic
    idx = {c: _Index([], [], [], [], []), d: _Index([], [], [], [], [])}
    expect = {c: ("color", "grey"), d: ("depth",)}
    intr = {c: color_intr, d: setup.depth_camera.intrinsics}
    last: dict[str, tuple[int, int]] = {}
    for topic, log_ns, data in src.messages([c, d]):
        prev = last.get(topic)
        occ = prev[1] + 1 if prev is not None and prev[0] == log_ns else 0
        last[topic] = (log_ns, occ)
        ix = idx[topic]
        camera_stamps = setup.stamps.get(topic)
        try:
            msg = setup.parse(src.wire, topic, data)
        except MessageError as e:
            ix.keys.append((log_ns, occ))
            ix.stamps.append(0)
            ix.logs.append(log_ns)
            ix.problems.append(f"unreadable message ({e})")
            ix.depth_units.append(0.0)
            continue
        kind = encoding_kind(msg.encoding)
        problem = None
        if kind not in expect[topic]:
            want = "a colour" if topic == c else "a depth"
            problem = f"encoding '{msg.encoding}' is not {want} image"
        problem = problem or _size_problem(msg, intr[topic], topic)
        if problem is None and camera_stamps is not None and log_ns not in camera_stamps:
            problem = "no camera timestamp for it in the stream's metadata"
        if problem is None:
            enc = msg.encoding.lower()
            problem = msg.problem(DEPTH_ENCODINGS.get(enc) or COLOR_ENCODINGS.get(enc) or GREY_ENCODINGS.get(enc) or 1)
        ix.keys.append((log_ns, occ))
        ix.stamps.append(camera_stamps.get(log_ns, 0) if camera_stamps is not None else msg.stamp_ns)
        ix.logs.append(log_ns)
        ix.problems.append(problem)
        ix.depth_units.append(msg.depth_units)
    return idx[c], idx[d]


@dataclass(frozen=True)
class _Damage:
    """Messages of a topic that the file's index lists but that could not be read (damaged records): how many, of
    how many, and the log-time window they are missing from (between the last message read before and the first
    after; None: the recording's start or end)."""

    topic: str
    expected: int
    read: int
    after_ns: int | None
    before_ns: int | None
    start_ns: int
    located: int = 0  # of the missing ones, those in the located damaged records (`_Located`), reported there
    placed: bool = True  # False: the messages read leave no stretch where they could have been

    def covers(self, t_ns: int, margin_ns: float = 0.0) -> bool:
        """Whether log time t_ns lies in the window the messages are missing from."""
        return self.placed and (self.after_ns is None or t_ns > self.after_ns) and \
            (self.before_ns is None or t_ns < self.before_ns)

    def holds(self, topic: str) -> bool:
        return topic == self.topic

    def describe(self) -> str:
        def at(t: int) -> str:
            return f"{(t - self.start_ns) * 1e-9:.3f} s"

        a, b = self.after_ns, self.before_ns
        if not self.placed:
            where = ("where, the messages read do not tell (they leave no stretch without one: lost at the "
                     "recording's start or end, or the index overcounts)")
            return (f"{self.expected - self.read - self.located} of the {self.expected} messages the file's index "
                    f"lists on {self.topic} could not be read, {where}")
        if a is None:
            where = "none was read" if b is None else f"before the message at {at(b)}"
        else:
            where = f"after the message at {at(a)}" if b is None else f"between the messages at {at(a)} and {at(b)}"
        besides = f" besides the {self.located} in the damaged records located" if self.located else ""
        return (f"{self.expected - self.read - self.located} of the {self.expected} messages the file's index lists "
                f"on {self.topic} could not be read{besides}, {where} (from the recording's start)")


@dataclass(frozen=True)
class _Located:
    """Damaged records the file locates (`DamagedRecords`), with the image topics that lack messages in their
    window by their own periods (`by_period`: topic -> messages) when the file does not tell their topics."""

    records: DamagedRecords
    start_ns: int
    by_period: dict[str, int]

    def covers(self, t_ns: int, margin_ns: float = 0.0) -> bool:
        return self.records.covers(t_ns, margin_ns)

    def holds(self, topic: str) -> bool:
        return topic in self.records.topics or topic in self.by_period

    def describe(self) -> str:
        guess = ("on topics the file does not tell; by the image streams' periods, "
                 + ", ".join(f"{n} on {t}" for t, n in self.by_period.items())) if self.by_period else ""
        return self.records.describe(self.start_ns, guess)


def _missing_by_period(rec: DamagedRecords, logs: list[int]) -> int:
    """How many messages of a stream (its log times read) are missing in the records' window, by the stream's own
    period (its median step): over the steps from the last message at or before the window to the first at or
    after it, those of 1.5 periods or more count their length in periods less one. 0 when the stream does not
    reach past both ends of the window."""
    t = np.sort(np.asarray(logs, dtype=np.int64))
    if len(t) < 3 or rec.first_ns is None or rec.last_ns is None:
        return 0
    period = float(np.median(np.diff(t)))
    a, b = int(np.searchsorted(t, rec.first_ns, "right")) - 1, int(np.searchsorted(t, rec.last_ns, "left"))
    if a < 0 or b >= len(t) or period <= 0:
        return 0
    steps = np.diff(t[a:b + 1]) / period
    return int(np.sum(np.where(steps >= 1.5, np.rint(steps) - 1, 0)))


def _by_period(rec: DamagedRecords, streams: dict[str, list[int]]) -> dict[str, int]:
    """The image streams (topic -> log times read) that lack messages in the window of records whose topics the
    file does not tell, by `_missing_by_period`; {} when those add up to more messages than the records hold (the
    streams' timing does not tell either)."""
    if rec.topics:
        return {}
    out = {t: n for t, logs in streams.items() if (n := _missing_by_period(rec, logs)) > 0}
    return out if sum(out.values()) <= rec.count else {}


def _damage(topic: str, logs: list[int], expected: int, span: tuple[int, int], period_ns: float,
            located: int = 0) -> _Damage | None:
    """The damage of a topic whose messages read (their log times) and `located` (in damaged records the file
    locates) are fewer than its index lists: the missing ones placed in the widest stretch without a message read,
    in the recording's image `span` (first and last log time of its colour and depth messages) at the image
    streams' `period_ns`."""
    if expected <= len(logs) + located:
        return None
    t = np.sort(np.asarray(logs, dtype=np.int64))
    start, end = span
    if len(t) == 0:
        return _Damage(topic, expected, 0, None, None, start, located)
    # stretches without a message: before the first, between two, after the last (None: the recording's ends)
    stretches = [(None, int(t[0]), int(t[0]) - start)] + [
        (int(a), int(b), int(b - a) - period_ns) for a, b in itertools.pairwise(t)] + [
        (int(t[-1]), None, end - int(t[-1]))]
    after, before, excess = max(stretches, key=lambda w: w[2])
    return _Damage(topic, expected, len(t), after, before, start, located, placed=excess > 0.5 * period_ns)


def _ms(seconds: float) -> str:
    return f"{seconds * 1000:.1f} ms"


def open_recording(path: str | Path, color_topic: str | None = None, depth_topic: str | None = None,
                   intrinsics: Intrinsics | str | Path | None = None,
                   depth_scale: float | None = None) -> RecordingSequence:
    """Open a `.bag` / `.db3` / `.mcap` recording or a rosbag2 folder as an RGB-D sequence.

    color_topic / depth_topic: the image topics to read (default: detected, see `gscan.io.recordings.ros` and
    `.realsense`). intrinsics overrides the colour camera's (Intrinsics or a cam_K.txt / Open3D JSON file);
    depth_scale (metres per raw unit) overrides the recording's. Raises InputError naming the file (and topic)
    for an unreadable, truncated or incomplete recording (no colour, no depth, no CameraInfo, no extrinsics
    for unregistered depth) or one whose colour and depth timestamps never pair.
    """
    path = Path(path)
    fmt = recording_format(path)
    if fmt is None:
        raise InputError(path, "not a recording (.bag, .db3, .mcap or a rosbag2 folder)")
    if depth_scale is not None:
        check_depth_scale(depth_scale, path)
    src = open_source(path)
    try:
        return _open(path, fmt, src, color_topic, depth_topic, intrinsics, depth_scale)
    except InputError as e:  # a recording refused for what its damaged records took says so
        lost = src.damaged()
        src.close()
        if lost and e.path == path:
            raise InputError(path, f"{e.reason} (the recording has damaged records: {lost[0].describe(None)}"
                             f"{f'; {len(lost) - 1} more' if len(lost) > 1 else ''})", e.fix) from None
        raise
    except BaseException:
        src.close()
        raise


def _open(path: Path, fmt: str, src: MessageSource, color_topic: str | None, depth_topic: str | None,
          intrinsics: Intrinsics | str | Path | None, depth_scale: float | None) -> RecordingSequence:
    topics = src.topics()
    setup = realsense_setup(src, color_topic, depth_topic) if is_realsense(topics) else \
        ros_setup(src, color_topic, depth_topic)
    c, d = setup.color_topic, setup.depth_topic
    intr = setup.color_intrinsics
    if isinstance(intrinsics, Intrinsics):
        intr = intrinsics
    elif intrinsics is not None:
        intr = load_intrinsics(Path(intrinsics), intr.width, intr.height)
    if (intr.width, intr.height) != (setup.color_intrinsics.width, setup.color_intrinsics.height):
        raise InputError(path, f"--intrinsics are for {intr.width}x{intr.height} images, topic {c} is "
                         f"{setup.color_intrinsics.width}x{setup.color_intrinsics.height}")
    cix, dix = _index(src, setup, intr)
    counts = src.counts()
    logs = np.sort(np.asarray(cix.logs + dix.logs, dtype=np.int64))
    span = (int(logs[0]), int(logs[-1])) if len(logs) else (0, 0)
    # the image streams' period: their messages' median step; the span over the messages the index lists only when
    # neither stream has two messages read (that span misses messages lost at the recording's end)
    steps = [float(np.median(np.diff(np.sort(np.asarray(ix.logs, dtype=np.int64))))) for ix in (cix, dix)
             if len(ix.logs) > 1]
    steps = steps or [(span[1] - span[0]) / (counts[t] - 1) for t in (c, d) if counts.get(t, 0) > 1]
    period = min(steps, default=0.0)
    located = [_Located(r, span[0], _by_period(r, {c: cix.logs, d: dix.logs})) for r in src.damaged()]
    damage: list[_Located | _Damage] = list(located)
    for ix, topic in ((cix, c), (dix, d)):
        known = sum(x.records.topics.get(topic, 0) + x.by_period.get(topic, 0) for x in located)
        if (short := _damage(topic, ix.logs, counts.get(topic, 0), span, period, known)) is not None:
            damage.append(short)
    for lost in damage:
        log.warning("%s: damaged records: %s", path, lost.describe())
    for ix, topic in ((cix, c), (dix, d)):
        if not ix.keys:
            raise InputError(path, f"topic {topic} holds no message")
        if all(p is not None for p in ix.problems):
            raise InputError(path, f"topic {topic}: no usable image ({ix.problems[0]})")
    bad_depth = [p for p in dix.problems if p is not None]
    if bad_depth:
        log.warning("%s: %d of %d depth messages on %s left out (first: %s)", path, len(bad_depth),
                    len(dix.problems), d, bad_depth[0])

    cok = [i for i, p in enumerate(cix.problems) if p is None]
    dok = [j for j, p in enumerate(dix.problems) if p is None]
    use_logs = not any(cix.stamps[i] for i in cok) or not any(dix.stamps[j] for j in dok)
    if use_logs:
        log.warning("%s: %s carries no header stamps; colour and depth are paired by their log times", path,
                    c if not any(cix.stamps[i] for i in cok) else d)
    ct = np.array([(cix.logs if use_logs else cix.stamps)[i] for i in cok], dtype=np.int64)
    dt = np.array([(dix.logs if use_logs else dix.stamps)[j] for j in dok], dtype=np.int64)
    tol = pair_tolerance(ct, dt)
    pairs_idx = pair_frames(ct, dt, tol)
    if not pairs_idx:
        gap = float(np.min(np.abs(ct[:, None] - dt[None, :]))) * 1e-9 if len(ct) * len(dt) <= 4_000_000 else None
        near = f"; the closest are {_ms(gap)} apart" if gap is not None else ""
        raise InputError(path, f"colour ({c}) and depth ({d}) timestamps never pair within {_ms(tol)}{near}")
    width = max(6, len(str(len(cix.keys) - 1)))
    problems: dict[str, str] = {}
    pairs: list[_Pair] = []
    order = np.argsort(dt, kind="stable")
    dts = dt[order]
    for a, i in enumerate(cok):
        name = f"{i:0{width}d}"
        if a in pairs_idx:
            j = dok[pairs_idx[a]]
            pairs.append(_Pair(name, cix.keys[i], dix.keys[j], int(ct[a])))
        else:
            k = int(np.searchsorted(dts, ct[a]))
            near_s = min(abs(int(dts[m]) - int(ct[a])) for m in (k - 1, k) if 0 <= m < len(dts)) * 1e-9
            took = next((x for x in damage if x.holds(d) and x.covers(int(cix.logs[i]), tol * 1e9)), None)
            if took is not None:
                problems[name] = (f"its depth message on {d} is among the recording's damaged records "
                                  f"({took.describe()})")
                continue
            why = "is paired with another colour frame" if near_s <= tol else "is farther"
            problems[name] = (f"no depth frame on {d} within {_ms(tol)} of this colour frame (the nearest, "
                              f"{_ms(near_s)} away, {why})")
            here = next((x for x in located if not x.records.topics and x.covers(int(cix.logs[i]), tol * 1e9)), None)
            if here is not None:  # lost records of topics the file does not tell, at this time
                problems[name] += f"; the recording has damaged records here ({here.describe()})"
    for i, p in enumerate(cix.problems):
        if p is not None:
            problems[f"{i:0{width}d}"] = f"colour message on {c}: {p}"
    problems = dict(sorted(problems.items()))
    pairs.sort(key=lambda q: q.name)

    if depth_scale is not None:
        scale, override = float(depth_scale), True
    elif setup.depth_scale is not None:
        scale, override = setup.depth_scale, False
    else:
        units = next((dix.depth_units[dok[pairs_idx[a]]] for a in sorted(pairs_idx)
                      if dix.depth_units[dok[pairs_idx[a]]] > 0), None)
        if units is None:
            raise InputError(path, f"no depth units for {d} (the recording has no Depth Units option); "
                             "pass --depth-scale")
        scale, override = float(str(np.float32(units))), False
    seq = RecordingSequence(path, fmt, src, setup, intr, scale, override, pairs, problems, tol)
    seq.damage = [f"{path}: damaged records: {dmg.describe()}" for dmg in damage]
    for name in list(seq.names):  # depth-scale sanity check on the first frame that decodes
        try:
            first = seq[name]
        except InputError:
            seq.names.remove(name)
            seq.timestamps.pop(name, None)
            continue
        check_depth_range(first.depth, scale, path)
        break
    if not seq.names:
        first_p = next(iter(seq.problems.items()))
        raise InputError(path, f"no usable RGB-D frame ({len(seq.problems)} unusable); "
                         f"first: {first_p[0]}: {first_p[1]}")
    seq._it = None  # the scan starts again from its first frame
    for name, reason in problems.items():
        log.warning("%s: frame %s left out: %s", path, name, reason)
    log.info("%s: %s, %d frames (%s colour, %s depth%s), pairing within %s", path, setup.kind, len(seq), c, d,
             ", reprojected to colour" if seq.aligned else ", registered", _ms(tol))
    return seq
