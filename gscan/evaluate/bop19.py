"""Evaluate pose estimation over RGB-D scenes with ground truth; write BOP19 results.

`evaluate(template, scenes, output_csv)` runs `gscan.estimate.estimator.Estimator` on every image of
- a BOP scene folder (rgb/, depth/, scene_camera.json, scene_gt.json; ground truth of `obj_id`),
- a capture-layout folder (rgb/, depth/, cam_K.txt, annotated_poses/ = T_cam_obj per image), or
- a folder whose sub-folders are such scenes (scene ids from numeric folder names, else their order).

Results CSV (BOP19, https://bop.felk.cvut.cz/challenges/): header `scene_id,im_id,obj_id,score,R,t,time`,
R = 9 numbers row-major, t = 3 numbers in millimetres, both space-separated; time = seconds spent on
the image (the same for all rows of one image). Only found poses are written. The file is written
to a temporary name and renamed, so it is never half-written. `score_results(results_csv, scenes, model_path)`
scores such a CSV (any method's) with the same errors and metrics, without estimating.

Several instances per image, as BOP19 scores them: a BOP dataset's test targets (test_targets_bop19.json in its
root, two folders above a scene: scene_id, im_id, obj_id, inst_count) choose the images scored and how many
instances of the object each holds; the inst_count most visible ground-truth instances (scene_gt_info.json's
visib_fract) are scored, and as many of the image's best-scoring estimates. Without targets every ground-truth
instance of the object in the image is scored (one in the capture layout). `evaluate` estimates an image of one
instance with the single estimate (`Estimator.estimate`) and an image of several with `Estimator.estimate_all`, up
to its inst_count (`max_instances` sets the count sought everywhere); every pose found is written to the CSV.
Estimates are matched to instances as the BOP toolkit's `pose_matching.match_poses` does (`metrics.bop_matched`):
per error function and threshold, greedily by decreasing score, each estimate to the unmatched instance with the
smallest error under the threshold; a recall is matched instances / instances scored. A report row is one
instance scored: the estimate assigned to it (by score, the nearest free instance by MSSD, those within half the
diameter first), or not found. With one instance and one estimate per image this is the single-pose scoring: a
match is an error under the threshold.

Metrics over all instances scored (a not-found pose counts as an infinite error):
"AUC ADD" / "AUC ADD-S" (YCB-Video AUC, 0-10 cm, percent), "AR VSD" / "AR MSSD" / "AR MSPD" (BOP19
average recalls, percent), "AR" (their mean: BOP19's AR, as the BOP toolkit's eval_bop19_pose.py computes
it), "found" (percent of instances with a pose), "mean time ms" (per image). VSD renders the model (ray-cast,
each pixel sampled where the toolkit's OpenGL renderers sample it: `metrics.VSD_RENDER_PIXEL_OFFSET`), so it
needs a mesh; with a point cloud alone "AR VSD" and "AR" are left out. Objects are taken as asymmetric (no symmetry
transformations). All model vertices are used (ADD-S's nearest neighbours exactly, by k-d tree).
Model: the template's mesh (else its cloud), or `model_path` (any mesh trimesh reads, in the ground
truth's object frame; BOP models in millimetres are detected by a diameter above 10 units and scaled to
metres). To score as the BOP toolkit does on a gscan BOP export, pass its models_eval/obj_000001.ply.

Frames: a CAD template keeps its mesh's frame, which is the ground truth's. A scanned template has
its own frame (the centre of the object's bounding box, z up from the support plane); its poses are
mapped to the ground truth's object frame by `template_to_gt` over the ground-truth poses of the capture
it was scanned from (`gt_capture`, else its stored input folder), so the CSV and the metrics are about
the ground-truth model. Scoring a scanned template against ground truth without such a capture is refused.
A gscan BOP export (a scene folder whose dataset holds gscan_views.json) has its ground truth in the frame of
the template it was exported from; that template is mapped through its own exported views, and any other
template is refused.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gscan.errors import InputError, not_a_file
from gscan.estimate.params import EstimateParams
from gscan.evaluate.metrics import (
    VSD_RENDER_PIXEL_OFFSET,
    VSD_THRESHOLDS,
    auc,
    bop_matched,
    diameter,
    mspd,
    mspd_thresholds,
    mssd,
    mssd_thresholds,
    vsd,
    vsd_taus,
)
from gscan.evaluate.metrics import add as add_err
from gscan.evaluate.metrics import adds as adds_err
from gscan.geometry.raycast import MeshRaycaster
from gscan.geometry.transforms import inv_T, mean_pose, pose_error, transform_points
from gscan.io import open_sequence
from gscan.io.camera import RGBDFrame
from gscan.io.layouts import FORMATS, detect_format, discover, require_ground_truth
from gscan.io.output import Output, check_not_input, check_output
from gscan.template.db import TemplateDB, open_estimable

if TYPE_CHECKING:  # imported by `evaluate` once its inputs are checked: a bad input is refused without numba
    from gscan.estimate.estimator import Estimator

log = logging.getLogger(__name__)

CSV_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
MM_DIAMETER_LIMIT = 10.0  # a model whose diameter exceeds this many units is taken to be in millimetres
GSCAN_VIEWS = "gscan_views.json"  # a gscan BOP export's map of image ids to the template's view names
TARGETS = "test_targets_bop19.json"  # a BOP dataset's test targets: the images and instance counts scored


@dataclass
class EvalRow:
    """One ground-truth instance scored (a row per estimate, or one not found, in an image without ground truth):
    ids, the pose assigned to it in the ground truth's object frame (None = not found), errors (inf when not
    found; nan without ground truth), gt_id (its index in the image's scene_gt list; 0 in other layouts, None
    without ground truth)."""

    scene_id: int
    im_id: int
    found: bool
    score: float
    time_s: float
    T_cam_obj: np.ndarray | None
    add: float = float("nan")
    adds: float = float("nan")
    mssd: float = float("nan")
    mspd: float = float("nan")
    reason: str | None = None
    vsd: list[float] | None = None  # one error per BOP19 tau (metrics.VSD_TAU_FRACTIONS); None without a mesh
    gt_id: int | None = None

    def to_json(self) -> dict:
        def f(x: float) -> float | None:
            return None if not np.isfinite(x) else float(x)

        return {"scene_id": self.scene_id, "im_id": self.im_id, "gt_id": self.gt_id, "found": self.found,
                "score": float(self.score),
                "time_s": float(self.time_s), "add_m": f(self.add), "adds_m": f(self.adds), "mssd_m": f(self.mssd),
                "mspd_px": f(self.mspd), "vsd": None if self.vsd is None else [f(x) for x in self.vsd],
                "reason": self.reason,
                "T_cam_obj": None if self.T_cam_obj is None else np.asarray(self.T_cam_obj).tolist()}


@dataclass
class EvalReport:
    """n_images evaluated, n_found rows with a pose, metrics {name: value} (see module docstring), rows (one per
    ground-truth instance scored, `EvalRow`)."""

    output: Path
    n_images: int
    n_found: int
    metrics: dict[str, float]
    rows: list[EvalRow] = field(default_factory=list)
    diameter_m: float = float("nan")  # the model's diameter, the scale of the metrics' thresholds

    def to_json(self) -> dict:
        return {"output": str(self.output), "n_images": self.n_images, "n_instances": len(self.rows),
                "n_found": self.n_found,
                "metrics": {k: float(v) for k, v in self.metrics.items()}, "rows": [r.to_json() for r in self.rows]}


def _scene_dirs(scenes: Path) -> list[tuple[int, Path]]:
    """(scene_id, folder) of one scene folder or of every scene sub-folder."""
    if not scenes.is_dir():
        raise InputError(scenes, "scenes folder not found")
    try:
        detect_format(scenes)
        return [(int(scenes.name) if scenes.name.isdigit() else 0, scenes)]
    except InputError:
        pass
    subs = sorted(p for p in scenes.iterdir() if p.is_dir())
    out = []
    for i, p in enumerate(subs):
        try:
            detect_format(p)
        except InputError:
            continue
        out.append((int(p.name) if p.name.isdigit() else i, p))
    if not out:
        splits = [p.name for p in subs if p.name.startswith(("test", "val", "train")) and any(
            (q / "scene_camera.json").is_file() for q in p.iterdir() if q.is_dir())]
        if splits:  # a BOP dataset root: which split is scored is the user's choice
            raise InputError(scenes, f"a BOP dataset, not a folder of scenes: pass one split's folder "
                             f"({', '.join(str(scenes / n) for n in splits)})")
        raise InputError(scenes, "neither an RGB-D scene (BOP or capture layout) nor a folder of scenes")
    return out


def load_model(model_path: Path | None, template: Path, estimator: Estimator) -> tuple[np.ndarray, np.ndarray | None]:
    """The model the metrics use: all its vertices [N x 3] in metres (object frame) and its triangles [F x 3]
    (None for a point cloud): `model_path`, else the template's mesh (else its cloud)."""
    if model_path is None:
        with TemplateDB.open(template, require_complete=True) as db:
            mesh = db.mesh()
        if mesh is not None and len(mesh.vertices) and len(mesh.triangles):
            return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)
        return np.asarray(estimator.model_points, dtype=np.float64), None
    return load_model_file(Path(model_path))


def load_model_file(model_path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The vertices [N x 3] in metres and triangles [F x 3] (None for a point cloud) of the model file
    `model_path` (any format trimesh reads; a diameter above MM_DIAMETER_LIMIT units is taken as millimetres)."""
    import trimesh

    if not model_path.is_file():
        raise not_a_file(model_path, "model file")
    try:
        m: Any = trimesh.load(str(model_path), force="mesh", process=False)  # a Trimesh, or a PointCloud, ...
        pts = np.asarray(m.vertices, dtype=np.float64)
        tris = np.asarray(m.faces, dtype=np.int64) if hasattr(m, "faces") else np.zeros((0, 3), np.int64)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types on malformed files
        raise InputError(model_path, f"cannot load model ({e.__class__.__name__}: {e})") from None
    if len(pts) == 0:
        raise InputError(model_path, "model holds no vertices")
    if not np.all(np.isfinite(pts)):
        raise InputError(model_path, "model vertices hold NaN or infinite values")
    d = diameter(pts)
    if d > MM_DIAMETER_LIMIT:
        log.info("%s: diameter %.1f units, taken as millimetres", model_path, d)
        pts = pts * 1e-3
    return pts, (tris if len(tris) else None)


_DISAGREE = "as ground truth of"  # reason prefix of a capture whose ground truth contradicts the template
GT_AGREEMENT = (3.0, 0.02)  # deg, m: two frames' template-to-ground-truth transforms within this agree


def template_to_gt(db_path: Path, gt_T_cam_obj: dict[str, np.ndarray]) -> np.ndarray:
    """T_obj_gt [4 x 4]: the scanned template frame <- ground-truth object frame, the mean
    over the capture's registered frames of T_obj_cam[f] @ T_cam_gt[f]; never from test frames. Only the
    frames whose transform agrees (GT_AGREEMENT) with the one most others agree with are averaged.
    InputError when fewer than two frames relate them, or fewer than half of them (and two) agree: the
    ground truth is not that of the capture the template was scanned from."""
    with TemplateDB.open(db_path, require_complete=True) as db:
        frames = db.poses()["frames"]
    Ts = [np.asarray(frames[n]) @ gt_T_cam_obj[n] for n in frames if n in gt_T_cam_obj]
    if not Ts:
        raise InputError(db_path, "no registered frame has ground truth")
    if len(Ts) < 2:
        raise InputError(db_path, "only one registered frame has ground truth: too few to check that the ground "
                         "truth belongs to the capture it was scanned from")
    # the frames that agree with the medoid (a badly registered frame does not pull the others off)
    E = np.array([[pose_error(A, B) for B in Ts] for A in Ts])  # [n x n x 2] (deg, m)
    close = (E[..., 0] <= GT_AGREEMENT[0]) & (E[..., 1] <= GT_AGREEMENT[1])
    medoid = int(np.argmax(close.sum(1)))
    agree = np.flatnonzero(close[medoid])
    if len(agree) < max(2, 0.5 * len(Ts)):  # frames named alike in another capture
        raise InputError(db_path, f"its poses disagree with the ground truth (only {len(agree)} of {len(Ts)} frames "
                         f"agree within {GT_AGREEMENT[0]:g} deg / {GT_AGREEMENT[1] * 100:g} cm): "
                         "not the capture it was scanned from")
    return mean_pose([Ts[i] for i in agree])


def _csv_row(scene_id: int, im_id: int, obj_id: int, score: float, T: np.ndarray, time_s: float) -> str:
    R = " ".join(f"{x:.9g}" for x in T[:3, :3].reshape(-1))
    t = " ".join(f"{x:.6f}" for x in T[:3, 3] * 1000.0)
    return f"{scene_id},{im_id},{obj_id},{score:.6f},{R},{t},{time_s:.6f}"


def scanned_to_gt(template: Path, gt_capture: Path | None, obj_id: int) -> np.ndarray | None:
    """T_obj_gt [4 x 4] that maps the ground truth's object frame into `template`'s frame: identity for a
    CAD template; for a scanned one, `template_to_gt` over the ground truth of `gt_capture` (InputError
    when it cannot relate them, read for object `obj_id`) or, without it, of the capture the template was
    scanned from, for the BOP object the scan followed (None when that is gone or holds no ground truth)."""
    with TemplateDB.open(template, require_complete=True) as db:
        source, stored_input, stored_format = db.get_meta("source"), db.get_meta("input"), db.get_meta("format")
        stored_obj_id = db.get_meta("obj_id")
    if source != "scan":
        if gt_capture is not None:
            raise InputError(gt_capture, f"a ground-truth capture relates scanned templates; {template} is a CAD "
                             "template, already in its mesh's frame")
        return np.eye(4)
    if gt_capture is not None:
        return _capture_to_gt(template, gt_capture, "auto", obj_id)
    if not isinstance(stored_input, str) or not Path(stored_input).is_dir():
        return None
    fmt = stored_format if stored_format in FORMATS else "auto"
    if isinstance(stored_obj_id, int):  # the object the scan followed (scenes may number it otherwise)
        obj_id = stored_obj_id
    try:
        return _capture_to_gt(template, Path(stored_input), fmt, obj_id)
    except InputError as e:
        # a capture whose ground truth contradicts the scan, or one of its files that is malformed, is named;
        # a capture that is gone, unreadable as a whole or without ground truth leaves --gt-capture to the user
        if e.reason.startswith(_DISAGREE) or (e.path is not None and e.path != Path(stored_input)):
            raise
        return None


def _capture_to_gt(template: Path, capture: Path, fmt: str, obj_id: int) -> np.ndarray:
    """`template_to_gt` over `capture`'s ground truth; InputError naming `capture` when it cannot."""
    if not capture.is_dir():
        raise InputError(capture, "ground-truth capture folder not found")
    layout = discover(capture, fmt, obj_id=obj_id)
    require_ground_truth(layout.gt_problems)
    gt = layout.gt_T_cam_obj
    if not gt:
        raise InputError(capture, f"holds no ground-truth object poses (annotated_poses/, or scene_gt.json "
                         f"with object {obj_id})")
    try:
        return template_to_gt(template, gt)
    except InputError as e:
        if e.reason.startswith("no registered frame"):
            raise InputError(capture, f"none of its ground-truth frames is a registered view of {template}") from None
        raise InputError(capture, f"{_DISAGREE} {template.name}: {e.reason}") from None


def _exported_views(scene: Path) -> dict[str, str] | None:
    """{image name: template view name} when `scene` is a scene of a gscan BOP export (its dataset root, two
    folders up, holds gscan_views.json); else None."""
    path = scene.parent.parent / GSCAN_VIEWS
    if not (scene / "scene_gt.json").is_file() or not path.is_file():
        return None
    try:
        views = json.loads(path.read_text(encoding="utf-8"))
        return {f"{int(k):06d}": str(v) for k, v in views.items()}
    except (OSError, ValueError, TypeError, AttributeError) as e:
        raise InputError(path, f"unreadable ({e.__class__.__name__}: {e})") from None


def _export_to_gt(template: Path, seqs: list, exported: dict[int, dict[str, str]]) -> np.ndarray:
    """T_obj_gt of `template` for scenes of a gscan BOP export, whose ground truth is in the frame of the
    template exported: `template_to_gt` over the exported views' ground truth, named as the template's views
    (identity, up to float rounding, for the template itself). InputError when the template does not hold
    those views at those poses: the export is another template's."""
    gt = {}
    for scene_id, seq in seqs:
        names = exported.get(scene_id)
        if names and seq.gt_T_cam_obj:
            gt.update({names[n]: T for n, T in seq.gt_T_cam_obj.items() if n in names})
    try:
        return template_to_gt(template, gt)
    except InputError as e:
        scene = next(seq.root for scene_id, seq in seqs if scene_id in exported)
        raise InputError(scene, f"is a gscan BOP export ({GSCAN_VIEWS}) whose ground truth is in the frame of the "
                         f"template it was exported from, and {template.name} is not that template ({e.reason})",
                         fix="gt_capture") from None


def read_targets(folders: list[tuple[int, Path]], obj_id: int) -> dict[tuple[int, int], int] | None:
    """{(scene_id, im_id): inst_count} of object `obj_id` in the BOP test targets (`TARGETS` in the dataset root,
    two folders above a scene), or None when no scene has such a file. InputError naming the file when it is
    malformed."""
    targets: dict[tuple[int, int], int] | None = None
    for path in sorted({folder.parent.parent / TARGETS for _, folder in folders}):
        if not path.is_file():
            continue
        doc = _read_json(path)
        try:
            entries = [(int(t["scene_id"]), int(t["im_id"]), int(t["obj_id"]), int(t["inst_count"])) for t in doc]
        except (TypeError, KeyError, ValueError, OverflowError) as e:
            raise InputError(path, f"malformed target ({e.__class__.__name__}: {e}): each needs scene_id, im_id, "
                             "obj_id and inst_count") from None
        if any(n < 1 for *_, n in entries):
            raise InputError(path, "an inst_count below 1")
        targets = targets or {}
        targets.update({(s, i): n for s, i, o, n in entries if o == obj_id})
    return targets


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise InputError(path, f"unreadable ({e.__class__.__name__}: {e})"[:300]) from None


def _visib_fracts(scene: Path) -> dict[int, list[float]]:
    """{im_id: visib_fract of each scene_gt entry} from the scene's scene_gt_info.json ({} without one)."""
    path = scene / "scene_gt_info.json"
    if not path.is_file():
        return {}
    doc = _read_json(path)
    try:
        return {int(k): [float(e["visib_fract"]) for e in v] for k, v in doc.items()}
    except (TypeError, KeyError, ValueError, AttributeError, OverflowError) as e:
        raise InputError(path, f"malformed entry ({e.__class__.__name__}: {e}): each needs visib_fract") from None


def scored_instances(instances: list[tuple[int, np.ndarray]], inst_count: int,
                     visib: list[float] | None) -> list[tuple[int, np.ndarray]]:
    """The ground-truth instances (gt_id, T_cam_obj [4 x 4]) an image's target scores, in gt_id order: the
    `inst_count` most visible (BOP19's rule, by the visib_fract of each scene_gt entry, `visib`; without it the
    first ones), all of them when there are no more."""
    if len(instances) <= inst_count:
        return instances
    def vis(i: int) -> float:
        gt_id = instances[i][0]
        return visib[gt_id] if visib is not None and gt_id < len(visib) else 1.0

    keep = sorted(sorted(range(len(instances)), key=vis, reverse=True)[:inst_count])
    return [instances[i] for i in keep]


@dataclass
class _Hits:
    """One image's scored instances, matched as the BOP toolkit matches them: [G x T] bool per MSSD / MSPD
    threshold, [G x K x T] per VSD tolerance and threshold (None without a mesh)."""

    mssd: np.ndarray
    mspd: np.ndarray
    vsd: np.ndarray | None


class _Scorer:
    """The errors of an image's estimates against its ground-truth instances: one row per scored instance, and the
    BOP matches (`_Hits`) that the average recalls count."""

    def __init__(self, pts: np.ndarray, caster: MeshRaycaster | None, diameter: float):
        self.pts, self.caster, self.diam = pts, caster, diameter
        self.taus = vsd_taus(diameter)

    def image(self, scene_id: int, im_id: int, frame: RGBDFrame, ests: list[tuple[float, np.ndarray]],
              truths: list[tuple[int, np.ndarray]] | None, inst_count: int, time_s: float,
              miss: tuple[float, str | None]) -> tuple[list[EvalRow], _Hits | None]:
        """Rows and matches of one image. ests: (score, T_cam_obj [4 x 4]) of each estimate; truths: the scored
        ground-truth instances (gt_id, T_cam_obj), None without ground truth (a row per estimate, errors NaN);
        inst_count: the estimates scored, the best-scoring ones (BOP: as many as the target's instances);
        miss: the score and reason of a row whose instance no estimate was assigned to."""
        order = sorted(range(len(ests)), key=lambda i: -ests[i][0])  # stable: ties keep the results' order
        ests = [ests[i] for i in order][:max(1, inst_count)]
        if not truths:
            if not ests:
                return [EvalRow(scene_id, im_id, False, miss[0], time_s, None, reason=miss[1])], None
            return [EvalRow(scene_id, im_id, True, s, time_s, T) for s, T in ests], None
        E, G = len(ests), len(truths)
        mssd_e = np.array([[mssd(self.pts, T, T_gt) for _, T_gt in truths] for _, T in ests]).reshape(E, G)
        mspd_e = np.array([[self._mspd(T, T_gt, frame) for _, T_gt in truths] for _, T in ests]).reshape(E, G)
        vsd_e = None
        if self.caster is not None:
            d_est = [self._render(T, frame) for _, T in ests]
            d_gt = [self._render(T_gt, frame) for _, T_gt in truths]
            vsd_e = np.array([[vsd(frame.depth, de, dg, frame.intrinsics, self.taus) for dg in d_gt]
                              for de in d_est]).reshape(E, G, len(self.taus))
        # the rows: each estimate, best score first, gets the free instance it is closest to (MSSD) among those
        # within the loosest MSSD threshold (BOP's matching there), then those left the free ones nearest
        loosest = float(mssd_thresholds(self.diam)[-1])
        owner: dict[int, int] = {}  # instance -> estimate
        for within in (True, False):
            for e in range(E):
                free = [g for g in range(G) if g not in owner and (mssd_e[e, g] < loosest or not within)]
                if free and e not in owner.values():
                    owner[min(free, key=lambda g: mssd_e[e, g])] = e
        rows = []
        for g, (gt_id, T_gt) in enumerate(truths):
            if g not in owner:
                row = EvalRow(scene_id, im_id, False, miss[0], time_s, None, reason=miss[1] if not ests else
                              "no estimate left for this instance (the others' were assigned to other instances)")
                row.add = row.adds = row.mssd = row.mspd = float("inf")
                row.vsd = None if self.caster is None else [float("inf")] * len(self.taus)
            else:
                e = owner[g]
                score, T = ests[e]
                row = EvalRow(scene_id, im_id, True, score, time_s, T, add=add_err(self.pts, T, T_gt),
                              adds=adds_err(self.pts, T, T_gt), mssd=float(mssd_e[e, g]), mspd=float(mspd_e[e, g]),
                              vsd=None if vsd_e is None else vsd_e[e, g].tolist())
            row.gt_id = gt_id
            rows.append(row)
        th_mssd = mssd_thresholds(self.diam)
        th_mspd = mspd_thresholds(frame.intrinsics.width)
        hits_vsd = None if vsd_e is None else np.stack(
            [bop_matched(vsd_e[:, :, k], VSD_THRESHOLDS) for k in range(len(self.taus))], axis=1)
        return rows, _Hits(bop_matched(mssd_e, th_mssd), bop_matched(mspd_e, th_mspd), hits_vsd)

    def _mspd(self, T: np.ndarray, T_gt: np.ndarray, frame: RGBDFrame) -> float:
        try:
            return mspd(self.pts, T, T_gt, frame.intrinsics)
        except ValueError:  # estimated model partly behind the camera
            return float("inf")

    def _render(self, T_cam_obj: np.ndarray, frame: RGBDFrame) -> np.ndarray:
        assert self.caster is not None
        return self.caster.depth(frame.intrinsics, inv_T(T_cam_obj), VSD_RENDER_PIXEL_OFFSET)


def _truths(seq: Any, name: str) -> list[tuple[int, np.ndarray]] | None:
    """Every ground-truth instance (gt_id, T_cam_obj [4 x 4]) of the sequence's object in image `name` (a BOP
    scene's every one, another layout's one), None when the image has none."""
    if seq.gt_instances is not None:
        return seq.gt_instances.get(name) or None
    T = (seq.gt_T_cam_obj or {}).get(name)
    return None if T is None else [(0, T)]


def evaluate(template: str | Path, scenes: str | Path, output_csv: str | Path, obj_id: int = 1,
             model_path: str | Path | None = None, refine: bool = True, force: bool = False,
             gt_capture: str | Path | None = None, max_instances: int | None = None,
             params: EstimateParams | None = None) -> EvalReport:
    """Estimate the pose of every instance of the template's object in every image under `scenes`, write
    BOP19 CSV `output_csv` and return the metrics (poses in the ground truth's object frame, see the module
    docstring). max_instances: the instances sought in every image (None: each image's target count, a
    single estimate where that is one); params: the estimator's settings (None: the defaults). InputError for an
    existing output without `force`, a missing or partial template, unreadable scenes, targets or model, a
    scanned template scored against ground truth that no ground-truth capture (`gt_capture`, else the
    template's own input) relates to its frame, or a gscan BOP export of another template scored without
    `gt_capture`."""
    output_csv = Path(output_csv)
    check_not_input(output_csv, [template, scenes, model_path, gt_capture])
    check_output(output_csv, force=force, kind=".csv file path")
    template = Path(template)
    # the template and the scenes are opened and checked before the estimator's stages load (numba, scipy)
    tpl = open_estimable(template)
    folders = _scene_dirs(Path(scenes))
    seqs = [(scene_id, open_sequence(folder, format="auto", obj_id=obj_id)) for scene_id, folder in folders]
    for _, seq in seqs:  # the scores need every ground-truth pose
        require_ground_truth(seq.gt_problems)
    targets = read_targets(folders, obj_id)
    exported = {scene_id: v for scene_id, folder in folders if (v := _exported_views(folder)) is not None}
    if exported and gt_capture is None:
        T_obj_gt: np.ndarray | None = _export_to_gt(template, seqs, exported)
    else:
        T_obj_gt = scanned_to_gt(template, None if gt_capture is None else Path(gt_capture), obj_id)
    if T_obj_gt is None:
        if any(seq.gt_T_cam_obj for _, seq in seqs):
            raise InputError(template, "is a scanned template, in its own frame, and the capture it was scanned "
                             "from is gone or holds no ground truth", fix="gt_capture")
        log.warning("%s: no ground-truth capture relates the scanned template's frame to the ground truth's; "
                    "the CSV holds poses of the template's own frame (a ground-truth capture relates them)", template)
        T_obj_gt = np.eye(4)  # no ground truth anywhere: poses of the template's own frame
    from gscan.estimate.estimator import Estimator

    estimator = Estimator(tpl) if params is None else Estimator(tpl, params)
    pts, tris = load_model(None if model_path is None else Path(model_path), template, estimator)
    if model_path is None:  # the template's mesh, in the ground truth's object frame
        pts = transform_points(inv_T(T_obj_gt), pts)
    diam = diameter(pts)
    caster = MeshRaycaster(pts, tris) if tris is not None else None
    if caster is None:
        log.warning("the model is a point cloud: no VSD, so no BOP AR (its MSSD and MSPD recalls are reported)")
    scorer = _Scorer(pts, caster, diam)
    rows: list[EvalRow] = []
    hits: list[_Hits] = []
    times: list[float] = []
    lines = [CSV_HEADER]
    bop_gt = False  # some scene has a scene_gt.json
    for scene_id, seq in seqs:
        bop_gt |= seq.format == "bop" and seq.gt_T_cam_obj is not None
        visib = _visib_fracts(seq.root) if targets is not None and seq.format == "bop" else {}
        for name in seq.names:
            im_id = int(name) if name.isdigit() else seq.names.index(name)
            if targets is not None and (scene_id, im_id) not in targets:
                continue  # not a target of this object
            try:
                frame = seq[name]
            except InputError as e:  # an unreadable image is left out (and reported), not fatal
                log.warning("scene %d: image %s left out: %s", scene_id, name, e)
                continue
            truths = _truths(seq, name)
            inst_count = targets[(scene_id, im_id)] if targets is not None else len(truths or [])
            t0 = time.perf_counter()
            if max_instances is None and inst_count <= 1 and len(truths or []) <= 1:
                res = estimator.estimate(frame, mask=None, refine=refine)  # one instance: the single estimate
                found = [(res.score, res.T_cam_obj)] if res.T_cam_obj is not None else []
                miss = (res.score, res.reason)
            else:
                out = estimator.estimate_all(frame, None, refine,
                                             max_instances=max_instances if max_instances is not None else inst_count)
                found = [(r.score, r.T_cam_obj) for r in out.results if r.T_cam_obj is not None]
                miss = (0.0, out.reason)
            dt = time.perf_counter() - t0
            ests = [(s, T @ T_obj_gt) for s, T in found]  # the ground-truth model's poses
            lines += [_csv_row(scene_id, im_id, obj_id, s, T, dt) for s, T in ests]
            if truths is not None:
                truths = scored_instances(truths, inst_count, visib.get(im_id))
            image_rows, image_hits = scorer.image(scene_id, im_id, frame, ests, truths, inst_count, dt, miss)
            rows += image_rows
            times.append(dt)
            if image_hits is not None:
                hits.append(image_hits)
            log.info("scene %d image %d: %d found (%s)", scene_id, im_id, len(ests), miss[1] or "")
    if not rows:
        raise InputError(Path(scenes), "no image to evaluate")
    if bop_gt and all(np.isnan(r.add) for r in rows):  # the metrics would silently be left out
        raise InputError(Path(scenes), f"scene_gt.json holds no pose of object {obj_id}", fix="obj_id")
    with_gt = [r for r in rows if r.found and np.isfinite(r.add)]
    if with_gt and all(r.add > diam for r in with_gt):
        log.warning("every pose found is more than the object's diameter (%.0f mm) from the ground truth: are the "
                    "template and the ground truth in one frame (the ground-truth capture, the model)?", 1000 * diam)
    with Output(output_csv, force=force, kind=".csv file path") as out_file:
        out_file.tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return EvalReport(output_csv, len(times), sum(r.found for r in rows), _metrics(rows, hits, times, diam), rows,
                      diam)


ROTATION_TOL = 1e-3  # max |R R^T - I| of a results CSV's rotation (9 significant digits, float32 rounding pass)


def read_results(path: Path, obj_id: int) -> dict[tuple[int, int], list[tuple[float, np.ndarray, float]]]:
    """{(scene_id, im_id): [(score, T_cam_obj [4 x 4] in metres, time s), ...]} of object `obj_id` in the BOP19
    results CSV `path` (the module docstring's format; the header line is optional), every estimate of each image
    in the file's order. InputError naming the file and the line for a malformed row (not 7 fields, R not a
    rotation, a value that is not a finite number)."""
    if not path.is_file():
        raise not_a_file(path, "results CSV")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"unreadable ({e.__class__.__name__}: {e})") from None
    out: dict[tuple[int, int], list[tuple[float, np.ndarray, float]]] = {}
    for n, line in enumerate(lines, 1):
        if not line.strip() or (n == 1 and line.startswith("scene_id")):
            continue
        fields = line.split(",")
        if len(fields) != 7:
            raise InputError(path, f"line {n}: {len(fields)} comma-separated fields, not 7 ({CSV_HEADER})")
        try:
            scene_id, im_id, oid = (int(f) for f in fields[:3])
            score, time_s = float(fields[3]), float(fields[6])
            R = np.array(fields[4].split(), dtype=np.float64)
            t = np.array(fields[5].split(), dtype=np.float64)
        except ValueError as e:
            raise InputError(path, f"line {n}: {e}") from None
        if R.size != 9 or t.size != 3:
            raise InputError(path, f"line {n}: R holds {R.size} numbers (9) and t {t.size} (3)")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.isfinite(score) and np.isfinite(time_s)):
            raise InputError(path, f"line {n}: a value is NaN or infinite")
        R = R.reshape(3, 3)
        if np.abs(R @ R.T - np.eye(3)).max() > ROTATION_TOL or np.linalg.det(R) < 0:
            raise InputError(path, f"line {n}: R is not a rotation matrix")
        if oid != obj_id:
            continue
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t / 1000.0
        out.setdefault((scene_id, im_id), []).append((score, T, time_s))
    return out


def score_results(results_csv: str | Path, scenes: str | Path, model_path: str | Path,
                  obj_id: int = 1) -> EvalReport:
    """Score the BOP19 results CSV `results_csv` (any method's; `evaluate` writes one) against the ground truth of
    object `obj_id` in `scenes`, with the errors and metrics `evaluate` reports, without estimating: per image
    the best-scoring estimates, as many as the target's instances (BOP19's rule; the test targets', else every
    ground-truth instance of the object in the image), matched to the instances as the BOP toolkit matches them;
    an instance without an estimate counts as not found. The image's time is its first estimate's. `model_path`:
    the object model in the ground truth's frame (a BOP model in millimetres is scaled; a gscan BOP export's is
    models_eval/obj_000001.ply). Only images with ground truth (and targets, where the dataset lists them) are
    scored. InputError for a missing or malformed CSV or targets, unreadable scenes or model, or scenes without
    ground truth of `obj_id`."""
    results_csv = Path(results_csv)
    estimates = read_results(results_csv, obj_id)
    folders = _scene_dirs(Path(scenes))
    seqs = [(scene_id, open_sequence(folder, format="auto", obj_id=obj_id)) for scene_id, folder in folders]
    for _, seq in seqs:
        require_ground_truth(seq.gt_problems)
    targets = read_targets(folders, obj_id)
    pts, tris = load_model_file(Path(model_path))
    diam = diameter(pts)
    scorer = _Scorer(pts, MeshRaycaster(pts, tris) if tris is not None else None, diam)
    rows: list[EvalRow] = []
    hits: list[_Hits] = []
    times: list[float] = []
    for scene_id, seq in seqs:
        visib = _visib_fracts(seq.root) if targets is not None and seq.format == "bop" else {}
        for name in seq.names:
            truths = _truths(seq, name)
            im_id = int(name) if name.isdigit() else seq.names.index(name)
            if truths is None or (targets is not None and (scene_id, im_id) not in targets):
                continue
            try:
                frame = seq[name]
            except InputError as e:  # an unreadable image is left out (and reported), as evaluate does
                log.warning("scene %d: image %s left out: %s", scene_id, name, e)
                continue
            inst_count = targets[(scene_id, im_id)] if targets is not None else len(truths)
            found = estimates.get((scene_id, im_id), [])
            dt = found[0][2] if found else 0.0
            image_rows, image_hits = scorer.image(
                scene_id, im_id, frame, [(s, T) for s, T, _ in found],
                scored_instances(truths, inst_count, visib.get(im_id)), inst_count, dt,
                (0.0, "no estimate in the results"))
            rows += image_rows
            times.append(dt)
            if image_hits is not None:
                hits.append(image_hits)
    if not rows:
        raise InputError(Path(scenes), f"holds no image with a ground-truth pose of object {obj_id}", fix="obj_id")
    return EvalReport(results_csv, len(times), sum(r.found for r in rows), _metrics(rows, hits, times, diam), rows,
                      diam)


def _metrics(rows: list[EvalRow], hits: list[_Hits], times: list[float], diameter: float) -> dict[str, float]:
    """The report's metrics (module docstring) of its rows, the images' BOP matches `hits` and their times (s).
    An image of one instance and one estimate gives its errors' recalls (a match is an error under the threshold)."""
    g = [r for r in rows if not np.isnan(r.add)]
    m: dict[str, float] = {"found": 100.0 * sum(r.found for r in rows) / len(rows),
                           "mean time ms": 1e3 * float(np.mean(times))}
    if g and hits:
        m["AUC ADD"] = auc([r.add for r in g])
        m["AUC ADD-S"] = auc([r.adds for r in g])
        if all(h.vsd is not None for h in hits):
            v = np.concatenate([h.vsd for h in hits if h.vsd is not None])  # [N x K x T]
            m["AR VSD"] = 100.0 * float(np.mean([v[:, k, :].mean(axis=0) for k in range(v.shape[1])]))
        m["AR MSSD"] = 100.0 * float(np.concatenate([h.mssd for h in hits]).mean(axis=0).mean())
        m["AR MSPD"] = 100.0 * float(np.concatenate([h.mspd for h in hits]).mean(axis=0).mean())
        if "AR VSD" in m:  # BOP19's AR: the mean of the three average recalls
            m["AR"] = (m["AR VSD"] + m["AR MSSD"] + m["AR MSPD"]) / 3.0
    return m
