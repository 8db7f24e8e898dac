"""Discovery of the four folder layouts (README, "Input layouts"): which files form which frame.

Discovery only lists files and reads the small text/JSON side files (intrinsics, ground truth);
images are checked by gscan.io.sequence. Every function raises InputError naming the file.
"""
from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.io.poses import check_rigid, read_open3d_log, read_pose_txt, tum_pose

log = logging.getLogger(__name__)

FORMATS = ("capture", "open3d", "tum", "bop")
COLOR_EXTS = (".png", ".jpg", ".jpeg")
# Depth folders are listed with every image extension so that a wrong-type depth (8-bit JPEG,
# float TIFF/EXR) is reported as such instead of as "missing".
DEPTH_EXTS = (".png", ".pgm", ".tif", ".tiff", ".exr", ".jpg", ".jpeg")
MASK_EXTS = (".png", ".jpg", ".jpeg", ".bmp")
TUM_MAX_DT = 0.02  # s, max timestamp difference of an associated colour/depth pair


@dataclass
class FrameSpec:
    """Files of one frame. intrinsics / depth_scale are per-frame values (BOP) or None (sequence-wide)."""

    name: str
    color: Path
    depth: Path
    mask: Path | None = None
    K: np.ndarray | None = None          # [3 x 3] per-frame calibration (BOP), size taken from the image
    depth_scale: float | None = None     # metres per raw unit, per frame (BOP)


@dataclass
class Layout:
    """What a layout's discovery found (before any image is opened)."""

    format: str
    root: Path
    frames: list[FrameSpec]
    depth_scale: float                         # metres per raw unit (format default)
    intrinsics_file: Path | None = None        # cam_K.txt / camera_intrinsic.json found in the folder
    intrinsics_expected: str = ""              # what to name when intrinsics are missing
    per_frame_K: bool = False                  # BOP: intrinsics come with each frame
    gt_T_cam_obj: dict[str, np.ndarray] | None = None
    # BOP: every ground-truth instance of `obj_id` per image, (its index in the image's scene_gt list, T_cam_obj)
    gt_instances: dict[str, list[tuple[int, np.ndarray]]] | None = None
    gt_T_world_cam: dict[str, np.ndarray] | None = None
    problems: dict[str, str] = field(default_factory=dict)
    obj_id: int | None = None                  # BOP: the object whose scene_gt pose / mask is used
    # optional ground-truth files that could not be read (path -> reason): left out, reported as warnings;
    # what needs the ground truth (evaluation) refuses them (`require_ground_truth`)
    gt_problems: dict[str, str] = field(default_factory=dict)


def require_ground_truth(gt_problems: dict[str, str]) -> None:
    """InputError naming the first unreadable ground-truth file, for a consumer of the ground truth."""
    for path, reason in gt_problems.items():
        raise InputError(path, f"unreadable ground truth: {reason}")


def _optional_gt_problem(problems: dict[str, str], e: InputError) -> None:
    """Record an unreadable optional ground-truth file (a scan does not use it) and warn about it."""
    problems[str(e.path)] = e.reason
    log.warning("%s: ground truth left out: %s", e.path, e.reason)


def natural_key(s: str) -> tuple:
    """Sort key: digit runs compare as numbers ("f2" < "f10"); ties broken by the raw string."""
    parts = tuple((0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", s) if t)
    return parts, s


def frame_name(path: Path | str) -> str:
    """A frame's name: the file's stem, with bytes that are not UTF-8 (Python's surrogate escapes in
    file names) written as \\xNN so that the name can be stored and printed."""
    return Path(path).stem.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def list_images(folder: Path, exts: tuple[str, ...]) -> dict[str, Path]:
    """Files of `folder` with one of `exts` (case-insensitive) keyed by `frame_name`, in natural order.

    Raises InputError naming the second file when two files share a stem (000001.png, 000001.jpg).
    """
    out: dict[str, Path] = {}
    try:
        entries = sorted(folder.iterdir(), key=lambda p: natural_key(p.name))
    except PermissionError:
        raise InputError(folder, "permission denied") from None
    except OSError as e:
        raise InputError(folder, f"cannot list folder ({e.__class__.__name__})") from None
    for p in entries:
        if p.name.startswith(".") or p.suffix.lower() not in exts:
            continue
        name = frame_name(p)
        if name in out:
            raise InputError(p, f"duplicate frame name '{name}': {out[name].name} has the same stem")
        out[name] = p
    return dict(sorted(out.items(), key=lambda kv: natural_key(kv[0])))


def _require_dir(path: Path, what: str) -> None:
    if not path.is_dir():
        raise InputError(path, f"{what} folder not found")


def _pair(colors: dict[str, Path], depths: dict[str, Path], masks: dict[str, Path] | None,
          depth_dir: Path) -> tuple[list[FrameSpec], dict[str, str]]:
    frames, problems = [], {}
    for name, c in colors.items():
        d = depths.get(name)
        if c.is_dir():
            link = " (a symbolic link to one)" if c.is_symlink() else ""
            problems[name] = f"{c.name}: is a folder{link}, not a colour image"
            continue
        if d is None:
            problems[name] = f"{c.name}: no depth image {name}.* in {depth_dir.name}/"
            continue
        frames.append(FrameSpec(name, c, d, masks.get(name) if masks else None))
    return frames, problems


def _color_and_depth(root: Path, color_dir: str) -> tuple[dict[str, Path], dict[str, Path]]:
    """The colour images of root/color_dir (at least one, else InputError) and the depth images of root/depth."""
    _require_dir(root / color_dir, f"{color_dir}/")
    _require_dir(root / "depth", "depth/")
    colors = list_images(root / color_dir, COLOR_EXTS)
    if not colors:
        raise InputError(root / color_dir, "no colour images (.png/.jpg) in folder")
    return colors, list_images(root / "depth", DEPTH_EXTS)


def discover_capture(root: Path) -> Layout:
    """Object-capture layout: rgb/, depth/ (uint16 mm), optional masks/, cam_K.txt, annotated_poses/."""
    colors, depths = _color_and_depth(root, "rgb")
    masks = list_images(root / "masks", MASK_EXTS) if (root / "masks").is_dir() else None
    frames, problems = _pair(colors, depths, masks, root / "depth")
    gt = None
    gt_problems: dict[str, str] = {}
    if (root / "annotated_poses").is_dir():
        gt = {}
        for f in frames:
            p = root / "annotated_poses" / f"{f.name}.txt"
            if p.is_file():
                try:
                    gt[f.name] = read_pose_txt(p)
                except InputError as e:
                    _optional_gt_problem(gt_problems, e)
    camk = root / "cam_K.txt"
    return Layout("capture", root, frames, 0.001, camk if camk.is_file() else None, "cam_K.txt",
                  gt_T_cam_obj=gt, problems=problems, gt_problems=gt_problems)


def discover_open3d(root: Path) -> Layout:
    """Open3D / Redwood layout: color/, depth/ (uint16 mm), camera_intrinsic.json, trajectory.log."""
    colors, depths = _color_and_depth(root, "color")
    if not set(colors) & set(depths) and len(colors) == len(depths):
        # Redwood-style numbering that differs between the folders: pair in sorted order.
        log.info("%s: colour and depth stems differ; pairing them in sorted order", root)
        depths = dict(zip(colors, depths.values(), strict=True))
    frames, problems = _pair(colors, depths, None, root / "depth")
    gt: dict[str, np.ndarray] | None = None
    gt_problems: dict[str, str] = {}
    traj = root / "trajectory.log"
    if traj.is_file():
        names = list(colors)
        try:
            gt = {}
            for idx, T in read_open3d_log(traj):
                if not 0 <= idx < len(names):
                    raise InputError(traj, f"pose for frame index {idx} but there are {len(names)} colour images")
                gt[names[idx]] = T
        except InputError as e:
            gt = None
            _optional_gt_problem(gt_problems, e)
    cam = root / "camera_intrinsic.json"
    return Layout("open3d", root, frames, 0.001, cam if cam.is_file() else None, "camera_intrinsic.json",
                  gt_T_world_cam=gt, problems=problems, gt_problems=gt_problems)


def _read_tum_list(path: Path) -> list[tuple[float, list[str]]]:
    if not path.is_file():
        raise InputError(path, "TUM list file not found")
    out = []
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read TUM list ({e.__class__.__name__})") from None
    for i, line in enumerate(text.splitlines()):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            t = float(parts[0])
        except ValueError:
            raise InputError(path, f"line {i + 1}: expected 'timestamp ...', got {line[:40]!r}") from None
        if len(parts) < 2 or not np.isfinite(t):
            raise InputError(path, f"line {i + 1}: expected 'timestamp value(s)', got {line[:40]!r}")
        out.append((t, parts[1:]))
    return out


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt: float = TUM_MAX_DT) -> dict[int, int]:
    """TUM associate.py: greedily pair timestamps closest first, each used once, |dt| <= max_dt.

    t_a: [Na], t_b: [Nb] seconds. Returns {index in a: index in b}.
    """
    if len(t_a) == 0 or len(t_b) == 0:
        return {}
    diff = np.abs(np.asarray(t_a)[:, None] - np.asarray(t_b)[None, :])
    ia, ib = np.nonzero(diff <= max_dt)
    order = np.lexsort((ib, ia, diff[ia, ib]))
    out: dict[int, int] = {}
    used_b: set[int] = set()
    for k in order:
        a, b = int(ia[k]), int(ib[k])
        if a not in out and b not in used_b:
            out[a] = b
            used_b.add(b)
    return out


def discover_tum(root: Path) -> Layout:
    """TUM RGB-D layout: rgb.txt and depth.txt associated by timestamp, depth factor 5000, groundtruth.txt."""
    rgb_list = _read_tum_list(root / "rgb.txt")
    depth_list = _read_tum_list(root / "depth.txt")
    if not rgb_list:
        raise InputError(root / "rgb.txt", "lists no colour images")
    t_rgb = np.array([t for t, _ in rgb_list])
    t_dep = np.array([t for t, _ in depth_list])
    pairs = associate(t_rgb, t_dep)
    frames: list[FrameSpec] = []
    problems: dict[str, str] = {}
    seen: dict[str, str] = {}
    for i, (_t, vals) in enumerate(rgb_list):
        c = root / vals[0]
        name = frame_name(vals[0])
        if name in seen:
            raise InputError(root / "rgb.txt", f"duplicate frame name '{name}' ({seen[name]} and {vals[0]})")
        seen[name] = vals[0]
        if i not in pairs:
            problems[name] = f"{c.name}: no depth within {TUM_MAX_DT} s in depth.txt"
            continue
        frames.append(FrameSpec(name, c, root / depth_list[pairs[i]][1][0]))
    order = {frame_name(v[0]): t for t, v in rgb_list}
    frames.sort(key=lambda f: (order[f.name], natural_key(f.name)))  # TUM frames are in time order
    gt: dict[str, np.ndarray] | None = None
    gt_problems: dict[str, str] = {}
    gt_path = root / "groundtruth.txt"
    if gt_path.is_file():
        try:
            gt_list = _read_tum_list(gt_path)
            t_gt = np.array([t for t, _ in gt_list])
            name_t = {frame_name(v[0]): t for t, v in rgb_list}
            gt = {}
            if len(t_gt):
                for f in frames:
                    j = int(np.argmin(np.abs(t_gt - name_t[f.name])))
                    if abs(t_gt[j] - name_t[f.name]) <= TUM_MAX_DT:
                        gt[f.name] = tum_pose(gt_list[j][1], gt_path)
        except InputError as e:
            gt = None
            _optional_gt_problem(gt_problems, e)
    return Layout("tum", root, frames, 1.0 / 5000.0, None,
                  "intrinsics (the TUM layout carries none)",
                  gt_T_world_cam=gt, problems=problems, gt_problems=gt_problems)


def _read_json(path: Path) -> dict:
    try:
        d = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise InputError(path, f"malformed JSON ({e.__class__.__name__}: {e})"[:300]) from None
    if not isinstance(d, dict):
        raise InputError(path, "malformed JSON: expected an object keyed by image id")
    return d


def discover_bop(root: Path, obj_id: int | None = None) -> Layout:
    """BOP scene: rgb/ (or gray/), depth/, scene_camera.json (cam_K, depth_scale: raw * s = mm),
    optional scene_gt.json (-> T_cam_obj of `obj_id`, default the first image's first object: its first
    instance in gt_T_cam_obj, every instance in gt_instances) and mask_visib/ or mask/
    ({im_id:06d}_{instance:06d}.png, the first instance's)."""
    cam_path = root / "scene_camera.json"
    if not cam_path.is_file():
        raise InputError(cam_path, "BOP scene_camera.json not found")
    rgb_dir = root / "rgb" if (root / "rgb").is_dir() else root / "gray"
    _require_dir(rgb_dir, "rgb/")
    _require_dir(root / "depth", "depth/")
    colors = list_images(rgb_dir, COLOR_EXTS)
    if not colors:
        raise InputError(rgb_dir, "no colour images (.png/.jpg) in folder")
    depths = list_images(root / "depth", DEPTH_EXTS)
    cams = _read_json(cam_path)
    gt_path = root / "scene_gt.json"
    scene_gt = _read_json(gt_path) if gt_path.is_file() else None
    mask_dir = next((root / m for m in ("mask_visib", "mask") if (root / m).is_dir()), None)
    frames, problems = _pair(colors, depths, None, root / "depth")
    kept: list[FrameSpec] = []
    gt: dict[str, np.ndarray] = {}
    instances: dict[str, list[tuple[int, np.ndarray]]] = {}
    for f in frames:
        try:
            im_id = int(f.name)
        except ValueError:
            problems[f.name] = f"{f.color.name}: BOP image names must be integer ids"
            continue
        cam = cams.get(str(im_id)) or {}  # none: no cam_K
        try:
            f.K = np.asarray(cam["cam_K"], dtype=np.float64).reshape(3, 3)
            f.depth_scale = float(cam.get("depth_scale", 1.0)) / 1000.0
        except (TypeError, KeyError, ValueError, AttributeError, OverflowError):
            problems[f.name] = f"{f.color.name}: no valid cam_K for image {im_id} in {cam_path.name}"
            continue
        if scene_gt is not None:
            entries = scene_gt.get(str(im_id)) or []
            try:
                if obj_id is None and entries:
                    obj_id = int(entries[0]["obj_id"])
                ks = [k for k, e in enumerate(entries) if int(e["obj_id"]) == obj_id]
                for k in ks:
                    e = entries[k]
                    T = np.eye(4)
                    T[:3, :3] = np.asarray(e["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
                    T[:3, 3] = np.asarray(e["cam_t_m2c"], dtype=np.float64).reshape(3) / 1000.0
                    if not np.all(np.isfinite(T)):
                        raise ValueError("non-finite pose")
                    instances.setdefault(f.name, []).append((k, check_rigid(T, gt_path)))
                if ks:
                    gt[f.name] = instances[f.name][0][1]
                    if mask_dir is not None:
                        m = mask_dir / f"{im_id:06d}_{ks[0]:06d}.png"
                        f.mask = m if m.is_file() else None
            except (TypeError, KeyError, ValueError, AttributeError, OverflowError) as e:
                raise InputError(gt_path, f"malformed entry for image {im_id} ({e.__class__.__name__})") from None
        kept.append(f)
    return Layout("bop", root, kept, 0.001, None, "scene_camera.json", per_frame_K=True,
                  gt_T_cam_obj=gt if scene_gt is not None else None,
                  gt_instances=instances if scene_gt is not None else None, problems=problems, obj_id=obj_id)


def detect_format(root: Path) -> str:
    """Layout of folder `root`: "bop" | "tum" | "capture" | "open3d", or the kind of a recording
    ("bag" | "db3" | "mcap" | "rosbag2", `gscan.io.recordings`); InputError when none fits."""
    from gscan.io.recordings.kinds import recording_format

    kind = recording_format(root)
    if kind is not None:
        return kind
    if not root.exists():
        raise InputError(root, "folder not found")
    if not root.is_dir():
        raise InputError(root, "not a folder (expected an RGB-D sequence folder)")
    if (root / "scene_camera.json").is_file():
        return "bop"
    if (root / "rgb.txt").is_file() and (root / "depth.txt").is_file():
        return "tum"
    if (root / "rgb").is_dir() and (root / "depth").is_dir():
        return "capture"
    if (root / "color").is_dir() and (root / "depth").is_dir():
        return "open3d"
    try:
        empty = not any(root.iterdir())
    except OSError:
        empty = False
    what = "folder is empty" if empty else "no recognisable RGB-D layout"
    raise InputError(root, f"{what}: expected rgb/+depth/ (capture), color/+depth/ (Open3D), "
                     "rgb.txt+depth.txt (TUM) or scene_camera.json (BOP)")


def discover(root: Path, format: str = "auto", obj_id: int | None = None) -> Layout:
    """Run the discovery of `format` (or the detected one) on folder `root`."""
    if format not in ("auto",) + FORMATS:
        raise ValueError(f"format must be 'auto' or one of {FORMATS}, got {format!r}")
    if format == "auto":
        format = detect_format(root)
    elif not root.is_dir():
        raise InputError(root, "folder not found")
    if format == "capture":
        return discover_capture(root)
    if format == "open3d":
        return discover_open3d(root)
    if format == "tum":
        return discover_tum(root)
    return discover_bop(root, obj_id)
