"""RGB-D sequences: open a folder in one of the four layouts, validate it, load frames lazily.

Opening checks every frame cheaply (files present, image headers: sizes and depth bit depth) and
fully loads the first usable frame's depth to check the depth scale. Frames that cannot be used
are listed in `Sequence.problems` (name -> reason naming the file) and left out of `names`; only
a sequence with no usable frame, or a sequence-wide problem (intrinsics, depth scale), raises.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gscan.errors import InputError, not_a_file
from gscan.io.camera import DepthCamera, FrameIteration, Intrinsics, RGBDFrame, implausible_intrinsics, load_intrinsics
from gscan.io.images import (
    MAX_DEPTH_SCALE,
    check_depth_range,
    check_depth_scale,
    image_size,
    load_frame,
    read_depth,
)
from gscan.io.layouts import FrameSpec, Layout, discover
from gscan.io.recordings.kinds import recording_format

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence

log = logging.getLogger(__name__)

_EIGHT_BIT_MODES = {"1", "L", "P", "LA", "PA", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr", "LAB", "HSV"}


def spread_indices(n: int, k: int, nearest: bool = False) -> list[int]:
    """At most k indices spread evenly over range(n), the first and (k > 1) the last included (each rounded down, or to
    the nearest with `nearest`; all of them when n <= k), in order: the frames or views a stage samples from a
    sequence."""
    x = np.linspace(0, n - 1, min(k, n))
    return [int(i) for i in np.unique(x.round() if nearest else x).astype(int)] if n > 0 else []


def image_header(path: Path) -> tuple[int, int, str]:
    """(width, height, PIL mode) read from the image header only; InputError naming the file (also for an
    OpenEXR image and one above the pixel limit, `gscan.io.images.image_size`)."""
    if not path.is_file():
        raise not_a_file(path, "image")
    try:
        return image_size(path)
    except PermissionError:
        raise InputError(path, "permission denied") from None
    except ValueError as e:
        raise InputError(path, str(e)) from None
    except Exception as e:  # noqa: BLE001 - PIL raises many types (UnidentifiedImageError, SyntaxError, OSError...)
        raise InputError(path, f"corrupt or unrecognised image ({e.__class__.__name__})") from None


def _depth_mode_problem(mode: str) -> str | None:
    if mode.startswith("I;16") or mode == "I":
        return None
    if mode == "F":
        return "depth is float; depth must be 16-bit unsigned (e.g. millimetres)"
    if mode in ("1", "L", "P"):
        return "depth is 8-bit; depth must be 16-bit unsigned (e.g. millimetres)"
    return f"depth is not a single-channel 16-bit image (mode {mode})"


class Sequence(FrameIteration):
    """An opened RGB-D sequence (see open_sequence). Indexing loads a frame from disk.

    Attributes: name (folder name), format ("capture"|"open3d"|"tum"|"bop"), root, names (usable
    frame names in order), intrinsics (sequence / first frame), depth_scale (metres per raw unit),
    gt_T_cam_obj / gt_T_world_cam (name -> [4 x 4], or None when the layout has none), gt_instances (BOP: name ->
    every ground-truth instance of obj_id, (index in the image's scene_gt list, T_cam_obj [4 x 4]); else None),
    has_masks, problems (name -> reason, frames left out or that failed to load), obj_id (BOP: the object
    whose ground truth and masks are used, None for the other layouts or a BOP folder without scene_gt).
    """

    def __init__(self, layout: Layout, specs: dict[str, FrameSpec], intrinsics: Intrinsics,
                 frame_intrinsics: dict[str, Intrinsics], depth_scale: float, frame_scales: dict[str, float],
                 problems: dict[str, str], depth_camera: DepthCamera | None = None):
        self.root: Path = layout.root
        self.name: str = layout.root.name
        self.format: str = layout.format
        self._specs = specs
        self.names: list[str] = list(specs)
        self.intrinsics = intrinsics
        self._frame_intrinsics = frame_intrinsics
        self.depth_scale = depth_scale
        self._frame_scales = frame_scales
        keep = set(specs)
        self.gt_T_cam_obj = None if layout.gt_T_cam_obj is None else \
            {n: T for n, T in layout.gt_T_cam_obj.items() if n in keep}
        self.gt_instances = None if layout.gt_instances is None else \
            {n: v for n, v in layout.gt_instances.items() if n in keep}
        self.gt_T_world_cam = None if layout.gt_T_world_cam is None else \
            {n: T for n, T in layout.gt_T_world_cam.items() if n in keep}
        self.has_masks: bool = any(s.mask is not None for s in specs.values())
        self.problems: dict[str, str] = problems
        self.damage: list[str] = []  # a recording's damaged records (`RecordingSequence.damage`); none in a folder
        self.obj_id: int | None = layout.obj_id
        self.gt_problems: dict[str, str] = dict(layout.gt_problems)  # unreadable ground-truth files, left out
        self.depth_camera = depth_camera  # unregistered depth's own camera (frames reproject it), or None

    def __len__(self) -> int:
        return len(self.names)

    def __repr__(self) -> str:
        return (f"Sequence({self.name!r}, format={self.format!r}, frames={len(self)}, "
                f"problems={len(self.problems)}, masks={self.has_masks})")

    def files(self, key: int | str) -> FrameSpec:
        """Files of a frame (by index or name)."""
        name = self.names[key] if isinstance(key, (int, np.integer)) else key
        if name not in self._specs:
            raise KeyError(name)
        return self._specs[name]

    def fingerprints(self) -> dict[str, dict[str, str] | None]:
        """What the frames' files hold, cheaply: {name: {"color"|"depth"|"mask": "<bytes>:<blake2b-128 hex>"}}
        for the usable frames, None for the frames left out (`problems`). A resumed scan compares them with
        the ones its partial database was started from. InputError naming a file that cannot be read."""
        out: dict[str, dict[str, str] | None] = dict.fromkeys(self.problems)
        for name in self.names:
            spec = self._specs[name]
            out[name] = {role: _file_fingerprint(p) for role, p in (("color", spec.color), ("depth", spec.depth),
                                                                     ("mask", spec.mask)) if p is not None}
        return out

    def frame_intrinsics(self, key: int | str) -> Intrinsics:
        return self._frame_intrinsics.get(self.files(key).name, self.intrinsics)

    def __getitem__(self, key: int | str) -> RGBDFrame:
        """Load frame `key` (index or name): RGB colour, depth in metres, mask when present.

        Raises InputError naming the file when it turns out unusable (also recorded in problems).
        """
        spec = self.files(key)
        try:
            return load_frame(spec.color, spec.depth, self.frame_intrinsics(spec.name),
                              self._frame_scales.get(spec.name, self.depth_scale), spec.mask, spec.name,
                              check_range=False, depth_camera=self.depth_camera)
        except InputError as e:
            self.problems[spec.name] = str(e)
            raise



def _file_fingerprint(path: Path) -> str:
    """"<size>:<blake2b-128 hex>" of a file's bytes (1 MiB reads)."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    size = 0
    try:
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
                size += len(chunk)
    except OSError as e:
        raise InputError(path, f"cannot read the file ({e.strerror or e})") from None
    return f"{size}:{h.hexdigest()}"


def _resolve_intrinsics(layout: Layout, override: Intrinsics | str | Path | None, w: int, h: int) -> Intrinsics:
    """The sequence-wide intrinsics (not for per-frame calibrations, which each frame checks itself)."""
    if isinstance(override, Intrinsics):
        return override
    if override is not None:
        return load_intrinsics(Path(override), w, h)
    if layout.intrinsics_file is not None:
        return load_intrinsics(layout.intrinsics_file, w, h)
    if layout.format == "tum":
        raise InputError(layout.root, f"no {layout.intrinsics_expected}", fix="intrinsics")
    expected = layout.root / layout.intrinsics_expected
    if expected.is_dir():  # found by name but not taken: say why, not that it is missing
        raise InputError(expected, "is a folder, not the intrinsics file (a text file of the 3x3 camera matrix)",
                         fix="intrinsics")
    raise InputError(expected, "intrinsics file not found (intrinsics are never guessed)", fix="intrinsics")


def sized_depth_camera(depth_camera: DepthCamera, depth_images: Iterable[Path], where: Path) -> DepthCamera:
    """The depth camera for the size of the first of `depth_images` whose header reads (as it is when none reads);
    InputError naming the camera's file (else `where`) when it cannot be of that size."""
    for path in depth_images:
        try:
            w, h = image_header(path)[:2]
        except InputError:
            continue
        if depth_camera.size is not None and depth_camera.size != (w, h):
            raise InputError(depth_camera.source or where, f"intrinsics are for {depth_camera.size[0]}x"
                             f"{depth_camera.size[1]} images but the images are {w}x{h}")
        try:
            return depth_camera.sized(w, h)
        except ValueError as e:
            raise InputError(depth_camera.source or where, str(e)) from None
    return depth_camera


def open_sequence(path: str | Path, format: str = "auto", intrinsics: Intrinsics | str | Path | None = None,
                  depth_scale: float | None = None, obj_id: int | None = None, color_topic: str | None = None,
                  depth_topic: str | None = None,
                  depth_camera: DepthCamera | None = None) -> Sequence | RecordingSequence:
    """Open an RGB-D sequence folder, or a recording (`.bag`, `.db3`, `.mcap`, rosbag2 folder; see
    `gscan.io.recordings.open_recording`, which takes color_topic / depth_topic).

    format: "auto" (detected) or "capture" | "open3d" | "tum" | "bop".
    intrinsics: Intrinsics or a cam_K.txt / Open3D JSON file overriding the layout's own.
    depth_scale: metres per raw depth unit overriding the layout's (capture/Open3D 0.001, TUM 1/5000,
    BOP scene_camera depth_scale / 1000). obj_id: BOP object whose scene_gt pose / mask is used
    (default: the first object of the first image).
    depth_camera: for depth images not registered to the colour images, their own camera (`DepthCamera`,
    `load_depth_camera`; one of no particular size takes the first depth image's); each frame's depth is then
    reprojected into the colour camera. Recordings carry their own.
    Raises InputError naming the file for a missing/unrecognised folder, missing intrinsics, a
    depth scale that puts the scene outside 0.05-20 m, or when no frame is usable.
    """
    root = Path(path)
    kind = recording_format(root)
    if kind is not None:
        if depth_camera is not None:
            raise InputError(root, f"is a recording ({kind}), which carries its own depth calibration; "
                             "--depth-intrinsics / --depth-to-color are for folders")
        if format not in ("auto", kind):
            raise InputError(root, f"is a recording ({kind}); --format {format} is for folders")
        from gscan.io.recordings.sequence import open_recording

        return open_recording(root, color_topic, depth_topic, intrinsics, depth_scale)
    if color_topic is not None or depth_topic is not None:
        raise InputError(root, "--color-topic / --depth-topic apply to recordings (.bag, .db3, .mcap), not folders")
    layout = discover(root, format, obj_id)
    if depth_scale is not None:
        check_depth_scale(depth_scale, root)
    problems = dict(layout.problems)
    specs: dict[str, FrameSpec] = {}
    sizes: dict[str, tuple[int, int]] = {}
    depth_cam = None if depth_camera is None else sized_depth_camera(depth_camera, (f.depth for f in layout.frames),
                                                                     root)
    for f in layout.frames:
        try:
            cw, ch, _ = image_header(f.color)
            dw, dh, mode = image_header(f.depth)
            bad = _depth_mode_problem(mode)
            if bad:
                raise InputError(f.depth, bad)
            if depth_cam is not None and depth_cam.size is not None and (dw, dh) != depth_cam.size:
                raise InputError(f.depth, f"depth is {dw}x{dh} but the depth camera's intrinsics are for "
                                 f"{depth_cam.size[0]}x{depth_cam.size[1]} images")
            if depth_cam is None and (dw, dh) != (cw, ch):
                raise InputError(f.depth, f"depth is {dw}x{dh} but colour image {f.color.name} is {cw}x{ch}")
            if f.mask is not None:
                mw, mh, _ = image_header(f.mask)
                if (mw, mh) != (cw, ch):
                    raise InputError(f.mask, f"mask is {mw}x{mh} but colour image {f.color.name} is {cw}x{ch}")
        except InputError as e:
            problems[f.name] = str(e)
            continue
        specs[f.name] = f
        sizes[f.name] = (cw, ch)
    if not specs:
        first = next(iter(problems.items()), None)
        detail = f"; first: {first[0]}: {first[1]}" if first else ""
        raise InputError(root, f"no usable RGB-D frame ({len(problems)} unusable){detail}")

    per_frame = layout.per_frame_K and intrinsics is None
    intr = None if per_frame else _resolve_intrinsics(layout, intrinsics, *sizes[next(iter(specs))])
    frame_intr: dict[str, Intrinsics] = {}
    frame_scales: dict[str, float] = {}
    for name, f in list(specs.items()):
        w, h = sizes[name]
        if per_frame:
            try:
                if f.K is None:
                    raise ValueError("no cam_K")
                K = np.asarray(f.K, dtype=float).reshape(3, 3)
                intr_f = Intrinsics.from_matrix(K, w, h)
                why = implausible_intrinsics(K, w, h)
                if why:
                    raise ValueError(why)
                frame_intr[name] = intr_f
            except ValueError as e:
                problems[name] = f"{f.color.name}: invalid cam_K in scene_camera.json ({e})"
                del specs[name]
                continue
        elif intr is not None and (intr.width, intr.height) != (w, h):  # intr: set unless per_frame
            problems[name] = f"{f.color.name} is {w}x{h} but the intrinsics are for {intr.width}x{intr.height}"
            del specs[name]
            continue
        if depth_scale is None and f.depth_scale is not None:
            if not (np.isfinite(f.depth_scale) and 0 < f.depth_scale <= MAX_DEPTH_SCALE):
                problems[name] = f"{f.color.name}: invalid depth_scale in scene_camera.json"
                del specs[name]
                continue
            frame_scales[name] = f.depth_scale
    scale = float(depth_scale) if depth_scale is not None else layout.depth_scale

    # Depth-scale sanity check on the first frame whose depth reads.
    for name in list(specs):
        f = specs[name]
        s = frame_scales.get(name, scale)
        try:
            depth = read_depth(f.depth, s)
        except InputError as e:
            problems[name] = str(e)
            del specs[name]
            continue
        check_depth_range(depth, s, f.depth)
        if depth_scale is None and name in frame_scales:
            scale = frame_scales[name]
        break
    if not specs:
        first_p = next(iter(problems.items()))
        raise InputError(root, f"no usable RGB-D frame ({len(problems)} unusable); first: {first_p[0]}: {first_p[1]}")
    if per_frame or intr is None:
        intr = frame_intr[next(iter(specs))]
    for name, reason in problems.items():
        log.warning("%s: frame %s left out: %s", root, name, reason)
    return Sequence(layout, specs, intr, frame_intr, scale, frame_scales, problems, depth_cam)
