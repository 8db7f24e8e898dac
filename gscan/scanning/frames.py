"""The scan's frames: the input read once, in order, the kept frames' images put in the frame store
(`load_frames`), and the kept frames as the later stages read them (`FrameData`).

- `detect_capture_mode(seq, mode_option) -> (mode, masks given)`: from a few frames spread over the input
- `load_frames(...) -> (kept frames, unreadable frames, selection, skipped frames)`, `read_ahead(seq)`
- `Frame`: a kept frame (counts, pose-independent facts); `FrameData`: images, masks and registration data on
  demand (the `SequenceFrames` registration reads)
"""
from __future__ import annotations

import collections.abc
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from gscan.errors import InputError
from gscan.features import Detection
from gscan.geometry.plane import Plane
from gscan.io.camera import RGBDFrame
from gscan.io.sequence import Sequence, spread_indices
from gscan.registration.edges import RegData, bounded_map
from gscan.scanning.capture_mode import (
    MOVING_OBJECT,
    STATIC_OBJECT,
    background_depth,
    detect_mode,
    foreground_mask,
)
from gscan.scanning.segment import SegmentParams, segment_frame
from gscan.scanning.select import FrameSelector, Selection, SelectionParams
from gscan.scanning.store import FrameStore, StoredFrame
from gscan.template.db import TemplateDB

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence

# threads for per-frame and per-edge work: the target machines have 2 cores (the results do not depend on it)
WORKERS = 2
REG_CACHE = 8  # frames whose registration data (keypoints, depth samples) stays loaded: the sequential window


@dataclass
class Frame:
    """A kept frame, as the stages after the load hold it: its images are in the scan's `FrameStore` ("color",
    "depth", "given_mask"; "object_mask" of a moving object when computed; "mask" once segmented), its keypoints in
    the database (camera frame until the last stage); `FrameData` loads them on demand."""

    stored: StoredFrame
    n_keypoints: int = 0  # registration keypoints with depth
    depth_m: float | None = None  # their median depth (m): the depth the frame looks at
    plane_cam: Plane | None = None  # support plane found while computing a moving object's mask
    object_keypoints: int = 0  # registration keypoints inside its object mask (set at the segment stage)

    @property
    def name(self) -> str:
        return self.stored.name


class FrameData:
    """The kept frames' images, masks and registration data, loaded on demand: images from the store, keypoints
    from the database. Registration data of the last `REG_CACHE` frames used is kept (the sequential pairs and the
    workers' frames), so memory does not grow with the capture. icp_voxel: the voxel of the ICP clouds (m), None:
    no ICP. detections: frames' whole-frame detections made
    before the features stage (the camera check's), by name, each taken by that stage. Thread-safe."""

    def __init__(self, frames: list[Frame], store: FrameStore, db: TemplateDB, mode: str, masks_given: bool,
                 icp_voxel: float | None, detections: dict[str, Detection] | None = None):
        self.frames, self.store, self.db, self.mode, self.masks_given = frames, store, db, mode, masks_given
        self.icp_voxel = icp_voxel
        self.detections = {} if detections is None else detections
        # the keypoints the frames were registered with (`gscan.features.depth.choose_source`), set by the
        # features stage: {"source": sift|depth|both, "chosen_by": auto|config, "median_image_keypoints": n|None}
        self.keypoints: dict = {"source": "sift", "chosen_by": "config", "median_image_keypoints": None}
        self._cache: OrderedDict[int, RegData] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def names(self) -> list[str]:
        return [f.name for f in self.frames]

    def n_keypoints(self, k: int) -> int:
        return self.frames[k].n_keypoints

    def depth_m(self, k: int) -> float | None:
        return self.frames[k].depth_m

    def frame(self, k: int) -> RGBDFrame:
        """Frame k as read (colour, depth, given mask)."""
        return self.frames[k].stored.load(self.store)

    def object_mask(self, k: int) -> np.ndarray | None:
        """A moving object's mask [H x W] bool in frame k (given, or computed at the load), or None."""
        if self.mode != MOVING_OBJECT:
            return None
        name = self.frames[k].name
        return self.store.get(name, "given_mask" if self.masks_given else "object_mask")

    def descriptors(self, k: int) -> np.ndarray:
        """Frame k's registration descriptors [N x D] (from the database)."""
        feats = self.db.features(self.frames[k].name)
        assert feats is not None, self.frames[k].name
        return feats.descriptors

    def reg(self, k: int) -> RegData:
        """Registration data of frame k (cached)."""
        with self._lock:
            if k in self._cache:
                self._cache.move_to_end(k)
                return self._cache[k]
        f = self.frames[k].stored
        feats = self.db.features(f.name)
        assert feats is not None, f.name
        data = RegData.of_frame(feats, self.store.need(f.name, "depth"), self.store.need(f.name, "color"),
                                f.intrinsics, self.object_mask(k), self.icp_voxel)
        with self._lock:
            self._cache[k] = data
            while len(self._cache) > REG_CACHE:
                self._cache.popitem(last=False)
        return data


class InputFrames(collections.abc.Sequence):
    """The input's frames as a lazy sequence (what `detect_mode` reads a few of): frame i, or the next usable one
    after it (before it at the end) when it cannot be read."""

    def __init__(self, seq: Sequence | RecordingSequence):
        self.seq = seq
        self._read: dict[int, RGBDFrame] = {}  # the few frames read (detect_mode reads each twice)

    def __len__(self) -> int:
        return len(self.seq.names)

    def __getitem__(self, i):
        names = self.seq.names
        for j in [*range(i, len(names)), *range(i - 1, -1, -1)]:
            if j not in self._read:
                try:
                    self._read[j] = self.seq[names[j]]
                except InputError:
                    continue
            return self._read[j]
        raise _NoUsableFrame


class _NoUsableFrame(Exception):
    pass


def detect_capture_mode(seq: Sequence | RecordingSequence, mode_option: str) -> tuple[str, bool]:
    """(capture mode, whether every frame comes with an object mask): the mode from a few frames spread over the
    input (`detect_mode`) unless given."""
    names = seq.names
    given = isinstance(seq, Sequence) and seq.has_masks and all(seq.files(n).mask is not None for n in names)
    if mode_option != "auto":
        return mode_option, given
    try:
        return detect_mode(InputFrames(seq)).mode, given
    except _NoUsableFrame:  # the load says so, on one line
        return STATIC_OBJECT, given


def load_frames(seq: Sequence | RecordingSequence, mode: str, masks_given: bool, params: SelectionParams,
                seg: SegmentParams, store: FrameStore, advance: Callable[[int], None], prefix: str = ""
                ) -> tuple[list[Frame], list[tuple[str, InputError]], Selection, list[StoredFrame]]:
    """Reads the input once, in order, keeping the frames frame selection keeps (`gscan.scanning.select`): their images
    go to the store, with a moving object's mask (`moving_object_masks`: the support plane and the object on it,
    else the difference from the background). Returns (kept frames, frames that could not be read, selection, the
    frames selection skipped with their images in the store, to be placed by registration to the kept frame each was
    compared with), the frames named `prefix` + their name in the input (a capture's name and "/" when a scan has
    several)."""
    moving = mode == MOVING_OBJECT
    selector = FrameSelector(params, mask_needed=moving)
    selection = Selection(params)
    frames: list[Frame] = []
    skipped: list[StoredFrame] = []
    failed: list[tuple[str, InputError]] = []
    for name, frame in read_ahead(seq):
        advance(1)
        name = prefix + name
        if isinstance(frame, InputError):
            failed.append((name, frame))
            continue
        if prefix:
            frame = replace(frame, name=name)
        why = selector.consider(frame)
        if why is not None:
            selection.skipped[name] = why
            if selector.reference is not None:  # kept in the store, to be placed by registration to its reference
                selection.reference[name] = selector.reference
                skipped.append(StoredFrame.put(store, frame))
            continue
        f = Frame(StoredFrame.put(store, frame))
        selection.kept.append(name)
        mask = frame.mask
        if moving and not masks_given:
            s_ = segment_frame(replace(frame, mask=None), seg)
            f.plane_cam = s_.plane_cam
            mask = s_.mask if s_.plane_cam is not None else None
            store.put(name, object_mask=mask)
        selector.keep(frame, mask if moving else None)
        frames.append(f)
    if moving and not masks_given and any(f.plane_cam is None for f in frames):
        # without a support plane (an object in hand) the object is what stands out of the background
        picks = spread_indices(len(frames), seg.background_frames, nearest=True)
        bg = background_depth([store.need(frames[k].name, "depth") for k in picks])
        for f in frames:
            if f.plane_cam is None:
                store.put(f.name, object_mask=foreground_mask(store.need(f.name, "depth"), bg))
    return frames, failed, selection, skipped


def read_ahead(seq: Sequence | RecordingSequence) -> Iterator[tuple[str, RGBDFrame | InputError]]:
    """(name, frame or why it could not be read) for every input frame in order, the next one decoded in a thread
    meanwhile (decoding releases the GIL)."""
    def read(name: str) -> RGBDFrame | InputError:
        try:
            return seq[name]
        except InputError as e:
            return e

    with ThreadPoolExecutor(max_workers=1) as pool:
        yield from zip(seq.names, bounded_map(pool, read, seq.names, 2), strict=True)
