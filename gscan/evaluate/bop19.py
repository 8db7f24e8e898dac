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

Metrics over all images with ground truth (a not-found pose counts as an infinite error):
"AUC ADD" / "AUC ADD-S" (YCB-Video AUC, 0-10 cm, percent), "AR VSD" / "AR MSSD" / "AR MSPD" (BOP19
average recalls, percent), "AR" (their mean: BOP19's AR, as the BOP toolkit's eval_bop19_pose.py computes
it), "found" (percent of images with a pose), "mean time ms". VSD renders the model (ray-cast, each pixel
sampled where the toolkit's OpenGL renderers sample it: `metrics.VSD_RENDER_PIXEL_OFFSET`), so it needs a mesh;
with a point cloud alone "AR VSD" and "AR" are left out. Objects are taken as asymmetric (no symmetry
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
from typing import Any

import numpy as np

from gscan.errors import InputError, not_a_file
from gscan.estimate.estimator import Estimator
from gscan.evaluate.metrics import (
    VSD_RENDER_PIXEL_OFFSET,
    ar_mspd,
    ar_mssd,
    ar_vsd,
    auc,
    diameter,
    mspd,
    mssd,
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
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)

CSV_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
MM_DIAMETER_LIMIT = 10.0  # a model whose diameter exceeds this many units is taken to be in millimetres
GSCAN_VIEWS = "gscan_views.json"  # a gscan BOP export's map of image ids to the template's view names


@dataclass
class EvalRow:
    """One image: ids, pose of the ground truth's object frame (None = not found), errors (inf when not
    found; nan without ground truth)."""

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

    def to_json(self) -> dict:
        def f(x: float) -> float | None:
            return None if not np.isfinite(x) else float(x)

        return {"scene_id": self.scene_id, "im_id": self.im_id, "found": self.found, "score": float(self.score),
                "time_s": float(self.time_s), "add_m": f(self.add), "adds_m": f(self.adds), "mssd_m": f(self.mssd),
                "mspd_px": f(self.mspd), "vsd": None if self.vsd is None else [f(x) for x in self.vsd],
                "reason": self.reason,
                "T_cam_obj": None if self.T_cam_obj is None else np.asarray(self.T_cam_obj).tolist()}


@dataclass
class EvalReport:
    """n_images evaluated, n_found with a pose, metrics {name: value} (see module docstring), rows."""

    output: Path
    n_images: int
    n_found: int
    metrics: dict[str, float]
    rows: list[EvalRow] = field(default_factory=list)
    diameter_m: float = float("nan")  # the model's diameter, the scale of the metrics' thresholds

    def to_json(self) -> dict:
        return {"output": str(self.output), "n_images": self.n_images, "n_found": self.n_found,
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


def evaluate(template: str | Path, scenes: str | Path, output_csv: str | Path, obj_id: int = 1,
             model_path: str | Path | None = None, refine: bool = True, force: bool = False,
             gt_capture: str | Path | None = None) -> EvalReport:
    """Estimate the pose of the template's object in every image under `scenes`, write BOP19 CSV
    `output_csv` and return the metrics (poses in the ground truth's object frame, see the module
    docstring). InputError for an existing output without `force`, a missing or partial template,
    unreadable scenes or model, a scanned template scored against ground truth that no ground-truth
    capture (`gt_capture`, else the template's own input) relates to its frame, or a gscan BOP export of
    another template scored without `gt_capture`."""
    output_csv = Path(output_csv)
    check_not_input(output_csv, [template, scenes, model_path, gt_capture])
    check_output(output_csv, force=force, kind=".csv file path")
    template = Path(template)
    estimator = Estimator.from_path(template)
    folders = _scene_dirs(Path(scenes))
    seqs = [(scene_id, open_sequence(folder, format="auto", obj_id=obj_id)) for scene_id, folder in folders]
    for _, seq in seqs:  # the scores need every ground-truth pose
        require_ground_truth(seq.gt_problems)
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
    pts, tris = load_model(None if model_path is None else Path(model_path), template, estimator)
    if model_path is None:  # the template's mesh, in the ground truth's object frame
        pts = transform_points(inv_T(T_obj_gt), pts)
    diam = diameter(pts)
    taus = vsd_taus(diam)
    caster = MeshRaycaster(pts, tris) if tris is not None else None
    if caster is None:
        log.warning("the model is a point cloud: no VSD, so no BOP AR (its MSSD and MSPD recalls are reported)")
    rows: list[EvalRow] = []
    lines = [CSV_HEADER]
    width = 640
    bop_gt = False  # some scene has a scene_gt.json
    for scene_id, seq in seqs:
        gt = seq.gt_T_cam_obj or {}
        bop_gt |= seq.format == "bop" and seq.gt_T_cam_obj is not None
        for name in seq.names:
            try:
                frame = seq[name]
            except InputError as e:  # an unreadable image is left out (and reported), not fatal
                log.warning("scene %d: image %s left out: %s", scene_id, name, e)
                continue
            width = frame.intrinsics.width
            im_id = int(name) if name.isdigit() else seq.names.index(name)
            t0 = time.perf_counter()
            res = estimator.estimate(frame, mask=None, refine=refine)
            dt = time.perf_counter() - t0
            T_est = None if res.T_cam_obj is None else res.T_cam_obj @ T_obj_gt  # the ground-truth model's pose
            row = EvalRow(scene_id, im_id, res.found, res.score, dt, T_est, reason=res.reason)
            T_gt = gt.get(name)
            if T_gt is not None:
                _errors(row, T_gt, frame, pts, caster, taus)
            if T_est is not None:  # found
                lines.append(_csv_row(scene_id, im_id, obj_id, res.score, T_est, dt))
            rows.append(row)
            log.info("scene %d image %d: %s", scene_id, im_id, "found" if res.found else f"not found ({res.reason})")
    if not rows:
        raise InputError(Path(scenes), "no image to evaluate")
    if bop_gt and all(np.isnan(r.add) for r in rows):  # the metrics would silently be left out
        raise InputError(Path(scenes), f"scene_gt.json holds no pose of object {obj_id}", fix="obj_id")
    found = [r for r in rows if r.found and np.isfinite(r.add)]
    if found and all(r.add > diam for r in found):
        log.warning("every pose found is more than the object's diameter (%.0f mm) from the ground truth: are the "
                    "template and the ground truth in one frame (the ground-truth capture, the model)?", 1000 * diam)
    with Output(output_csv, force=force, kind=".csv file path") as out:
        out.tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return EvalReport(output_csv, len(rows), sum(r.found for r in rows), _metrics(rows, diam, width), rows, diam)


def _errors(row: EvalRow, T_gt: np.ndarray, frame: RGBDFrame, pts: np.ndarray, caster: MeshRaycaster | None,
            taus: np.ndarray) -> None:
    """Set `row`'s errors of its pose against the ground truth T_cam_obj `T_gt` [4 x 4] in `frame`, on the model's
    vertices `pts` [N x 3] (VSD with its mesh `caster`, at the tolerances `taus`); infinite when not found."""
    T_est = row.T_cam_obj
    if T_est is None:
        row.add = row.adds = row.mssd = row.mspd = float("inf")
        row.vsd = None if caster is None else [float("inf")] * len(taus)
        return
    row.add = add_err(pts, T_est, T_gt)
    row.adds = adds_err(pts, T_est, T_gt)
    row.mssd = mssd(pts, T_est, T_gt)
    try:
        row.mspd = mspd(pts, T_est, T_gt, frame.intrinsics)
    except ValueError:  # estimated model partly behind the camera
        row.mspd = float("inf")
    if caster is not None:
        d_est = caster.depth(frame.intrinsics, inv_T(T_est), VSD_RENDER_PIXEL_OFFSET)
        d_gt = caster.depth(frame.intrinsics, inv_T(T_gt), VSD_RENDER_PIXEL_OFFSET)
        row.vsd = vsd(frame.depth, d_est, d_gt, frame.intrinsics, taus).tolist()


ROTATION_TOL = 1e-3  # max |R R^T - I| of a results CSV's rotation (9 significant digits, float32 rounding pass)


def read_results(path: Path, obj_id: int) -> dict[tuple[int, int], tuple[float, np.ndarray, float]]:
    """{(scene_id, im_id): (score, T_cam_obj [4 x 4] in metres, time s)} of object `obj_id` in the BOP19 results
    CSV `path` (the module docstring's format; the header line is optional), the highest-scoring estimate of each
    image. InputError naming the file and the line for a malformed row (not 7 fields, R not a rotation, a value
    that is not a finite number)."""
    if not path.is_file():
        raise not_a_file(path, "results CSV")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"unreadable ({e.__class__.__name__}: {e})") from None
    best: dict[tuple[int, int], tuple[float, np.ndarray, float]] = {}
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
        if oid != obj_id or ((scene_id, im_id) in best and best[(scene_id, im_id)][0] >= score):
            continue
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t / 1000.0
        best[(scene_id, im_id)] = (score, T, time_s)
    return best


def score_results(results_csv: str | Path, scenes: str | Path, model_path: str | Path,
                  obj_id: int = 1) -> EvalReport:
    """Score the BOP19 results CSV `results_csv` (any method's; `evaluate` writes one) against the ground truth of
    object `obj_id` in `scenes`, with the errors and metrics `evaluate` reports, without estimating: per image the
    estimate with the highest score (BOP19's rule for one instance of the object per image; an image without
    one counts as not found), its time the CSV's. `model_path`: the object model in the ground truth's frame (a
    BOP model in millimetres is scaled; a gscan BOP export's is models_eval/obj_000001.ply). Only images with
    ground truth are scored. InputError for a missing or malformed CSV, unreadable scenes or model, or scenes
    without ground truth of `obj_id`."""
    results_csv = Path(results_csv)
    estimates = read_results(results_csv, obj_id)
    folders = _scene_dirs(Path(scenes))
    seqs = [(scene_id, open_sequence(folder, format="auto", obj_id=obj_id)) for scene_id, folder in folders]
    for _, seq in seqs:
        require_ground_truth(seq.gt_problems)
    pts, tris = load_model_file(Path(model_path))
    diam = diameter(pts)
    taus = vsd_taus(diam)
    caster = MeshRaycaster(pts, tris) if tris is not None else None
    rows: list[EvalRow] = []
    width = 640
    for scene_id, seq in seqs:
        gt = seq.gt_T_cam_obj or {}
        for name in seq.names:
            if name not in gt:
                continue
            try:
                frame = seq[name]
            except InputError as e:  # an unreadable image is left out (and reported), as evaluate does
                log.warning("scene %d: image %s left out: %s", scene_id, name, e)
                continue
            width = frame.intrinsics.width
            im_id = int(name) if name.isdigit() else seq.names.index(name)
            est = estimates.get((scene_id, im_id))
            row = (EvalRow(scene_id, im_id, True, est[0], est[2], est[1]) if est is not None else
                   EvalRow(scene_id, im_id, False, 0.0, 0.0, None, reason="no estimate in the results"))
            _errors(row, gt[name], frame, pts, caster, taus)
            rows.append(row)
    if not rows:
        raise InputError(Path(scenes), f"holds no image with a ground-truth pose of object {obj_id}", fix="obj_id")
    return EvalReport(results_csv, len(rows), sum(r.found for r in rows), _metrics(rows, diam, width), rows, diam)


def _metrics(rows: list[EvalRow], diameter: float, width: int) -> dict[str, float]:
    g = [r for r in rows if not np.isnan(r.add)]
    m: dict[str, float] = {"found": 100.0 * sum(r.found for r in rows) / len(rows),
                           "mean time ms": 1e3 * float(np.mean([r.time_s for r in rows]))}
    if g:
        m["AUC ADD"] = auc([r.add for r in g])
        m["AUC ADD-S"] = auc([r.adds for r in g])
        vsds = [r.vsd for r in g if r.vsd is not None]
        if len(vsds) == len(g):
            m["AR VSD"] = 100.0 * ar_vsd(vsds)
        m["AR MSSD"] = 100.0 * ar_mssd([r.mssd for r in g], diameter)
        m["AR MSPD"] = 100.0 * ar_mspd([r.mspd for r in g], width)
        if "AR VSD" in m:  # BOP19's AR: the mean of the three average recalls
            m["AR"] = (m["AR VSD"] + m["AR MSSD"] + m["AR MSPD"]) / 3.0
    return m
