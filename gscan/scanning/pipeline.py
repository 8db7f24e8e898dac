"""The scan pipeline: an RGB-D folder to registered views, pose graph, fused mesh and template database.

Stages (each timed, each reported through a `Progress`):
  mode      static-object vs moving-object (`gscan.scanning.capture_mode`), from a few frames spread over the input
  load      read every frame once, in order (unusable ones are reported by name and left out); frame selection
            (`gscan.scanning.select`) keeps the frames the view moved enough to, the sharper where frames blur, and
            reports the others as skipped (not failures); a kept frame's images go to the scan's frame store
            (`gscan.scanning.store`, an anonymous file beside the output), with a moving object's mask
  features  keypoints + descriptors lifted to 3D; whole frame for a static object, object only for a
            moving one; stored at once in the database with the view's images (camera frame, pose unknown)
  register  pairwise edges: each frame against the previous one, falling back to the next earlier
            ones (`MAX_SKIP` frames in all), then loop closures chosen by view overlap
            and bag-of-words votes; each edge = GMatch -> Kabsch -> guided refinement (-> ICP when
            configured), accepted by the rules of `gscan.registration.pairwise`; stored as it is computed
  posegraph robust global optimisation (`gscan.registration.posegraph`) with pruning of inconsistent edges;
            a frame it cuts loose (its edges disagree and no cycle decides, or a weak edge alone held it) is
            registered to `SECOND_OPINIONS` more frames and the graph optimised again with those edges;
            frames not connected to the reference frame stay unregistered and are never fused
  segment   object masks (given, background subtraction, or support plane + working volume)
  fuse      TSDF fusion of the object's depth; template frame (fuse.template_frame)
  database  poses, masks, keyframes and keypoints in the object frame, mesh, cloud; status complete

Memory does not grow with the capture: after the load a stage holds a few frames at a time, reading their
images back from the frame store and their keypoints from the database (`_FrameData`); what stays in memory
per kept frame is its name, counts and pose, and per edge its matches and pose-graph evidence.

Database writes: one transaction per stage (per COMMIT_ROWS views or edges in a long one) on a write-ahead log,
each view's images written once (`gscan.template.db`).

Resume: the database is `partial` until the last transaction. `--resume` reuses the stored views'
keypoints and every stored edge (the expensive parts) and recomputes the rest, which is
deterministic, so an interrupted scan resumes to the same result as an uninterrupted one.
"""
from __future__ import annotations

import collections.abc
import contextlib
import json
import logging
import shutil
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gscan.errors import InputError, OutputExists
from gscan.features import (
    OBJECT_FEATURES,
    Detection,
    FeatureParams,
    Features,
    extract_features,
    extract_features_in_mask,
)
from gscan.geometry.plane import Plane
from gscan.geometry.transforms import transform_points
from gscan.io.camera import RGBDFrame
from gscan.io.output import (
    Output,
    check_output,
    file_identity,
    journal_fits,
    missing_folders,
    occupied,
    remove_empty_folders,
    remove_sqlite_sidecars,
)
from gscan.io.sequence import Sequence
from gscan.progress import Progress, StageTimer
from gscan.registration.dense import DenseGeometry
from gscan.registration.edges import EdgeSink, PairEdge, RegData, Registrar, bounded_map, icp_cloud
from gscan.registration.noise import DepthNoise
from gscan.registration.pairwise import RegisterParams
from gscan.registration.sequence import SequenceParams, capture_noise, optimise_sequence, register_edges
from gscan.scanning.capture_mode import (
    MOVING_OBJECT,
    STATIC_OBJECT,
    background_depth,
    detect_mode,
    foreground_mask,
)
from gscan.scanning.config import ScanConfig
from gscan.scanning.fuse import FusedModel, FusionParams, fuse_tsdf, template_frame
from gscan.scanning.keyframes import select_keyframes, view_direction
from gscan.scanning.options import ScanOptions
from gscan.scanning.segment import SegmentParams, segment_frame
from gscan.scanning.select import FrameSelector, Selection, SelectionParams
from gscan.scanning.store import FrameStore, LazyList, StoredFrame
from gscan.template.db import Edge, TemplateDB, View

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence
    from gscan.io.sequence import Sequence

log = logging.getLogger(__name__)

# eps_f for whole-frame registration (static object) when the config leaves it unset: on whole frames
# RootSIFT 0.5 is as accurate as the object-only default 0.6 and gives far fewer candidates, so the search is
# faster (see BENCHMARKS.md, section Parameter studies)
WHOLE_FRAME_EPS_F = {"rootsift": 0.5}
WORKERS = 2  # threads for per-frame and per-edge work (the target machines have 2 cores)
COMMIT_ROWS = 64  # a stage's database writes are committed in chunks of this many views or edges (and at its end)
REG_CACHE = 8  # frames whose registration data (keypoints, depth samples) stays loaded: the sequential window
AHEAD = 2 * WORKERS  # per-frame and per-edge work submitted to the pool and not yet consumed
BACKGROUND_FRAMES = 30  # kept frames (evenly spaced) a static camera's background depth is taken from


@dataclass
class ScanResult:
    output: Path
    frames: int
    registered: int
    unregistered: list[str]
    edges_accepted: int
    edges_rejected: int
    mode: str
    mesh_vertices: int
    mesh_triangles: int
    timings_s: dict[str, float]
    problems: dict[str, str]  # frames that could not be read: name -> why
    keyframes: int = 0
    unregistered_reasons: dict[str, str] = field(default_factory=dict)  # every unregistered frame -> why
    parts: list[list[str]] = field(default_factory=list)  # frames of the parts not joined to the template's
    noise: DepthNoise | None = None  # the noise model of lifted keypoints registration used
    # frame selection: {"kept": int, "skipped": int, "reasons": {why: frames}}; skipped frames are not failures
    selection: dict = field(default_factory=dict)
    # the colour camera's check (`_check_camera`): given and used focal lengths, texture agreement; None: not run
    camera: dict | None = None

    def to_json(self) -> dict:
        """The `scan --json` object of the CLI contract."""
        return {"output": str(self.output), "frames": self.frames, "registered": self.registered,
                "unregistered": list(self.unregistered),
                "unregistered_reasons": {n: self.unregistered_reasons.get(n, "") for n in self.unregistered},
                "parts": [list(p) for p in self.parts],
                "edges": {"accepted": self.edges_accepted, "rejected": self.edges_rejected},
                "mode": self.mode, "mesh": {"vertices": self.mesh_vertices, "triangles": self.mesh_triangles},
                "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
                "skipped": dict(self.problems), "keyframes": self.keyframes, "selection": dict(self.selection),
                "camera": self.camera}


def _feature_params(cfg: ScanConfig) -> FeatureParams:
    """The registration keypoints' parameters from the config."""
    return FeatureParams(kind=cfg.features.kind, max_keypoints=cfg.features.max_keypoints)


def _register_params(cfg: ScanConfig, mode: str) -> RegisterParams:
    """Registration's parameters from the config; the noise models are the configured ones, or the priors a
    capture's own noise is estimated from (`capture_noise`)."""
    from gscan.matching.gmatch import GMatchParams

    m, r = cfg.match, cfg.registration
    eps_f = m.eps_f
    if eps_f is None and mode == STATIC_OBJECT:
        eps_f = WHOLE_FRAME_EPS_F.get(cfg.features.kind)
    # the depth refines edges of a moving object, whose masked views hold few keypoints; a static scene's
    # whole-frame depth pulls real Kinect edges off the truth where the camera moves fast (see BENCHMARKS.md,
    # section Real Kinect frames)
    dense = r.dense_refine if r.dense_refine is not None else mode == MOVING_OBJECT
    gm = GMatchParams(eps_f=eps_f, eps_c=m.eps_c, eta=m.eta, T=m.T, L=m.L, constraint=m.constraint, order=m.order)
    params = RegisterParams(method=m.method, gmatch=gm, min_matches=r.min_matches, max_rms=r.max_rms,
                            max_sigma_deg=r.max_sigma_deg, max_sigma_rel=r.max_sigma_rel,
                            max_see_through=r.max_see_through, min_colour_agreement=r.min_colour_agreement,
                            dense_refine=dense, verify=r.verify,
                            support_eps_scale=r.support_eps_scale, icp=r.icp, icp_max_dist=r.icp_max_dist,
                            icp_voxel=r.icp_voxel, min_fitness=r.min_fitness, max_rmse=r.max_rmse,
                            max_icp_shift_deg=r.max_icp_shift_deg, max_icp_shift_m=r.max_icp_shift_m)
    if r.noise is None:
        return params
    return replace(params, noise=DepthNoise(**r.noise.keypoint.model_dump()),
                   depth_noise=DepthNoise(**r.noise.depth.model_dump()))


def _sequence_params(cfg: ScanConfig) -> SequenceParams:
    """The sequence registration's parameters from the config."""
    p = cfg.posegraph
    return SequenceParams(loop_candidates=p.loop_candidates, max_view_angle_deg=p.max_view_angle_deg, alpha=p.alpha,
                          bridge_min_matches=p.bridge_min_matches)


class _EdgeRecords(EdgeSink):
    """The scan's database as the sink of a sequence's edges."""

    def __init__(self, db: TemplateDB):
        self.db = db

    def add(self, edge: PairEdge) -> None:
        self.db.add_edge(_record(edge))

    def commit(self) -> None:
        self.db.commit()

    def batch(self) -> contextlib.AbstractContextManager[None]:
        return self.db.batch()


def _record(e: PairEdge) -> Edge:
    """The database record of an edge."""
    return Edge(e.src, e.tgt, e.T_tgt_src, e.matches, e.cost, e.rmse, e.fitness, e.kind, e.accepted, e.reason)


def _pair_edge(e: Edge) -> PairEdge:
    """An edge of the database as registration holds it."""
    return PairEdge(e.src, e.tgt, e.T_tgt_src, e.matches, e.cost, e.rmse, e.fitness, e.kind, e.accepted, e.reason)


RESUME_KEYS = ("input", "format", "intrinsics_sha256", "depth_scale_option", "config", "mode_option", "segment",
               "obj_id_option", "topics_option", "depth_camera_sha256")


def _scan_meta(source: Path, opts: ScanOptions) -> dict:
    """The database's meta; a resumed scan must agree on every RESUME_KEYS value (what changes its result):
    the layout as detected (`--format auto` and the named layout agree), the calibration files' contents."""
    from gscan.io import detect_format

    return {"source": "scan", "input": str(source.resolve()),
            "format": detect_format(source) if opts.format == "auto" else opts.format,
            "intrinsics_sha256": None if opts.intrinsics is None else _sha256(Path(opts.intrinsics)),
            "depth_scale_option": opts.depth_scale, "config": opts.config.model_dump(), "mode_option": opts.mode,
            "segment": opts.segment, "obj_id_option": opts.obj_id, "descriptor": opts.config.features.kind,
            "topics_option": None if opts.color_topic is None and opts.depth_topic is None else
            [opts.color_topic, opts.depth_topic],
            "depth_camera_sha256": None if opts.depth_intrinsics is None else
            [_sha256(Path(p)) if p is not None else None for p in (opts.depth_intrinsics, opts.depth_to_color)],
            "units": "m"}


def _sha256(path: Path) -> str:
    import hashlib

    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as e:
        raise InputError(path, f"cannot read the calibration file ({e.strerror or e})") from None


def _open_resumed(source: Path, output: Path, opts: ScanOptions, seq: Sequence | RecordingSequence, frames: dict
                  ) -> tuple[TemplateDB, Output | None]:
    """The interrupted scan's database; it must come from the same input, configuration and input frames
    (`frames`: `Sequence.fingerprints`). A complete database (or one whose journal would have too long a
    name) is continued in a copy renamed over it at the end, so a failed run leaves it as it was."""
    meta = _scan_meta(source, opts)
    db = TemplateDB.open(output, require_complete=False)  # read only until it is known to be continued
    try:
        stored = {k: db.get_meta(k) for k in RESUME_KEYS}
        # settings added to the configuration since the scan started take their defaults; a configuration this
        # version does not read differs
        with contextlib.suppress(ValueError, TypeError):
            stored["config"] = json.loads(json.dumps(ScanConfig.model_validate(stored["config"]).model_dump()))
        if stored != {k: json.loads(json.dumps(meta[k])) for k in stored}:
            raise InputError(output, "was written from another input or configuration", fix="restart")
        _check_frames(output, db.get_meta("input_frames"), json.loads(json.dumps(frames)), seq)
        in_place = db.status != "complete" and journal_fits(output)
    except BaseException:
        db.close()
        raise
    db.close()
    if in_place:
        return TemplateDB.open(output, require_complete=False, writable=True, wal=True), None
    target = Output(output, force=True, kind=".gscan file path")
    try:
        shutil.copyfile(output, target.open())
        return TemplateDB.open(target.tmp, require_complete=False, writable=True, wal=True), target
    except BaseException as e:
        target.discard()
        t = target.translate(e)
        if t is not e:
            raise t from None
        raise


def _check_frames(output: Path, stored: object, frames: dict, seq: Sequence | RecordingSequence) -> None:
    """InputError unless the input frames hold what they held when the partial scan `output` started (their
    files' sizes and hashes): a scan resumed on other images would mix their keypoints and edges."""
    if not isinstance(stored, dict):
        raise InputError(output, "holds no record of the input frames it was started from (written by an older "
                         "gscan); it cannot be resumed safely", fix="restart")
    if stored == frames:
        return
    from gscan.io.layouts import natural_key

    for name in sorted(set(stored) | set(frames), key=natural_key):
        old, new = stored.get(name, "absent"), frames.get(name, "absent")
        if old == new:
            continue
        if new == "absent":
            what = f"frame {name} is no longer in the input"
        elif old == "absent":
            what = f"frame {name} was not in the input"
        elif old is None or new is None:
            what = f"frame {name} {'was unusable then' if old is None else 'is unusable now'}"
        else:
            role = next((r for r in ("color", "depth", "mask") if old.get(r) != new.get(r)), None)
            if role is None or not isinstance(seq, Sequence):  # a recording: one fingerprint of the frame's messages
                what = f"frame {name} changed"
            else:
                changed = getattr(seq.files(name), role) if role in new else None
                what = f"{changed} changed" if changed is not None else f"frame {name} has no {role} image now"
        raise InputError(output, f"the input frames are not the ones this partial scan was started from ({what})",
                         fix="restart")


def _create_output(output: Path, opts: ScanOptions, meta: dict) -> tuple[TemplateDB, Output | None]:
    """A new database: in place while nothing is at the output (an interrupted scan is then resumed from it),
    else in a temporary sibling that replaces the old output once complete (`Output`)."""
    if not occupied(output) and journal_fits(output):
        try:
            return TemplateDB.create(output, meta=meta, wal=True), None
        except OutputExists as e:  # created by another process since the checks
            if not opts.force:
                raise OutputExists(output, e.reason, fix="resume") from None
    target = Output(output, force=opts.force, kind=".gscan file path", fix="resume")
    try:
        return TemplateDB.create(target.open(), force=True, meta=meta, wal=True), target
    except BaseException as e:
        target.discard()
        t = target.translate(e)
        if t is not e:
            raise t from None
        raise


def _check_camera(source: Path, seq: Sequence | RecordingSequence, opts: ScanOptions, detections: dict[str, Detection]
                  ) -> tuple[Sequence | RecordingSequence, dict | None]:
    """A folder capture read with one set of intrinsics (no --depth-intrinsics, one K for every frame): the
    colour camera's focal length checked against the data (gscan.scanning.calibration). When the texture rejects
    the given one, the capture is read again with the given intrinsics as the depth camera's and the focal
    length the data give as the colour camera's. Returns (the sequence to scan, the check's report or None);
    the frames the check detected keypoints in are left in `detections` for the features stage."""
    from gscan.io import open_sequence
    from gscan.io.sequence import Sequence
    from gscan.scanning.calibration import check_colour_focal

    cfg = opts.config
    if (not cfg.camera.check_colour_focal or opts.depth_intrinsics is not None or not isinstance(seq, Sequence)
            or seq.depth_camera is not None or any(seq.frame_intrinsics(n) != seq.intrinsics for n in seq.names)):
        return seq, None

    def read(i: int) -> RGBDFrame | None:
        try:
            return seq[seq.names[i]]
        except InputError:
            return None

    check = check_colour_focal(read, len(seq.names), _register_params(cfg, STATIC_OBJECT), _feature_params(cfg),
                               workers=WORKERS, detections=detections)
    if check is None:
        return seq, None
    K = seq.intrinsics
    Kc = check.colour_intrinsics(K)
    # (the intrinsics themselves: `gscan.estimate` reads frames of this camera the same way)
    report = {"given_focal_px": [K.fx, K.fy], "colour_focal_px": [round(Kc.fx, 1), round(Kc.fy, 1)],
              "corrected": check.significant, "pairs": check.pairs,
              "texture_agreement": {"given": round(check.agreement[1.0], 3),
                                    "used": round(check.peak, 3)},
              "given_intrinsics": K.to_dict(), "colour_intrinsics": Kc.to_dict()}
    if not check.significant:
        return seq, report
    log.warning("the depth does not line up with the colour under the given intrinsics: the texture of %d frame "
                "pairs lines up best with a colour focal length of %.1f px (%.0f %% of textured tiles, %.0f %% at the "
                "given %.1f px); scanning with it, the given intrinsics taken as the depth camera's", check.pairs,
                Kc.fx, 100 * check.peak, 100 * check.agreement[1.0], K.fx)
    seq = open_sequence(source, format=opts.format, intrinsics=Kc, depth_scale=opts.depth_scale,
                        obj_id=opts.obj_id, depth_intrinsics=K)
    return seq, report


def run_scan(source: Path, output: Path, opts: ScanOptions, progress: Progress | None = None) -> ScanResult:
    """Run the whole pipeline (see the module docstring). Raises InputError for bad input.

    The output is checked before any frame is read (so a bad output fails on one line). A new output is
    written in place (resumable); an existing one (`force`) is replaced only by a complete new database,
    written beside it, so a failed or interrupted run leaves it as it was. The kept frames' images wait in a
    `FrameStore` beside the output while the scan runs (gone when it ends, however it ends).
    """
    from gscan.io import open_sequence

    resumed = opts.resume and output.is_file()
    check_output(output, force=opts.force or resumed, kind=".gscan file path", fix="resume")
    timer = StageTimer(progress)
    db: TemplateDB | None = None
    target: Output | None = None
    store: FrameStore | None = None
    try:
        seq = open_sequence(source, format=opts.format, intrinsics=opts.intrinsics,
                            depth_scale=opts.depth_scale, obj_id=opts.obj_id, color_topic=opts.color_topic,
                            depth_topic=opts.depth_topic, depth_intrinsics=opts.depth_intrinsics,
                            T_color_depth=opts.depth_to_color)
        if opts.obj_id is not None and seq.format != "bop":
            raise InputError(source, f"an object id is for BOP scene folders, this is a {seq.format} folder")
        if opts.obj_id is not None and seq.gt_T_cam_obj is None:
            raise InputError(source / "scene_gt.json", "not found (the object id picks an object of its "
                             "poses)", fix="obj_id")
        if opts.obj_id is not None and not seq.gt_T_cam_obj:
            raise InputError(source / "scene_gt.json", f"holds no pose of object {opts.obj_id}", fix="obj_id")
        fingerprints = seq.fingerprints()
        if resumed:
            db, target = _open_resumed(source, output, opts, seq, fingerprints)
        detections: dict[str, Detection] = {}
        with timer.stage("camera", total=1) as advance:  # (after the checks that refuse the input in one line)
            seq, camera = _check_camera(source, seq, opts, detections)
            advance(1)
        store = FrameStore(output)
        seg = _segment_params(opts.config)
        with timer.stage("mode", total=1) as advance:
            mode, masks_given = _detect_mode(seq, opts.mode)
            advance(1)
        with timer.stage("load", total=len(seq)) as advance:
            frames, failed, selection = _load(seq, mode, masks_given, opts.config, seg, store, advance)
        # in input order (the camera check reads frames on two threads): the listing problems first, as found,
        # then unreadable frames in the order of their names
        index = {name: i for i, name in enumerate(seq.names)}
        problems = dict(sorted(seq.problems.items(), key=lambda kv: index.get(kv[0], -1)))
        if not frames:  # one line (the CLI contract), no per-frame warnings before it
            first = next(iter(problems.items()), ("?", "?"))
            raise InputError(source,
                             f"no usable frame ({len(problems)} unusable); first: {first[0]}: {first[1]}")
    except BaseException:
        if store is not None:
            store.close()
        if db is not None:
            db.close()
        if target is not None:
            target.discard()
        raise
    for name, err in failed:
        log.warning("skipping frame %s: %s", name, err)

    made = missing_folders(output)
    created = None
    try:
        if db is None:
            # obj_id: the BOP object the scan followed (its ground truth and masks), for `gscan eval`
            db, target = _create_output(output, opts, dict(opts.meta) | _scan_meta(source, opts) | {
                "obj_id": seq.obj_id, "input_frames": fingerprints, "camera": camera})
        created = file_identity(output)  # a new output in place: only this file is removed on failure
        if resumed:  # only once the input is known to hold frames: a complete database stays complete
            db.mark_partial()
        data = _FrameData(frames, store, db, mode, masks_given, opts.config, detections)
        result = _scan_frames(data, source, output, opts, db, resumed, timer, problems, selection)
        result.camera = camera
    except BaseException as e:
        store.close()
        if db is not None:
            db.close()
        if target is not None:  # the old output stays as it was
            target.discard()
            t = target.translate(e)
            if t is not e:
                raise t from None
        elif (db is not None and not resumed and not isinstance(e, KeyboardInterrupt)
              and file_identity(output) == created):
            # a failed scan leaves no output behind: neither the file nor folders made for it (never a file
            # another process put there since); Ctrl+C keeps the partial file for --resume (as a killed scan does)
            output.unlink(missing_ok=True)
            remove_sqlite_sidecars(output)
            remove_empty_folders(made)
        raise
    store.close()
    db.close()
    if target is not None:
        remove_sqlite_sidecars(output)  # a killed writer's journal or log there would be replayed into ours
        target.commit()
    return result


# ------------------------------------------------------------------------------------------ the frames
@dataclass
class _Frame:
    """A kept frame, as the stages after the load hold it: its images are in the scan's `FrameStore` ("color",
    "depth", "given_mask"; "object_mask" of a moving object when computed; "mask" once segmented), its keypoints in
    the database (camera frame until the last stage); `_FrameData` loads them on demand."""

    stored: StoredFrame
    n_keypoints: int = 0  # registration keypoints with depth
    depth_m: float | None = None  # their median depth (m): the depth the frame looks at
    plane_cam: Plane | None = None  # support plane found while computing a moving object's mask
    object_keypoints: int = 0  # registration keypoints inside its object mask (set at the segment stage)

    @property
    def name(self) -> str:
        return self.stored.name


class _FrameData:
    """The kept frames' images, masks and registration data, loaded on demand: images from the store, keypoints
    from the database. Registration data of the last `REG_CACHE` frames used is kept (the sequential pairs and the
    workers' frames), so memory does not grow with the capture. detections: frames' whole-frame detections made
    before the features stage (the camera check's), by name, each taken by that stage. Thread-safe."""

    def __init__(self, frames: list[_Frame], store: FrameStore, db: TemplateDB, mode: str, masks_given: bool,
                 cfg: ScanConfig, detections: dict[str, Detection] | None = None):
        self.frames, self.store, self.db, self.mode, self.masks_given, self.cfg = (frames, store, db, mode,
                                                                                    masks_given, cfg)
        self.detections = {} if detections is None else detections
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
        depth = self.store.need(f.name, "depth")
        reg_mask = self.object_mask(k)
        r = self.cfg.registration
        cloud = icp_cloud(depth, f.intrinsics, reg_mask, r.icp_voxel) if r.icp else None
        data = RegData(feats, cloud, DenseGeometry.from_depth(depth, f.intrinsics, reg_mask,
                                                               image=self.store.need(f.name, "color")))
        with self._lock:
            self._cache[k] = data
            while len(self._cache) > REG_CACHE:
                self._cache.popitem(last=False)
        return data


class _InputFrames(collections.abc.Sequence):
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


def _detect_mode(seq: Sequence | RecordingSequence, mode_option: str) -> tuple[str, bool]:
    """(capture mode, whether every frame comes with an object mask): the mode from a few frames spread over the
    input (`detect_mode`) unless given."""
    names = seq.names
    given = isinstance(seq, Sequence) and seq.has_masks and all(seq.files(n).mask is not None for n in names)
    if mode_option != "auto":
        return mode_option, given
    try:
        return detect_mode(_InputFrames(seq)).mode, given
    except _NoUsableFrame:  # the load says so, on one line
        return STATIC_OBJECT, given


def _load(seq: Sequence | RecordingSequence, mode: str, masks_given: bool, cfg: ScanConfig, seg: SegmentParams,
          store: FrameStore, advance: Callable[[int], None]) -> tuple[list[_Frame], list[tuple[str, InputError]],
                                                                     Selection]:
    """Reads the input once, in order, keeping the frames frame selection keeps (`gscan.scanning.select`): their images
    go to the store, with a moving object's mask (`moving_object_masks`: the support plane and the object on it,
    else the difference from the background). Returns (kept frames, frames that could not be read, selection)."""
    s = cfg.selection
    params = SelectionParams(min_motion_deg=s.min_motion_deg, blur_ratio=s.blur_ratio)
    moving = mode == MOVING_OBJECT
    selector = FrameSelector(params, mask_needed=moving)
    selection = Selection(params)
    frames: list[_Frame] = []
    failed: list[tuple[str, InputError]] = []
    for name, frame in _read_ahead(seq):
        advance(1)
        if isinstance(frame, InputError):
            failed.append((name, frame))
            continue
        why = selector.consider(frame)
        if why is not None:
            selection.skipped[name] = why
            continue
        f = _Frame(StoredFrame.put(store, frame))
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
        picks = np.unique(np.linspace(0, len(frames) - 1, min(BACKGROUND_FRAMES, len(frames))).round().astype(int))
        bg = background_depth([store.need(frames[k].name, "depth") for k in picks])
        for f in frames:
            if f.plane_cam is None:
                store.put(f.name, object_mask=foreground_mask(store.need(f.name, "depth"), bg))
    return frames, failed, selection


def _read_ahead(seq: Sequence | RecordingSequence) -> Iterator[tuple[str, RGBDFrame | InputError]]:
    """(name, frame or why it could not be read) for every input frame in order, the next one decoded in a thread
    meanwhile (decoding releases the GIL)."""
    def read(name: str) -> RGBDFrame | InputError:
        try:
            return seq[name]
        except InputError as e:
            return e

    with ThreadPoolExecutor(max_workers=1) as pool:
        yield from zip(seq.names, bounded_map(pool, read, seq.names, 2), strict=True)


# ------------------------------------------------------------------------------------------ the stages
def _scan_frames(data: _FrameData, source: Path, output: Path, opts: ScanOptions, db: TemplateDB, resumed: bool,
                 timer: StageTimer, problems: dict[str, str], selection: Selection) -> ScanResult:
    cfg = opts.config
    seg = _segment_params(cfg)
    frames, mode = data.frames, data.mode
    log.info("%s capture, %d of %d frames kept%s", mode, len(frames), len(frames) + len(selection.skipped),
             ", masks given" if data.masks_given else "")

    # each stage's writes are batched: one commit per stage, or per COMMIT_ROWS records in a long one
    with timer.stage("features", total=len(frames)) as advance, db.batch():
        db.set_meta("mode", mode)
        db.set_meta("selection", selection.to_meta())
        _extract(data, db, resumed, advance)
    if not any(f.n_keypoints for f in frames):  # every frame dark, textureless or without depth: nothing to scan
        raise InputError(source, f"no keypoint with depth in any of the {len(frames)} frames "
                         "(dark or textureless images, or no valid depth)")

    n = len(frames)
    rparams = _register_params(cfg, mode)
    sparams = _sequence_params(cfg)
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        with timer.stage("noise", total=1) as advance, db.batch():
            if cfg.registration.noise is None:
                kp_noise, depth_noise = capture_noise(data, rparams, sparams.pilot_pairs, pool)
                rparams = replace(rparams, noise=kp_noise, depth_noise=depth_noise)
            db.set_meta("noise", {"keypoint": rparams.noise.to_dict(), "depth": rparams.depth_noise.to_dict()})
            advance(1)
        sink = _EdgeRecords(db)
        reg = Registrar(data, rparams, sink, [_pair_edge(e) for e in db.edges()] if resumed else (), AHEAD)
        with timer.stage("register", total=max(1, n - 1)) as advance, db.batch():
            edges = register_edges(reg, sparams, pool, advance)
        with timer.stage("posegraph", total=1) as advance:
            res = optimise_sequence(reg, edges, sparams, pool)
            advance(1)
    edges, T_world_cam, quality = res.edges, res.T_world_cam, res.quality
    registered = [k for k in range(n) if T_world_cam[k] is not None]
    reasons, parts = res.unregistered_reasons, res.parts

    with timer.stage("segment", total=n) as advance:
        mask_of, plane_world = _segment(data, T_world_cam, opts.segment, replace(seg, depth_noise=rparams.depth_noise),
                                        advance)

    with timer.stage("fuse", total=1) as advance:
        model, T_obj_world = _fuse(data, T_world_cam, mask_of, plane_world, cfg, source)
        advance(1)

    with timer.stage("database", total=n + 1) as advance, db.batch():
        T_obj_cam = [None if T is None else T_obj_world @ T for T in T_world_cam]
        keyframes = _store_views(data, T_obj_cam, mask_of, quality, cfg, db, advance)
        for e in edges:  # the pose graph's verdicts, also where a resumed run reaches another one
            if e.pruned or (e.src, e.tgt) in res.restored:
                db.add_edge(_record(e))
        mesh = model.mesh.transformed(T_obj_world)
        db.set_mesh(mesh)
        db.set_cloud(transform_points(T_obj_world, model.points), model.point_colors)
        unregistered = [f.name for f, T in zip(frames, T_world_cam, strict=True) if T is None]
        db.set_meta("unregistered", unregistered)
        db.set_meta("unregistered_reasons", reasons)
        db.set_meta("parts", parts)
        db.set_meta("skipped", problems)
        db.set_meta("voxel_size", model.voxel_size)
        db.set_meta("support_plane", plane_world is not None)
        db.set_meta("timings_s", timer.timings)
        db.mark_complete()
        advance(1)
    stored_edges = db.edges()
    accepted = sum(1 for e in stored_edges if e.accepted)
    total_edges = len(stored_edges)
    return ScanResult(output=output, frames=n + len(selection.skipped) + len(problems),
                      registered=len(registered), unregistered=unregistered + sorted(problems),
                      edges_accepted=accepted, edges_rejected=total_edges - accepted, mode=mode,
                      mesh_vertices=len(mesh.vertices), mesh_triangles=len(mesh.triangles),
                      timings_s=dict(timer.timings), problems=problems, keyframes=len(keyframes),
                      unregistered_reasons=reasons | problems, parts=parts, noise=rparams.noise,
                      selection=selection.summary())


def _fuse(data: _FrameData, T_world_cam: list[np.ndarray | None], mask_of: Callable[[int], np.ndarray | None],
          plane_world: Plane | None, cfg: ScanConfig, input_dir: Path) -> tuple[FusedModel, np.ndarray]:
    """(TSDF model in the world frame, T_obj_world [4 x 4] of the template frame); InputError when
    nothing could be fused."""
    params = FusionParams(voxel_size=cfg.fusion.voxel, depth_max=cfg.fusion.depth_max)
    n = len(data)
    try:
        model = fuse_tsdf(LazyList(n, data.frame), T_world_cam, LazyList(n, mask_of), params)
    except ValueError as e:  # no registered frame has object depth within fusion.depth_max
        raise InputError(input_dir, f"nothing could be fused: {e} (fusion.depth_max); check the depth scale",
                         fix="depth_scale") from None
    registered = [k for k, T in enumerate(T_world_cam) if T is not None]
    if len(model.mesh.triangles) == 0 or len(model.mesh.vertices) < 3:
        raise InputError(input_dir, "nothing could be fused: no surface in the object depth of the "
                         f"{len(registered)} registered frame(s)")
    obj_pts = model.points if len(model.points) >= 3 else model.mesh.vertices
    T_world_cam0 = T_world_cam[registered[0]]
    assert T_world_cam0 is not None
    return model, template_frame(obj_pts, plane_world, T_world_cam0)


def _segment_params(cfg: ScanConfig) -> SegmentParams:
    s = cfg.segmentation
    return SegmentParams(depth_min=s.depth_min, depth_max=s.depth_max, height_max=s.height_max)


def _extract(data: _FrameData, db: TemplateDB, resumed: bool, advance: Callable[[int], None]) -> None:
    """Each frame's registration keypoints (camera frame; a moving object's only), stored at once with the view's
    images: the one write of those. A resumed scan reuses the keypoints of views stored without a pose."""
    cfg, frames = data.cfg, data.frames
    fparams = _feature_params(cfg)
    stored = set(db.view_names()) if resumed else set()
    db_poses = {v.name: v.T_obj_cam for v in db.views()} if stored else {}
    for name in stored - {f.name for f in frames}:  # a view of a frame this scan does not keep
        db.remove_view(name)

    def frame_work(k: int) -> tuple[RGBDFrame | None, Features | None]:
        name = frames[k].name
        if name in stored and db_poses.get(name, 1) is None:
            return None, None  # stored by the interrupted run, still in the camera frame
        frame = data.frame(k)
        return frame, extract_features(frame, fparams, mask=data.object_mask(k),
                                       detection=data.detections.pop(name, None))

    # OpenCV releases the GIL: two threads use both cores; results are per frame and written in input order,
    # so the output does not depend on the scheduling
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        for k, (frame, feats) in enumerate(bounded_map(pool, frame_work, range(len(frames)), AHEAD)):
            f = frames[k]
            if frame is None or feats is None:  # stored by the interrupted run, still in the camera frame
                stored_feats = db.features(f.name)
                if stored_feats is None:
                    raise InputError(db.path, f"view {f.name!r} is stored without its keypoints", fix="restart")
                f.n_keypoints, f.depth_m = len(stored_feats), _median_depth(stored_feats)
            else:
                db.add_view(View.from_frame(frame, keyframe=False, input_index=k), feats, replace=f.name in stored)
                f.n_keypoints, f.depth_m = len(feats), _median_depth(feats)
                if (k + 1) % COMMIT_ROWS == 0:
                    db.commit()
            advance(1)
    data.detections.clear()  # frames the scan does not keep


def _median_depth(feats: Features) -> float | None:
    return float(np.median(feats.points[:, 2])) if len(feats) else None


def _store_views(data: _FrameData, T_obj_cam: list[np.ndarray | None], mask_of: Callable[[int], np.ndarray | None],
                 quality: dict[int, float], cfg: ScanConfig, db: TemplateDB,
                 advance: Callable[[int], None]) -> set[int]:
    """Completes every view with its pose (its keypoints follow into the object frame), mask, keyframe flag and
    quality; chooses the keyframes and returns their indices.

    Keyframes also keep keypoints on the object alone, detected inside the object mask with the
    estimator's settings: the template's keypoints for pose estimation (registration keypoints of a
    static object are mostly on the table)."""
    frames = data.frames

    def shows(k: int) -> bool:
        m = mask_of(k)
        return m is None or bool(m.any())

    dirs = _keyframe_candidates(T_obj_cam, shows)
    kc = cfg.keyframes
    keyframes = set(select_keyframes(dirs, kc.min_angle_deg, kc.max_views,
                                     {k: frames[k].object_keypoints for k in dirs}, kc.min_object_keypoints,
                                     kc.min_views))
    oparams = replace(OBJECT_FEATURES, kind=cfg.features.kind, max_keypoints=cfg.features.max_keypoints)

    def view_work(k: int) -> tuple[np.ndarray | None, Features | None]:
        f = frames[k].stored
        if T_obj_cam[k] is None:  # an unregistered view keeps the mask it came with
            return (data.store.get(f.name, "given_mask") if f.has_mask else None), None
        m = mask_of(k)
        obj = extract_features_in_mask(data.frame(k), m, oparams) if k in keyframes and m is not None else None
        return m, obj

    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        for k, (m, obj) in enumerate(bounded_map(pool, view_work, range(len(frames)), AHEAD)):
            T = T_obj_cam[k]
            # the view's images and keypoints were stored at the features stage: its pose (the keypoints follow
            # it into the object frame), mask, keyframe flag and quality complete it
            db.update_view(frames[k].name, T_obj_cam=T, mask=m, keyframe=k in keyframes, quality=quality.get(k))
            if obj is not None and T is not None:
                db.add_features(frames[k].name, obj.transformed(T), role="object")
            advance(1)
    return keyframes


def _keyframe_candidates(T_obj_cam: list[np.ndarray | None], shows: Callable[[int], bool]) -> dict[int, np.ndarray]:
    """Frame index -> viewing direction (`view_direction`) of the registered frames that show the object
    (`shows(k)`: its object mask is not empty): a frame without it (a sweep that starts elsewhere) would give
    the template its background as the object's keypoints. All registered frames when none shows it."""
    reg = {k: T for k, T in enumerate(T_obj_cam) if T is not None}
    showing = {k: T for k, T in reg.items() if shows(k)}
    return {k: view_direction(T) for k, T in (showing or reg).items()}


def _object_keypoints(pixels: np.ndarray, mask: np.ndarray | None) -> int:
    """Registration keypoints (with depth; their pixels [N x 2]) of a frame that lie in its object mask (all
    without a mask)."""
    if mask is None:
        return len(pixels)
    uv = np.round(pixels).astype(int)
    H, W = mask.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    return int(mask[uv[inside, 1], uv[inside, 0]].sum())


def _segment(data: _FrameData, T_world_cam: list[np.ndarray | None], segment: bool, seg: SegmentParams,
             advance: Callable[[int], None]) -> tuple[Callable[[int], np.ndarray | None], Plane | None]:
    """Per-frame object masks for fusion (a function of the frame index, the masks being in the store) and the
    support plane in the world frame (or None); sets each frame's count of keypoints inside its mask.

    The plane defines the template frame's z axis even when masks are given: for a static object
    it comes from the working volume over the registered frames; for a moving object from the
    reference frame alone (a turntable's plane moves with the object; an object in hand has none).
    """
    from gscan.scanning.segment import estimate_working_volume, segment_frame, segment_in_volume

    frames = data.frames
    n = len(frames)
    reg = [k for k, T in enumerate(T_world_cam) if T is not None]
    plane: Plane | None = None
    if not segment:
        def mask_of(k: int) -> np.ndarray | None:
            return None
    elif data.mode == MOVING_OBJECT:
        ref = frames[reg[0]]
        plane_cam = ref.plane_cam if ref.plane_cam is not None else segment_frame(
            replace(data.frame(reg[0]), mask=None), seg).plane_cam
        T_world_ref = T_world_cam[reg[0]]
        plane = None if plane_cam is None or T_world_ref is None else plane_cam.transformed(T_world_ref)
        mask_of = data.object_mask
    else:  # given masks win
        vol = estimate_working_volume(LazyList(len(reg), lambda i: data.frame(reg[i])),
                                      [T for T in (T_world_cam[k] for k in reg) if T is not None], seg)

        def mask_at(k: int) -> np.ndarray | None:
            return segment_in_volume(data.frame(k), T_world_cam[k], vol, seg).mask

        # per frame, on both cores (reading and reprojecting the images release the GIL), stored in input order
        with ThreadPoolExecutor(max_workers=WORKERS) as pool:
            for k, mask in enumerate(bounded_map(pool, mask_at, range(n), AHEAD)):
                data.store.put(frames[k].name, mask=mask)
        plane = vol.plane_world if vol is not None else None

        def mask_of(k: int) -> np.ndarray | None:
            return data.store.get(frames[k].name, "mask")
    for k in range(n):  # what the keyframes are chosen by
        f = frames[k]
        if T_world_cam[k] is not None:
            feats = data.db.features(f.name)
            f.object_keypoints = 0 if feats is None else _object_keypoints(feats.pixels, mask_of(k))
        advance(1)
    return mask_of, plane
