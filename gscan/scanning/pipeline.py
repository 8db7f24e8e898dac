"""The scan pipeline: an RGB-D folder to registered views, pose graph, fused mesh and template database.

Stages (each timed, each reported through a `Progress`):
  camera    a folder capture's colour focal length checked against its data (`gscan.scanning.camera`)
  mode      static-object vs moving-object (`gscan.scanning.capture_mode`), from a few frames spread over the input
  load      read every frame once, in order (unusable ones are reported by name and left out); frame selection
            (`gscan.scanning.select`) keeps the frames the view moved enough to, the sharper where frames blur, and
            reports the others as skipped (not failures); a kept frame's images go to the scan's frame store
            (`gscan.scanning.store`, an anonymous file beside the output), with a moving object's mask
  features  keypoints + descriptors lifted to 3D; whole frame for a static object, object only for a
            moving one; stored at once in the database with the view's images (camera frame, pose unknown)
  noise     the capture's keypoint and depth noise from a few sequential pairs (unless configured)
  register  pairwise edges (`gscan.registration.sequence`): each frame against the previous one, falling back to
            the next earlier ones, then loop closures chosen by view overlap and bag-of-words votes; each edge =
            GMatch -> Kabsch -> guided refinement (-> ICP when configured), accepted by the rules of
            `gscan.registration.pairwise`; stored as it is computed
  posegraph robust global optimisation (`gscan.registration.sequence`, `.posegraph`) with pruning of inconsistent
            edges and second opinions on the frames it cuts loose; frames not connected to the reference frame
            stay unregistered and are never fused
  segment   object masks (given, background subtraction, or support plane + working volume)
  fuse      TSDF fusion of the object's depth; template frame (fuse.template_frame)
  symmetry  the object's symmetries on the fused mesh (`gscan.scanning.symmetry`), stored in the "symmetries" meta
  database  poses, masks, keyframes and keypoints in the object frame, mesh, cloud; status complete

Memory does not grow with the capture: after the load a stage holds a few frames at a time, reading their
images back from the frame store and their keypoints from the database (`FrameData`); what stays in memory
per kept frame is its name, counts and pose, and per edge its matches and pose-graph evidence.

Database writes: one transaction per stage (per COMMIT_ROWS views or edges in a long one) on a write-ahead log,
each view's images written once (`gscan.template.db`).

Resume: the database is `partial` until the last transaction. `--resume` reuses the stored views'
keypoints and every stored edge (the expensive parts) and recomputes the rest, which is
deterministic, so an interrupted scan resumes to the same result as an uninterrupted one
(`gscan.scanning.output`). The frames are loaded and read back by `gscan.scanning.frames`.
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gscan.errors import InputError
from gscan.features import (
    OBJECT_FEATURES,
    Detection,
    FeatureParams,
    Features,
    extract_features,
    extract_features_in_mask,
)
from gscan.features.depth import (
    choose_source,
    depth_keypoints,
    extract_keypoints,
    joint_features,
    median_object_size,
    pilot_frames,
)
from gscan.features.keypoints import JOINT
from gscan.geometry.coverage import template_coverage
from gscan.geometry.plane import Plane
from gscan.geometry.symmetry import Symmetries
from gscan.geometry.transforms import transform_points
from gscan.io.camera import RGBDFrame, point_cloud
from gscan.io.captures import CaptureInput
from gscan.io.output import (
    file_identity,
    missing_folders,
    remove_empty_folders,
    remove_sqlite_sidecars,
)
from gscan.io.sequence import spread_indices
from gscan.progress import Progress, StageTimer
from gscan.registration.edges import COMMIT_ROWS, EdgeSink, RegData, Registrar, bounded_map
from gscan.registration.join import Join, JoinView, join_captures
from gscan.registration.noise import DepthNoise
from gscan.registration.pairwise import RegisterParams, register_features
from gscan.registration.sequence import capture_noise, optimise_sequence, register_edges
from gscan.scanning.camera import check_camera
from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT
from gscan.scanning.config import ScanConfig, for_capture
from gscan.scanning.frames import WORKERS, Frame, FrameData, detect_capture_mode, load_frames
from gscan.scanning.fuse import FusedModel, FusionParams, fuse_tsdf, template_frame
from gscan.scanning.keyframes import keyframe_candidates, select_keyframes
from gscan.scanning.opening import OpenedScan, open_scan, template_captures
from gscan.scanning.options import ScanOptions
from gscan.scanning.output import create_output, scan_meta
from gscan.scanning.segment import ChosenObject, ObjectHint, SegmentParams, object_hint, segment_frame
from gscan.scanning.select import BLURRED, LITTLE_MOTION, Selection
from gscan.scanning.store import FrameStore, LazyList, StoredFrame
from gscan.scanning.symmetry import scan_symmetries
from gscan.template.db import Edge, TemplateDB, View

if TYPE_CHECKING:
    from gscan.io.recordings.sequence import RecordingSequence
    from gscan.io.sequence import Sequence as FrameSequence

log = logging.getLogger(__name__)

AHEAD = 2 * WORKERS  # per-frame and per-edge work submitted to the pool and not yet consumed


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
    # a recording's damaged records, one line each (file, topic, messages listed and read, where they are missing)
    damage: list[str] = field(default_factory=list)
    # a scan of several captures: each one's name, input, frames, registered, whether it was joined (and why not),
    # seconds per stage (`_capture_summary`); empty for one capture
    captures: list[dict] = field(default_factory=list)
    # the colour camera's check (`check_camera`): verdict, focal lengths given and used, the estimate's interval, the
    # depth-edge evidence, the frames resting on an unconfirmed focal length; None: not run
    camera: dict | None = None
    coverage: dict | None = None  # {"share": float, "missing": [sentences]} (`gscan.geometry.coverage`)
    symmetries: Symmetries = field(default_factory=Symmetries)  # the object's (object frame)
    # which object segmentation chose and why (`gscan.scanning.segment.ChosenObject.to_json`); None: not segmented
    object: dict | None = None
    # the keypoints registration used (the first capture's `FrameData.keypoints`) and "depth_only_edges": the
    # accepted edges of this run that the depth alone decided (`gscan.registration.pairwise`); with depth keypoints
    # on the keyframes, "object": "both" and "object_depth_size" (m) they and a query's are found at
    keypoints: dict = field(default_factory=dict)
    # the steady motion of the first capture that measured one (an --append's stored template measures none), the
    # refused edges it accepted and the breaks it bridged (`SequenceResult.motion`); None: no capture had enough
    # accepted consecutive edges
    motion: dict | None = None

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
                "camera": self.camera, "coverage": self.coverage, "symmetries": self.symmetries.to_json(),
                "object": self.object, "damage": list(self.damage), "keypoints": dict(self.keypoints),
                "motion": self.motion} | (
                    {"captures": list(self.captures)} if self.captures else {})


def _icp_voxel(cfg: ScanConfig) -> float | None:
    """The voxel of the clouds ICP refines edges on (m); None without ICP."""
    return cfg.registration.icp_voxel if cfg.registration.icp else None


class _EdgeRecords(EdgeSink):
    """The scan's database as the sink of a sequence's edges."""

    def __init__(self, db: TemplateDB):
        self.db = db

    def add(self, edge: Edge) -> None:
        self.db.add_edge(edge)

    def commit(self) -> None:
        self.db.commit()

    def batch(self) -> contextlib.AbstractContextManager[None]:
        return self.db.batch()


@dataclass
class _Capture:
    """One capture of the scan as its stages fill it in: read and loaded (`_load`), then registered in its own
    world (`_register_capture`), then joined to the first (`_join`)."""

    input: CaptureInput
    seq: FrameSequence | RecordingSequence | None  # None: the views of the template appended to
    prefix: str  # of its frames' names: "CAPTURE/" when the scan has several, else ""
    camera: dict | None = None
    mode: str = ""
    masks_given: bool = False
    frames: list[Frame] = field(default_factory=list)
    failed: list[tuple[str, InputError]] = field(default_factory=list)
    selection: Selection | None = None
    skipped: list[StoredFrame] = field(default_factory=list)  # frames selection skipped, images in the store
    problems: dict[str, str] = field(default_factory=dict)  # unusable frames (prefixed names) -> why
    detections: dict[str, Detection] = field(default_factory=dict)
    data: FrameData | None = None
    reg: _Registered | None = None
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage spent on this capture
    join: Join | None = None  # how it was joined to the captures before it (None: the first, or one capture)
    hint: ObjectHint | None = None  # the user's choice of the object in its first frame (--roi / --mask)

    @property
    def source(self) -> Path:
        return self.input.source


@dataclass
class _Registered:
    """A capture registered in its own world: per kept frame T_world_cam (None: unregistered), object masks (a
    function of the frame's index), the support plane, view qualities, the pose graph's outcome."""

    T_world_cam: list[np.ndarray | None]
    mask_of: Callable[[int], np.ndarray | None]
    plane_world: Plane | None
    quality: dict[int, float]
    reasons: dict[str, str]
    parts: list[list[str]]
    edges: list[Edge]
    restored: set[tuple[str, str]]
    rparams: RegisterParams
    # frames skipped by selection: name -> T_world_cam found by registration to their reference, or why not
    placed: dict[str, np.ndarray | str] = field(default_factory=dict)
    chosen: ChosenObject | None = None  # the object segmentation chose, and why
    motion: dict | None = None  # the capture's steady motion (`SequenceResult.motion`)


def run_scan(sources: Path | Sequence[Path], output: Path, opts: ScanOptions,
             progress: Progress | None = None, opened: OpenedScan | None = None) -> ScanResult:
    """Run the whole pipeline (see the module docstring) on one capture or several of one object. Raises
    InputError for bad input.

    The output is checked before any frame is read (so a bad output fails on one line). A new output is
    written in place (resumable); an existing one (`force`) is replaced only by a complete new database,
    written beside it, so a failed or interrupted run leaves it as it was. The kept frames' images wait in a
    `FrameStore` beside the output while the scan runs (gone when it ends, however it ends).

    opened: the input and output `open_scan(sources, output, opts)` opened (`gscan scan` opens them before this
    module loads); None: opened here.
    """
    if opened is None:
        opened = open_scan(sources, output, opts)
    sources, resumed, db, target = opened.sources, opened.resumed, opened.db, opened.target
    timer = StageTimer(progress)
    store: FrameStore | None = None
    base: _Capture | None = None  # --append: the template's views, as a capture registered in the object frame
    try:
        caps = [_Capture(c, seq, prefix) for c, seq, prefix in opened.captures]
        seqs = [cap.seq for cap in caps if cap.seq is not None]
        fingerprints = opened.fingerprints
        store = FrameStore(output)
        if opts.append:
            assert db is not None
            base = _template_capture(db, store, opts)
        hint = _first_frame_hint(caps[0], opts)  # before the loads: a bad box or mask fails at once
        for cap in caps:
            _load(cap, opts, timer, store)
        caps[0].hint = _kept_first(caps[0], hint)
    except BaseException:
        if store is not None:
            store.close()
        if db is not None:
            db.close()
        if target is not None:
            target.discard()
        raise
    for cap in caps:
        for name, err in cap.failed:
            log.warning("skipping frame %s: %s", name, err)

    made = missing_folders(output)
    created = None
    try:
        if db is None:
            # obj_id: the BOP object the scan followed (its ground truth and masks), for `gscan eval`
            db, target = create_output(output, opts, dict(opts.meta) | scan_meta(sources, opts) | {
                "obj_id": seqs[0].obj_id, "input_frames": fingerprints, "camera": caps[0].camera})
        created = file_identity(output)  # a new output in place: only this file is removed on failure
        if resumed or opts.append:  # only once the input is known to hold frames: a complete database stays complete
            db.mark_partial()
        result = _scan_frames(caps if base is None else [base, *caps], output, opts, db, store, resumed, timer)
        result.camera = caps[0].camera
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


def _load(cap: _Capture, opts: ScanOptions, timer: StageTimer, store: FrameStore) -> None:
    """The camera check, the capture mode and the load of one capture (frames named with its prefix)."""
    before = dict(timer.timings)
    detections: dict[str, Detection] = {}
    assert cap.seq is not None
    with timer.stage("mode", total=1) as advance:  # (after the checks that refuse the input in one line)
        cap.mode, cap.masks_given = detect_capture_mode(cap.seq, opts.mode)
        advance(1)
    with timer.stage("camera", total=1) as advance:
        # (read again, if at all, as this capture was opened: its own layout and object)
        own = replace(opts, format=cap.input.format or opts.format,
                      obj_id=opts.obj_id if cap.input.obj_id is None else cap.input.obj_id)
        cap.seq, cap.camera = check_camera(cap.source, cap.seq, own, detections, cap.mode)
        advance(1)
    cap.detections = {cap.prefix + n: d for n, d in detections.items()}
    seq = cap.seq
    assert seq is not None
    with timer.stage("load", total=len(seq)) as advance:
        cap.frames, cap.failed, cap.selection, cap.skipped = load_frames(
            seq, cap.mode, cap.masks_given, opts.config.selection, opts.config.segmentation, store, advance,
            cap.prefix)
    # in input order (the camera check reads frames on two threads): the listing problems first, as found,
    # then unreadable frames in the order of their names
    index = {name: i for i, name in enumerate(seq.names)}
    cap.problems = {cap.prefix + n: why for n, why in sorted(seq.problems.items(),
                                                              key=lambda kv: index.get(kv[0], -1))}
    if not cap.frames:  # one line (the CLI contract), no per-frame warnings before it
        first = next(iter(cap.problems.items()), ("?", "?"))
        raise InputError(cap.source,
                         f"no usable frame ({len(cap.problems)} unusable); first: {first[0]}: {first[1]}")
    _add_timings(cap, before, timer)


def _add_timings(cap: _Capture, before: dict[str, float], timer: StageTimer) -> None:
    for k, v in timer.timings.items():
        if v - before.get(k, 0.0) > 0:
            cap.timings[k] = cap.timings.get(k, 0.0) + v - before.get(k, 0.0)


# ------------------------------------------------------------------------------------------ the stages
def _scan_frames(caps: list[_Capture], output: Path, opts: ScanOptions, db: TemplateDB, store: FrameStore,
                 resumed: bool, timer: StageTimer) -> ScanResult:
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        for cap in caps:
            if cap.reg is not None:  # the template appended to
                continue
            before = dict(timer.timings)
            _register_capture(cap, opts, db, store, resumed, timer, pool)
            _add_timings(cap, before, timer)
        if len(caps) > 1:
            _join(caps, opts.config, timer, pool)
    for cap in caps[1:] if opts.append else []:
        assert cap.join is not None
        if cap.join.T_a_b is None:  # the template is left as it was
            raise InputError(cap.source, f"cannot be joined to the template {output}: {cap.join.reason}; the "
                             "template is left as it was")

    # the captures' frames as one sequence in the first capture's world (a capture not joined: unregistered)
    frames = [f for cap in caps for f in cap.frames]
    n = len(frames)
    offsets = np.cumsum([0] + [len(cap.frames) for cap in caps])
    T_world_cam: list[np.ndarray | None] = []
    quality: dict[int, float] = {}
    reasons: dict[str, str] = {}
    parts: list[list[str]] = []
    for cap, off in zip(caps, offsets, strict=False):
        r = cap.reg
        assert r is not None
        T_join = np.eye(4) if cap.join is None else cap.join.T_a_b
        if T_join is None:  # its own part, never fused at a guessed pose
            why = f"capture {cap.input.name} was not joined to the others: {cap.join.reason}"  # type: ignore[union-attr]
            reasons |= {f.name: why for f, T in zip(cap.frames, r.T_world_cam, strict=True) if T is not None}
            parts.append([f.name for f, T in zip(cap.frames, r.T_world_cam, strict=True) if T is not None])
            T_world_cam += [None] * len(cap.frames)
        else:
            T_world_cam += [None if T is None else T_join @ T for T in r.T_world_cam]
            quality |= {off + k: q for k, q in r.quality.items()}
        reasons |= r.reasons
        parts += r.parts
    registered = [k for k in range(n) if T_world_cam[k] is not None]
    first = caps[0]
    assert first.reg is not None and first.data is not None
    data = FrameData(frames, store, db, first.mode, first.masks_given, _icp_voxel(opts.config))

    def mask_of(g: int) -> np.ndarray | None:
        c = int(np.searchsorted(offsets, g, side="right")) - 1
        return caps[c].reg.mask_of(g - int(offsets[c]))  # type: ignore[union-attr]

    with timer.stage("fuse", total=1) as advance:
        model, T_obj_world = _fuse(data, T_world_cam, mask_of, first.reg.plane_world, opts.config.fusion,
                                   first.source)
        if opts.append:  # the template's frame is kept: its views' poses stay as they were
            T_obj_world = np.eye(4)
        advance(1)

    cfg = for_capture(opts.config, first.mode)
    problems = {n_: why for cap in caps for n_, why in cap.problems.items()}
    selection = _merged_selection(caps)
    with timer.stage("symmetry", total=1) as advance:  # on the fused mesh, at the cameras' median distance
        dist = np.median([np.linalg.norm((T_obj_world @ T)[:3, 3]) for T in T_world_cam if T is not None])
        symmetries = scan_symmetries(model.mesh.transformed(T_obj_world), model.voxel_size,
                                     first.reg.rparams.depth_noise, float(dist), opts.config.symmetry)
        db.set_meta("symmetries", symmetries.to_json())
        advance(1)

    with timer.stage("database", total=n + 1) as advance, db.batch():
        T_obj_cam = [None if T is None else T_obj_world @ T for T in T_world_cam]
        keyframes, object_source, depth_size, object_counts = _store_views(
            data, T_obj_cam, mask_of, quality, cfg, db, advance, _object_source(caps, opts.config, db, opts.append),
            first.reg.rparams.depth_noise)
        # the keyframes' object keypoints' kind, which the estimator reads: set on every run (an --append that
        # stores image keypoints alone replaces a joint template's)
        db.set_meta("descriptor", JOINT if object_source == "both" else opts.config.features.kind)
        for cap in caps:
            for e in cap.reg.edges:  # type: ignore[union-attr]  # the pose graph's verdicts, also where a
                if e.pruned or (e.src, e.tgt) in cap.reg.restored:  # type: ignore[union-attr]  # resumed run
                    db.add_edge(e)  # reaches another one
        mesh = model.mesh.transformed(T_obj_world)
        db.set_mesh(mesh)
        db.set_cloud(transform_points(T_obj_world, model.points), model.point_colors)
        unregistered = [f.name for f, T in zip(frames, T_world_cam, strict=True) if T is None]
        db.set_meta("mode", first.mode)
        db.set_meta("noise", first.reg.rparams.noise_models())
        db.set_meta("unregistered", unregistered)
        db.set_meta("unregistered_reasons", reasons)
        db.set_meta("parts", parts)
        db.set_meta("skipped", problems)
        db.set_meta("selection", selection.to_meta())
        if opts.append:  # the template's captures as they were recorded, then the new ones
            recorded = template_captures(db) + [_capture_meta(cap, T_obj_world) for cap in caps[1:]]
            db.set_meta("captures", recorded)
            db.set_meta("input", [c["input"] for c in recorded])
        else:
            db.set_meta("captures", [_capture_meta(cap, T_obj_world) for cap in caps] if len(caps) > 1 else [])
            db.set_meta("support_plane", first.reg.plane_world is not None)
        db.set_meta("selection_poses", _selection_poses(caps, T_obj_world))
        db.set_meta("voxel_size", model.voxel_size)
        chosen = None if first.reg.chosen is None else first.reg.chosen.to_json()
        assert first.data is not None
        keypoints = dict(first.data.keypoints, depth_only_edges=sum(
            1 for cap in caps if cap.reg is not None for e in cap.reg.edges if e.accepted and e.depth_only))
        if object_source == "both":  # (a template of the image's keypoints keeps its meta as it was)
            keypoints |= {"object": object_source, "object_depth_size": depth_size}
            if object_counts is not None:  # the keyframes' own image keypoints on the object chose it
                keypoints["object_image_keypoints"] = float(np.median(object_counts))
        if not opts.append:
            db.set_meta("object", chosen)
        db.set_meta("timings_s", timer.timings)
        db.set_meta("keypoints", keypoints)
        # which sides were seen; without a support plane the template frame is the first camera's: up is its -y
        plane = bool(db.get_meta("support_plane")) if opts.append else first.reg.plane_world is not None
        coverage = template_coverage([T for T in T_obj_cam if T is not None], mesh,
                                     up=None if plane else (0.0, -1.0, 0.0))
        db.set_meta("coverage", coverage.to_meta())
        db.mark_complete()
        advance(1)
    stored_edges = db.edges()
    accepted = sum(1 for e in stored_edges if e.accepted)
    total_edges = len(stored_edges)
    return ScanResult(output=output, frames=n + len(selection.skipped) + len(problems),
                      registered=len(registered), unregistered=unregistered + sorted(problems),
                      edges_accepted=accepted, edges_rejected=total_edges - accepted, mode=first.mode,
                      mesh_vertices=len(mesh.vertices), mesh_triangles=len(mesh.triangles),
                      timings_s=dict(timer.timings), problems=problems, keyframes=len(keyframes),
                      unregistered_reasons=reasons | problems, parts=parts, noise=first.reg.rparams.noise,
                      selection=selection.summary(), coverage=coverage.to_json(), symmetries=symmetries,
                      damage=[line for cap in caps if cap.seq is not None for line in cap.seq.damage],
                      captures=_captures_summary(caps, db, opts.append), object=chosen, keypoints=keypoints,
                      motion=next((c.reg.motion for c in caps if c.reg is not None and c.reg.motion), None))


def _captures_summary(caps: list[_Capture], db: TemplateDB, append: bool) -> list[dict]:
    """`scan --json`'s "captures": each capture's summary (`_capture_summary`); after --append the template's
    records first (as its meta holds them); empty for a scan of one capture."""
    if append:
        return [{k: c.get(k) for k in _capture_summary(caps[1])} for c in db.get_meta("captures")]
    return [_capture_summary(cap) for cap in caps] if len(caps) > 1 else []


def _template_capture(db: TemplateDB, store: FrameStore, opts: ScanOptions) -> _Capture:
    """The views of the template appended to (`--append`) as a capture registered in the object frame: their
    images and masks put in the frame store, their poses, qualities and the reasons of the unregistered ones. A
    template of one capture has its views renamed `CAPTURE/FRAME` first, as a scan of several names them."""
    if not db.get_meta("captures"):
        [only] = template_captures(db)
        prefix = f"{only['name']}/"
        db.rename_views(prefix)
        meta = db.meta()
        with db.batch():
            db.set_meta("captures", [only | {"T_obj_world": np.eye(4).tolist()}])
            for key in ("unregistered_reasons", "skipped", "input_frames"):
                db.set_meta(key, {prefix + n: v for n, v in (meta.get(key) or {}).items()})
            db.set_meta("unregistered", [prefix + n for n in meta.get("unregistered") or []])
            db.set_meta("parts", [[prefix + n for n in p] for p in meta.get("parts") or []])
            sel = dict(meta.get("selection") or {})
            db.set_meta("selection", sel | {"frames": {prefix + n: v for n, v in (sel.get("frames") or {}).items()}})
            old = meta.get("selection_poses") or {}
            db.set_meta("selection_poses", {
                "frames": {prefix + n: T for n, T in (old.get("frames") or {}).items()},
                "reference": {prefix + n: prefix + r for n, r in (old.get("reference") or {}).items()},
                "reasons": {prefix + n: why for n, why in (old.get("reasons") or {}).items()}})
    meta = db.meta()
    frames: list[Frame] = []
    T_obj_cam: list[np.ndarray | None] = []
    quality: dict[int, float] = {}
    for k, name in enumerate(db.view_names()):
        v = db.view(name, load_images=True)
        if v.color is None or v.depth is None:
            raise InputError(db.path, f"view {name!r} is stored without its images: captures cannot be appended")
        store.put(name, color=v.color, depth=v.depth, mask=v.mask)
        feats = db.features(name)
        f = Frame(StoredFrame(name, v.intrinsics, None, False), n_keypoints=0 if feats is None else len(feats))
        if feats is not None and v.T_obj_cam is not None:
            f.object_keypoints = _object_keypoints(feats.pixels, v.mask)
        frames.append(f)
        T_obj_cam.append(v.T_obj_cam)
        if v.quality is not None:
            quality[k] = v.quality
    noise = meta.get("noise") or {}
    rparams = for_capture(opts.config, meta.get("mode") or STATIC_OBJECT).registration
    with contextlib.suppress(TypeError, ValueError, KeyError):
        rparams = rparams.with_noise_models(noise)
    names = [f.name for f in frames]

    def mask_of(k: int) -> np.ndarray | None:
        return store.get(names[k], "mask")

    reasons = {n: why for n, why in (meta.get("unregistered_reasons") or {}).items() if n in set(names)}
    # the frames its selection skipped, as recorded (their poses already in the object frame)
    placed_meta = meta.get("selection_poses") or {}
    skipped = {n: (BLURRED if why.startswith("blurred") else LITTLE_MOTION, why)
               for n, why in ((meta.get("selection") or {}).get("frames") or {}).items()}
    selection = Selection(opts.config.selection, kept=names, skipped=skipped,
                          reference=dict(placed_meta.get("reference") or {}))
    placed: dict[str, np.ndarray | str] = {n: np.asarray(T) for n, T in (placed_meta.get("frames") or {}).items()}
    placed |= dict(placed_meta.get("reasons") or {})
    cap = _Capture(CaptureInput("template", db.path), None, "", mode=meta.get("mode") or STATIC_OBJECT,
                   frames=frames, selection=selection, problems=dict(meta.get("skipped") or {}))
    cap.data = FrameData(frames, store, db, cap.mode, False, _icp_voxel(opts.config))
    cap.reg = _Registered(T_obj_cam, mask_of, None, quality, reasons, [list(p) for p in meta.get("parts") or []],
                          [], set(), rparams, placed)
    return cap


def _register_capture(cap: _Capture, opts: ScanOptions, db: TemplateDB, store: FrameStore, resumed: bool,
                      timer: StageTimer, pool: ThreadPoolExecutor) -> None:
    """Features, noise, pairwise registration, pose graph and segmentation of one capture, in its own world."""
    frames, mode = cap.frames, cap.mode
    cfg = for_capture(opts.config, mode)
    data = cap.data = FrameData(frames, store, db, mode, cap.masks_given, _icp_voxel(opts.config), cap.detections)
    assert cap.selection is not None
    log.info("%s%s capture, %d of %d frames kept%s", f"{cap.input.name}: " if cap.prefix else "", mode,
             len(frames), len(frames) + len(cap.selection.skipped), ", masks given" if data.masks_given else "")

    # each stage's writes are batched: one commit per stage, or per COMMIT_ROWS records in a long one
    with timer.stage("features", total=len(frames)) as advance, db.batch():
        _extract(data, cfg.features, cfg.registration.depth_noise, db, resumed, advance)
    if not any(f.n_keypoints for f in frames):  # every frame dark, textureless or without depth: nothing to scan
        raise InputError(cap.source, f"no keypoint with depth in any of the {len(frames)} frames "
                         "(dark or textureless images, or no valid depth)")

    n = len(frames)
    rparams, sparams = cfg.registration, cfg.posegraph
    with timer.stage("noise", total=1) as advance:
        if sparams.estimate_noise:
            kp_noise, depth_noise, ray = capture_noise(data, rparams, sparams.pilot_pairs, pool)
            rparams = replace(rparams, noise=kp_noise, depth_noise=depth_noise, depth_noise_ray=ray)
        advance(1)
    sink = _EdgeRecords(db)
    reg = Registrar(data, rparams, sink, db.edges() if resumed else (), AHEAD, cfg.features.auto_min_keypoints)
    with timer.stage("register", total=max(1, n - 1)) as advance, db.batch():
        edges = register_edges(reg, sparams, pool, advance)
    with timer.stage("posegraph", total=1) as advance:
        res = optimise_sequence(reg, edges, sparams, pool)
        advance(1)

    with timer.stage("segment", total=n) as advance:
        seg = replace(cfg.segmentation, depth_noise=rparams.depth_noise)  # the capture's own
        mask_of, plane_world, chosen = _segment(data, res.T_world_cam, opts.segment, seg, advance, cap.hint)
    cap.reg = _Registered(res.T_world_cam, mask_of, plane_world, res.quality, res.unregistered_reasons, res.parts,
                          res.edges, res.restored, rparams, chosen=chosen, motion=res.motion)
    with timer.stage("place", total=len(cap.skipped)) as advance:
        cap.reg.placed = _place_skipped(cap, cfg.features, rparams, pool, advance)


def _place_skipped(cap: _Capture, fparams: FeatureParams, rparams: RegisterParams, pool: ThreadPoolExecutor,
                   advance: Callable[[int], None]) -> dict[str, np.ndarray | str]:
    """A pose for each frame frame selection skipped: registered (like an edge) to the kept frame it was compared
    with, which moved little from it; name -> T_world_cam, or why it has none (its reference has no pose, or the
    edge was refused). Such frames are not fused and are never keyframes."""
    data, r = cap.data, cap.reg
    assert data is not None and r is not None and cap.selection is not None
    index = {f.name: k for k, f in enumerate(cap.frames)}

    def place(stored: StoredFrame) -> np.ndarray | str:
        ref = cap.selection.reference[stored.name]  # type: ignore[union-attr]
        k = index.get(ref)
        T_world_ref = None if k is None else r.T_world_cam[k]
        if k is None or T_world_ref is None:
            return f"skipped by frame selection; the frame it was compared with ({ref}) has no pose"
        frame = stored.load(data.store)
        mask = data.object_mask(k)  # a moving object's: the reference's (the view moved little)
        b = data.reg(k)
        feats = extract_keypoints(frame, fparams, data.keypoints["source"], rparams.depth_noise.sigma, mask=mask)
        a = RegData.of_frame(feats, frame.depth, frame.color, frame.intrinsics, mask, data.icp_voxel)
        res = register_features(a.feats, b.feats, rparams, clouds=(a.cloud, b.cloud), dense=(a.dense, b.dense))
        if not res.accepted or res.T_tgt_src is None:
            return f"skipped by frame selection; not placed against {ref}: {res.reason}"
        return T_world_ref @ res.T_tgt_src

    out: dict[str, np.ndarray | str] = {}
    for stored, got in zip(cap.skipped, bounded_map(pool, place, cap.skipped, AHEAD), strict=True):
        out[stored.name] = got
        advance(1)
    return out


def _join(caps: list[_Capture], config: ScanConfig, timer: StageTimer, pool: ThreadPoolExecutor) -> None:
    """Joins each capture after the first to those joined before it (`gscan.registration.join`), on the object's
    own keypoints and depth (the object moved against the table between captures)."""
    params = config.join
    # object-only registration (a moving object's settings), with the first capture's noise
    first = caps[0].reg
    assert first is not None
    moving = for_capture(config, MOVING_OBJECT).registration
    rparams = moving.with_noise_models(first.rparams.noise_models())
    oparams = replace(OBJECT_FEATURES, kind=config.features.kind, max_keypoints=config.features.max_keypoints)
    with timer.stage("join", total=len(caps) - 1) as advance:
        joined = _join_views(caps[0], params.views, oparams, _icp_voxel(config), pool)
        for cap in caps[1:]:
            views = _join_views(cap, params.views, oparams, _icp_voxel(config), pool)
            cap.join = join_captures(joined, views, rparams, params, pool)
            if cap.join.T_a_b is not None:
                T = cap.join.T_a_b
                joined += [JoinView(v.name, v.reg, T @ v.T_world_cam) for v in views]
                log.info("capture %s joined to the others (%d of %d view pairs agree)", cap.input.name,
                         len(cap.join.agreeing), cap.join.tried)
            else:
                log.warning("capture %s is not joined to the others: %s", cap.input.name, cap.join.reason)
            advance(1)


def _join_views(cap: _Capture, k: int, oparams: FeatureParams, icp_voxel: float | None,
                pool: ThreadPoolExecutor) -> list[JoinView]:
    """Up to k registered views of a capture, spread over it, with the object in view: keypoints detected in the
    object mask, depth samples and ICP cloud inside it (camera frame), pose in the capture's world."""
    r, data = cap.reg, cap.data
    assert r is not None and data is not None
    reg = [i for i, T in enumerate(r.T_world_cam) if T is not None]

    def view(i: int) -> JoinView | None:
        mask, T = r.mask_of(i), r.T_world_cam[i]
        if mask is None or not mask.any() or T is None:
            return None
        frame = data.frame(i)
        feats = extract_features_in_mask(frame, mask, oparams)
        return JoinView(frame.name, RegData.of_frame(feats, frame.depth, frame.color, frame.intrinsics, mask,
                                                     icp_voxel), T)

    return [v for v in pool.map(view, [reg[j] for j in spread_indices(len(reg), k, nearest=True)]) if v is not None]


def _selection_poses(caps: list[_Capture], T_obj_world: np.ndarray) -> dict:
    """The template's "selection_poses" meta: {"frames": {name: T_obj_cam}, "reference": {name: the kept frame it
    was registered to}, "reasons": {name: why it has no pose}} of the frames frame selection skipped."""
    frames, refs, reasons = {}, {}, {}
    for cap in caps:
        r = cap.reg
        assert r is not None and cap.selection is not None
        T_join = np.eye(4) if cap.join is None else cap.join.T_a_b
        for name, got in r.placed.items():
            if isinstance(got, str):
                reasons[name] = got
            elif T_join is None:
                reasons[name] = f"capture {cap.input.name} was not joined to the others"
            else:
                frames[name] = (T_obj_world @ T_join @ got).tolist()
                refs[name] = cap.selection.reference[name]
    return {"frames": frames, "reference": refs, "reasons": reasons}


def _merged_selection(caps: list[_Capture]) -> Selection:
    out = Selection(caps[0].selection.params)  # type: ignore[union-attr]
    for cap in caps:
        assert cap.selection is not None
        out.kept += cap.selection.kept
        out.skipped |= cap.selection.skipped
        out.reference |= cap.selection.reference
    return out


def _capture_summary(cap: _Capture) -> dict:
    """A capture of a scan of several, in `scan --json`'s "captures"."""
    r = cap.reg
    assert r is not None
    return {"name": cap.input.name, "input": str(cap.source), "mode": cap.mode, "frames": len(cap.frames),
            "registered": sum(T is not None for T in r.T_world_cam),
            "joined": cap.join is None or cap.join.T_a_b is not None,
            "reason": None if cap.join is None else cap.join.reason,
            "joined_at_turn": None if cap.join is None else cap.join.turned,
            "timings_s": {k: round(v, 3) for k, v in cap.timings.items()}}


def _capture_meta(cap: _Capture, T_obj_world: np.ndarray) -> dict:
    """A capture's record in the template's "captures" meta: its summary, the noise its registration used, how it
    was joined and T_obj_world [4 x 4] of its world (None: not joined)."""
    r = cap.reg
    assert r is not None
    T = np.eye(4) if cap.join is None else cap.join.T_a_b
    return _capture_summary(cap) | {
        "noise": r.rparams.noise_models(),
        "join": None if cap.join is None else cap.join.to_meta(),
        "T_obj_world": None if T is None else (T_obj_world @ T).tolist()}


def _fuse(data: FrameData, T_world_cam: list[np.ndarray | None], mask_of: Callable[[int], np.ndarray | None],
          plane_world: Plane | None, params: FusionParams, input_dir: Path) -> tuple[FusedModel, np.ndarray]:
    """(TSDF model in the world frame, T_obj_world [4 x 4] of the template frame); InputError when
    nothing could be fused."""
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


def _choose_keypoints(data: FrameData, fparams: FeatureParams) -> dict[int, Features]:
    """Decide the capture's keypoints (`choose_source`, into data.keypoints); with `keypoints: auto` from the
    image keypoints of the frames spread over it (`pilot_frames`), returned by frame index for the features stage."""
    n = len(data.frames)
    pilot: dict[int, Features] = {}
    if fparams.keypoints == "auto" and fparams.kind == "rootsift" and n:
        for k in pilot_frames(n):
            pilot[k] = extract_features(data.frame(k), fparams, mask=data.object_mask(k),
                                        detection=data.detections.pop(data.frames[k].name, None))
    counts = [len(f) for f in pilot.values()]
    source = choose_source(fparams, counts)
    data.keypoints = {"source": source, "chosen_by": "auto" if fparams.keypoints == "auto" else "config",
                      "median_image_keypoints": float(np.median(counts)) if counts else None}
    log.info("keypoints: %s (%s%s)", source, data.keypoints["chosen_by"],
             f", median {np.median(counts):g} image keypoints in {len(counts)} frames" if counts else "")
    return pilot


def _extract(data: FrameData, fparams: FeatureParams, depth_noise: DepthNoise, db: TemplateDB, resumed: bool,
             advance: Callable[[int], None]) -> None:
    """Each frame's registration keypoints (camera frame; a moving object's only), stored at once with the view's
    images: the one write of those. Which keypoints (the image's, the depth's, both) is decided first
    (`_choose_keypoints`); depth keypoints are scaled by the depth noise `depth_noise`. A resumed scan reuses the
    keypoints of views stored without a pose."""
    frames = data.frames
    stored = set(db.view_names()) if resumed else set()
    db_poses = {v.name: v.T_obj_cam for v in db.views()} if stored else {}
    for name in stored - {f.name for f in frames}:  # a view of a frame this scan does not keep
        db.remove_view(name)
    pilot = _choose_keypoints(data, fparams)
    source = data.keypoints["source"]

    def frame_work(k: int) -> tuple[RGBDFrame | None, Features | None]:
        name = frames[k].name
        if name in stored and db_poses.get(name, 1) is None:
            return None, None  # stored by the interrupted run, still in the camera frame
        frame = data.frame(k)
        mask = data.object_mask(k)
        image = pilot.pop(k, None)
        if image is None or source == "depth":
            return frame, extract_keypoints(frame, fparams, source, depth_noise.sigma, mask=mask,
                                            detection=data.detections.pop(name, None))
        if source == "sift":
            return frame, image
        return frame, joint_features(image, depth_keypoints(frame, depth_noise.sigma, fparams, mask))

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


def _object_source(caps: list[_Capture], config: ScanConfig, db: TemplateDB, append: bool) -> str | None:
    """The keypoints the keyframes keep for estimation, "sift" (the image's) or "both" (the image's and the
    depth's, one rootsift+fpfh set): `keyframes.object_keypoints` unless "auto"; auto: "both" where a capture
    registered with depth keypoints, or, appended to, the template's keyframes hold them; else None: the keyframes'
    own image keypoints on the object decide (`_store_views`: a plain object on a printed table registers on the
    table's keypoints)."""
    chosen = config.keyframes.object_keypoints
    if chosen == "auto":
        stored = db.get_meta("keypoints") if append else None
        depth = any(c.data is not None and c.data.keypoints["source"] in ("depth", "both") for c in caps) or (
            isinstance(stored, dict) and stored.get("object") == "both")
        if not depth:
            return None
        chosen = "both"
    if chosen == "both" and config.features.kind != "rootsift":  # chosen by auto: a configuration asking for
        # "both" is refused when it is read (ScanConfig)
        raise ValueError(f"the template's keyframes hold depth keypoints joined to rootsift ones: an appended "
                         f"capture's features.kind must be rootsift, not {config.features.kind}")
    return chosen


def _depth_size(data: FrameData, keyframes: set[int], mask_of: Callable[[int], np.ndarray | None]) -> float | None:
    """The object's size (m) the keyframes' depth keypoints are found at, and a query's: the median over the
    keyframes of the size registration scales a view's depth keypoints by (`object_size` of its masked points);
    None when no keyframe has a mask with 50 points."""
    def points(k: int) -> np.ndarray:
        m = mask_of(k)
        return point_cloud(data.frame(k), m)[0] if m is not None else np.zeros((0, 3))

    return median_object_size(points(k) for k in sorted(keyframes))


def _store_views(data: FrameData, T_obj_cam: list[np.ndarray | None], mask_of: Callable[[int], np.ndarray | None],
                 quality: dict[int, float], cfg: ScanConfig, db: TemplateDB, advance: Callable[[int], None],
                 source: str | None, depth_noise: DepthNoise
                 ) -> tuple[set[int], str, float | None, list[int] | None]:
    """Completes every view with its pose (its keypoints follow into the object frame), mask, keyframe flag and
    quality; chooses the keyframes and returns their indices, the keypoints they keep on the object ("sift" or
    "both"), the depth keypoints' object size (m; None without depth keypoints) and, where the keyframes decided
    that (`source` None), their image keypoint counts on the object.

    Keyframes also keep keypoints on the object alone, detected inside the object mask with the
    estimator's settings: the template's keypoints for pose estimation (registration keypoints of a
    static object are mostly on the table). `source` "both" (`_object_source`) makes them joint: the image's and
    the depth's (of the capture's `depth_noise`) on the mask's points, all views' at one size (`_depth_size`), the
    one a query's are found at; None lets the keyframes' image keypoints decide as `features.keypoints: auto`
    decides a capture's (`choose_source`: below a median of `features.auto_min_keypoints`, a plain object)."""
    frames = data.frames

    def shows(k: int) -> bool:
        m = mask_of(k)
        return m is None or bool(m.any())

    dirs = keyframe_candidates(T_obj_cam, shows)
    kc = cfg.keyframes
    keyframes = set(select_keyframes(dirs, kc.min_angle_deg, kc.max_views,
                                     {k: frames[k].object_keypoints for k in dirs}, kc.min_object_keypoints,
                                     kc.min_views))
    oparams = replace(OBJECT_FEATURES, kind=cfg.features.kind, max_keypoints=cfg.features.max_keypoints)
    masks = {k: m for k in sorted(keyframes) if T_obj_cam[k] is not None and (m := mask_of(k)) is not None}
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        image = dict(zip(masks, pool.map(lambda k: extract_features_in_mask(data.frame(k), masks[k], oparams), masks),
                         strict=True))
    counts: list[int] | None = None
    chosen = source
    if chosen is None:  # auto, nothing registered on depth keypoints: the keyframes' own count decides
        counts = [len(f) for f in image.values()]
        chosen = choose_source(replace(cfg.features, keypoints="auto"), counts)
        log.info("keyframes' object keypoints: %s (auto, %d keyframes' image keypoints on the object: median %s)",
                 chosen, len(counts), np.median(counts) if counts else None)
    size = _depth_size(data, keyframes, mask_of) if chosen == "both" else None

    def view_work(k: int) -> tuple[np.ndarray | None, Features | None]:
        f = frames[k].stored
        if T_obj_cam[k] is None:  # an unregistered view keeps the mask it came with
            return (data.store.get(f.name, "given_mask") if f.has_mask else None), None
        if k not in image:  # not a keyframe, or one without a mask
            return mask_of(k), None
        m, obj = masks[k], image[k]
        if chosen == "both":
            obj = joint_features(obj, depth_keypoints(data.frame(k), depth_noise.sigma, cfg.features, m, size=size))
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
    return keyframes, chosen, size, counts


def _object_keypoints(pixels: np.ndarray, mask: np.ndarray | None) -> int:
    """Registration keypoints (with depth; their pixels [N x 2]) of a frame that lie in its object mask (all
    without a mask)."""
    if mask is None:
        return len(pixels)
    uv = np.round(pixels).astype(int)
    H, W = mask.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    return int(mask[uv[inside, 1], uv[inside, 0]].sum())


def _first_frame_hint(cap: _Capture, opts: ScanOptions) -> ObjectHint | None:
    """The object the user chose in the capture's first frame (`opts.roi` / `opts.mask`), checked against that
    frame (InputError); None when neither is given."""
    if (opts.roi is None and opts.mask is None) or cap.seq is None or not len(cap.seq.names):
        return None
    first = cap.seq.names[0]
    try:
        frame = cap.seq[first]
    except InputError as e:
        raise InputError(e.path, f"{e.reason} (the first frame, which the object is chosen in)",
                         fix="roi" if opts.roi is not None else "mask") from None
    return object_hint(opts.roi, opts.mask, frame, cap.source)


def _kept_first(cap: _Capture, hint: ObjectHint | None) -> ObjectHint | None:
    """`hint` once the capture is loaded: InputError when its first frame, which the hint is about, was not kept."""
    if hint is None or cap.seq is None:
        return hint
    first = cap.seq.names[0]
    if not cap.frames or cap.frames[0].name != cap.prefix + first:
        skipped = cap.selection.skipped if cap.selection is not None else {}
        why = cap.problems.get(cap.prefix + first) or next(
            (r for n, (_, r) in skipped.items() if n in (first, cap.prefix + first)), "not kept")
        raise InputError(cap.source, f"the first frame {first} is not scanned ({why}), and the object is chosen in it",
                         fix=hint.by)
    return hint


def _segment(data: FrameData, T_world_cam: list[np.ndarray | None], segment: bool, seg: SegmentParams,
             advance: Callable[[int], None], hint: ObjectHint | None = None
             ) -> tuple[Callable[[int], np.ndarray | None], Plane | None, ChosenObject | None]:
    """Per-frame object masks for fusion (a function of the frame index, the masks being in the store), the
    support plane in the world frame (or None) and the object chosen (or None); sets each frame's count of
    keypoints inside its mask. `hint`: the user's choice of the object in frame 0 (its pose: its world).

    The plane defines the template frame's z axis even when masks are given: for a static object
    it comes from the working volume over the registered frames; for a moving object from the
    reference frame alone (a turntable's plane moves with the object; an object in hand has none).
    """
    from gscan.scanning.segment import estimate_working_volume, segment_in_volume

    frames = data.frames
    n = len(frames)
    reg = [k for k, T in enumerate(T_world_cam) if T is not None]
    plane: Plane | None = None
    chosen: ChosenObject | None = None
    if not segment:
        def mask_of(k: int) -> np.ndarray | None:
            return None
    elif data.mode == MOVING_OBJECT:
        if hint is not None:
            log.warning("a moving object's masks come from the background: the %s of the first frame is not used",
                        hint.by)
        ref = frames[reg[0]]
        plane_cam = ref.plane_cam if ref.plane_cam is not None else segment_frame(
            replace(data.frame(reg[0]), mask=None), seg).plane_cam
        T_world_ref = T_world_cam[reg[0]]
        plane = None if plane_cam is None or T_world_ref is None else plane_cam.transformed(T_world_ref)
        mask_of = data.object_mask
    else:  # given masks win
        if hint is not None and (not reg or reg[0] != 0):
            log.warning("the first frame is not registered: the object is chosen from where the views look, not "
                        "from its %s", hint.by)
            hint = None
        vol = estimate_working_volume(LazyList(len(reg), lambda i: data.frame(reg[i])),
                                      [T for T in (T_world_cam[k] for k in reg) if T is not None], seg, hint)
        chosen = None if vol is None else vol.chosen

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
    return mask_of, plane, chosen
