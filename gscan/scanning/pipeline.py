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
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

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
from gscan.geometry.plane import Plane
from gscan.geometry.symmetry import Symmetries
from gscan.geometry.transforms import transform_points
from gscan.io.camera import RGBDFrame
from gscan.io.output import (
    Output,
    check_output,
    file_identity,
    missing_folders,
    remove_empty_folders,
    remove_sqlite_sidecars,
)
from gscan.progress import Progress, StageTimer
from gscan.registration.edges import COMMIT_ROWS, EdgeSink, Registrar, bounded_map
from gscan.registration.noise import DepthNoise
from gscan.registration.sequence import capture_noise, optimise_sequence, register_edges
from gscan.scanning.camera import check_camera
from gscan.scanning.capture_mode import MOVING_OBJECT
from gscan.scanning.config import ScanConfig, for_capture
from gscan.scanning.frames import WORKERS, FrameData, detect_capture_mode, load_frames
from gscan.scanning.fuse import FusedModel, FusionParams, fuse_tsdf, template_frame
from gscan.scanning.keyframes import keyframe_candidates, select_keyframes
from gscan.scanning.options import ScanOptions
from gscan.scanning.output import create_output, open_resumed, scan_meta
from gscan.scanning.segment import SegmentParams, segment_frame
from gscan.scanning.select import Selection
from gscan.scanning.store import FrameStore, LazyList
from gscan.scanning.symmetry import scan_symmetries
from gscan.template.db import Edge, TemplateDB, View

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
    # the colour camera's check (`check_camera`): given and used focal lengths, texture agreement; None: not run
    camera: dict | None = None
    symmetries: Symmetries = field(default_factory=Symmetries)  # the object's (object frame)

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
                "camera": self.camera, "symmetries": self.symmetries.to_json()}


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
                            depth_topic=opts.depth_topic, depth_camera=opts.depth_camera)
        if opts.obj_id is not None and seq.format != "bop":
            raise InputError(source, f"an object id is for BOP scene folders, this is a {seq.format} folder")
        if opts.obj_id is not None and seq.gt_T_cam_obj is None:
            raise InputError(source / "scene_gt.json", "not found (the object id picks an object of its "
                             "poses)", fix="obj_id")
        if opts.obj_id is not None and not seq.gt_T_cam_obj:
            raise InputError(source / "scene_gt.json", f"holds no pose of object {opts.obj_id}", fix="obj_id")
        fingerprints = seq.fingerprints()
        if resumed:
            db, target = open_resumed(source, output, opts, seq, fingerprints)
        detections: dict[str, Detection] = {}
        with timer.stage("camera", total=1) as advance:  # (after the checks that refuse the input in one line)
            seq, camera = check_camera(source, seq, opts, detections)
            advance(1)
        store = FrameStore(output)
        with timer.stage("mode", total=1) as advance:
            mode, masks_given = detect_capture_mode(seq, opts.mode)
            advance(1)
        with timer.stage("load", total=len(seq)) as advance:
            frames, failed, selection = load_frames(seq, mode, masks_given, opts.config.selection,
                                                   opts.config.segmentation, store, advance)
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
            db, target = create_output(output, opts, dict(opts.meta) | scan_meta(source, opts) | {
                "obj_id": seq.obj_id, "input_frames": fingerprints, "camera": camera})
        created = file_identity(output)  # a new output in place: only this file is removed on failure
        if resumed:  # only once the input is known to hold frames: a complete database stays complete
            db.mark_partial()
        data = FrameData(frames, store, db, mode, masks_given, _icp_voxel(opts.config), detections)
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


# ------------------------------------------------------------------------------------------ the stages
def _scan_frames(data: FrameData, source: Path, output: Path, opts: ScanOptions, db: TemplateDB, resumed: bool,
                 timer: StageTimer, problems: dict[str, str], selection: Selection) -> ScanResult:
    frames, mode = data.frames, data.mode
    cfg = for_capture(opts.config, mode)
    log.info("%s capture, %d of %d frames kept%s", mode, len(frames), len(frames) + len(selection.skipped),
             ", masks given" if data.masks_given else "")

    # each stage's writes are batched: one commit per stage, or per COMMIT_ROWS records in a long one
    with timer.stage("features", total=len(frames)) as advance, db.batch():
        db.set_meta("mode", mode)
        db.set_meta("selection", selection.to_meta())
        _extract(data, cfg.features, db, resumed, advance)
    if not any(f.n_keypoints for f in frames):  # every frame dark, textureless or without depth: nothing to scan
        raise InputError(source, f"no keypoint with depth in any of the {len(frames)} frames "
                         "(dark or textureless images, or no valid depth)")

    n = len(frames)
    rparams, sparams = cfg.registration, cfg.posegraph
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        with timer.stage("noise", total=1) as advance, db.batch():
            if sparams.estimate_noise:
                kp_noise, depth_noise = capture_noise(data, rparams, sparams.pilot_pairs, pool)
                rparams = replace(rparams, noise=kp_noise, depth_noise=depth_noise)
            db.set_meta("noise", {"keypoint": rparams.noise.to_dict(), "depth": rparams.depth_noise.to_dict()})
            advance(1)
        sink = _EdgeRecords(db)
        reg = Registrar(data, rparams, sink, db.edges() if resumed else (), AHEAD)
        with timer.stage("register", total=max(1, n - 1)) as advance, db.batch():
            edges = register_edges(reg, sparams, pool, advance)
        with timer.stage("posegraph", total=1) as advance:
            res = optimise_sequence(reg, edges, sparams, pool)
            advance(1)
    edges, T_world_cam, quality = res.edges, res.T_world_cam, res.quality
    registered = [k for k in range(n) if T_world_cam[k] is not None]
    reasons, parts = res.unregistered_reasons, res.parts

    with timer.stage("segment", total=n) as advance:
        seg = replace(cfg.segmentation, depth_noise=rparams.depth_noise)  # the capture's own
        mask_of, plane_world = _segment(data, T_world_cam, opts.segment, seg, advance)

    with timer.stage("fuse", total=1) as advance:
        model, T_obj_world = _fuse(data, T_world_cam, mask_of, plane_world, cfg.fusion, source)
        advance(1)

    with timer.stage("symmetry", total=1) as advance:  # on the fused mesh, at the cameras' median distance
        dist = np.median([np.linalg.norm((T_obj_world @ T)[:3, 3]) for T in T_world_cam if T is not None])
        symmetries = scan_symmetries(model.mesh.transformed(T_obj_world), model.voxel_size, rparams.depth_noise,
                                     float(dist), cfg.symmetry)
        db.set_meta("symmetries", symmetries.to_json())
        advance(1)

    with timer.stage("database", total=n + 1) as advance, db.batch():
        T_obj_cam = [None if T is None else T_obj_world @ T for T in T_world_cam]
        keyframes = _store_views(data, T_obj_cam, mask_of, quality, cfg, db, advance)
        for e in edges:  # the pose graph's verdicts, also where a resumed run reaches another one
            if e.pruned or (e.src, e.tgt) in res.restored:
                db.add_edge(e)
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
                      selection=selection.summary(), symmetries=symmetries)


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


def _extract(data: FrameData, fparams: FeatureParams, db: TemplateDB, resumed: bool,
             advance: Callable[[int], None]) -> None:
    """Each frame's registration keypoints (camera frame; a moving object's only), stored at once with the view's
    images: the one write of those. A resumed scan reuses the keypoints of views stored without a pose."""
    frames = data.frames
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


def _store_views(data: FrameData, T_obj_cam: list[np.ndarray | None], mask_of: Callable[[int], np.ndarray | None],
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

    dirs = keyframe_candidates(T_obj_cam, shows)
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


def _object_keypoints(pixels: np.ndarray, mask: np.ndarray | None) -> int:
    """Registration keypoints (with depth; their pixels [N x 2]) of a frame that lie in its object mask (all
    without a mask)."""
    if mask is None:
        return len(pixels)
    uv = np.round(pixels).astype(int)
    H, W = mask.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    return int(mask[uv[inside, 1], uv[inside, 0]].sum())


def _segment(data: FrameData, T_world_cam: list[np.ndarray | None], segment: bool, seg: SegmentParams,
             advance: Callable[[int], None]) -> tuple[Callable[[int], np.ndarray | None], Plane | None]:
    """Per-frame object masks for fusion (a function of the frame index, the masks being in the store) and the
    support plane in the world frame (or None); sets each frame's count of keypoints inside its mask.

    The plane defines the template frame's z axis even when masks are given: for a static object
    it comes from the working volume over the registered frames; for a moving object from the
    reference frame alone (a turntable's plane moves with the object; an object in hand has none).
    """
    from gscan.scanning.segment import estimate_working_volume, segment_in_volume

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
