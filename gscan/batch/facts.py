"""What a finished template says about its scan, and how its poses compare with a capture's ground truth.

`template_facts(path)` reads a complete template database: frames, registered and unregistered frames (with
the reasons the scan stored), keyframes, mode and the views' poses. `ground_truth_check(source, facts)`
compares the registered poses with the capture's ground truth where the layout has one (annotated_poses/ or
scene_gt.json: T_cam_obj; TUM / Open3D trajectories: T_world_cam, for a static object only): the ATE of the
camera positions after a rigid alignment (`gscan.evaluate.metrics.ate`) and the frames registered at a wrong
pose (`frame_errors(...).wrong(WRONG_DEG, WRONG_M)`: relative poses against most other frames).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.evaluate.metrics import ate, frame_errors
from gscan.geometry.transforms import inv_T
from gscan.io.layouts import FORMATS, discover
from gscan.io.recordings.kinds import recording_format
from gscan.scanning.modes import STATIC_OBJECT
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)

WRONG_DEG, WRONG_M = 5.0, 0.02  # a registered frame off by more than this against most others is wrong


@dataclass
class TemplateFacts:
    """A complete template's scan: `frames` read (registered, unregistered, unreadable, and skipped by the scan's
    frame selection), the unregistered
    ones by name with their reasons, keyframes, capture mode, the stored input, layout and BOP object, and
    the registered views' poses T_obj_cam [4 x 4] by frame name."""

    frames: int
    registered: int
    unregistered: list[str]
    unregistered_reasons: dict[str, str]
    keyframes: int
    mode: str | None
    input: str | None
    format: str | None
    obj_id: int | None
    T_obj_cam: dict[str, np.ndarray] = field(repr=False)


@dataclass
class GroundTruthCheck:
    """Registered poses against the ground truth: `gt_frames` compared, the ATE (m, rigid alignment) of their
    camera positions (None when no frame was compared), and the frames registered at a wrong pose."""

    reference: str  # "T_cam_obj" or "T_world_cam": the ground truth compared with
    gt_frames: int
    ate_rmse_m: float | None
    ate_max_m: float | None
    wrong_frames: list[str]


def template_facts(path: str | Path) -> TemplateFacts:
    """The scan facts of the complete template `path` (InputError when it is missing, partial or not a
    template)."""
    with TemplateDB.open(path, require_complete=True) as db:
        views = db.views(load_images=False)
        poses = db.poses()
        summary = db.summary()
        reasons = db.get_meta("unregistered_reasons") or {}
        skipped = db.get_meta("skipped") or {}
        mode, stored_input, fmt, obj_id = (db.get_meta(k) for k in ("mode", "input", "format", "obj_id"))
    unregistered = list(poses["unregistered"])
    reasons = {str(k): str(v) for k, v in {**reasons, **skipped}.items()}
    return TemplateFacts(frames=len(views) + len(skipped) + summary.selection.get("skipped", 0),
                         registered=summary.registered, unregistered=unregistered,
                         unregistered_reasons={n: reasons.get(n, "") for n in unregistered},
                         keyframes=summary.keyframes, mode=mode if isinstance(mode, str) else None,
                         input=stored_input if isinstance(stored_input, str) else None,
                         format=fmt if isinstance(fmt, str) else None,
                         obj_id=obj_id if isinstance(obj_id, int) else None,
                         T_obj_cam={n: np.asarray(T, dtype=np.float64) for n, T in poses["frames"].items()})


def ground_truth_check(source: str | Path, facts: TemplateFacts) -> GroundTruthCheck | None:
    """The template's registered poses against the ground truth of the capture `source` it was scanned from;
    None when the capture has none (a recording, a layout without poses, a moving object with a camera
    trajectory only) or its ground truth cannot be read (logged: the scan itself is not at fault)."""
    source = Path(source)
    if recording_format(source) is not None:
        return None
    fmt = facts.format if facts.format in FORMATS else "auto"
    try:
        layout = discover(source, fmt, obj_id=facts.obj_id)
    except InputError as e:
        log.warning("%s: ground truth not read: %s", source, e)
        return None
    if layout.gt_T_cam_obj:
        reference = "T_cam_obj"
        gt = {n: inv_T(np.asarray(T, dtype=np.float64)) for n, T in layout.gt_T_cam_obj.items()}  # T_obj_cam
    elif layout.gt_T_world_cam and facts.mode == STATIC_OBJECT:
        reference = "T_world_cam"
        gt = {n: np.asarray(T, dtype=np.float64) for n, T in layout.gt_T_world_cam.items()}
    else:
        return None
    names = [n for n in facts.T_obj_cam if n in gt]
    if not names:
        return GroundTruthCheck(reference, 0, None, None, [])
    res = ate([facts.T_obj_cam[n] for n in names], [gt[n] for n in names])
    wrong = frame_errors({n: facts.T_obj_cam[n] for n in names}, {n: gt[n] for n in names}).wrong(WRONG_DEG, WRONG_M)
    return GroundTruthCheck(reference, len(names), res.rmse, res.max, wrong)
