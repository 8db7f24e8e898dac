"""The scan pipeline: an RGB-D folder to registered views, pose graph, fused mesh and template database.

Stages (each timed, each reported through a `Progress`):
  load      read every frame (unusable ones are reported by name and left out)
  mode      static-object vs moving-object (`gscan.scan.capture_mode`); object masks for a static camera
  features  keypoints + descriptors lifted to 3D; whole frame for a static object, object only for a
            moving one; stored at once in the database (camera frame, pose unknown)
  register  pairwise edges: each frame against the previous one, falling back to the next earlier
            ones (`MAX_SKIP` frames in all), then loop closures chosen by view overlap
            and bag-of-words votes; each edge = GMatch -> Kabsch -> guided refinement (-> ICP when
            configured), accepted by the rules of `gscan.registration.pairwise`; stored as it is computed
  posegraph robust global optimisation (open3d, line process) with pruning of inconsistent edges;
            frames not connected to the reference frame stay unregistered and are never fused
  segment   object masks (given, background subtraction, or support plane + working volume)
  fuse      TSDF fusion of the object's depth; template frame (DESIGN.md "Frames of reference")
  database  poses, masks, keyframes and keypoints in the object frame, mesh, cloud; status complete

Resume: the database is `partial` until the last transaction. `--resume` reuses the stored views'
keypoints and every stored edge (the expensive parts) and recomputes the rest, which is
deterministic, so an interrupted scan resumes to the same result as an uninterrupted one.
"""
from __future__ import annotations

import json
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from gscan.io.camera import RGBDFrame, backproject
from gscan.scan.capture_mode import MOVING_OBJECT, STATIC_OBJECT, detect_mode, moving_object_masks, select_keyframes
from gscan.scan.config import ScanConfig
from gscan.errors import InputError
from gscan.features import OBJECT_FEATURES, FeatureParams, Features, extract_features, extract_features_in_mask
from gscan.scan.fuse import FusedModel, FusionParams, fuse_tsdf, template_frame
from gscan.geometry.transforms import transform_points
from gscan.progress import Progress, StageTimer
from gscan.registration.pairwise import RegisterParams, register_features
from gscan.scan.segment import Plane, SegmentParams
from gscan.template.db import Edge, TemplateDB, View, ViewFeatures

log = logging.getLogger(__name__)

MAX_SKIP = 3  # a frame is tried against up to this many preceding frames, its predecessor first, until one is accepted
ICP_VOXEL_STRIDE = 2  # pixel stride of the clouds kept for ICP before voxel downsampling
# eps_f for whole-frame registration (static object) when the config leaves it unset: on rendered
# whole-frame pairs RootSIFT 0.5 is as accurate as the object-only default 0.6 (100 % at every
# threshold from 0.4 to 0.8, BENCHMARKS.md) and 7x faster (85 vs 640 ms a pair: fewer candidates)
WHOLE_FRAME_EPS_F = {"rootsift": 0.5}
QUALITY_RMSE = 0.01  # m: a view whose best accepted edge has this residual gets quality 0
WORKERS = 2  # threads for per-frame and per-edge work (the target machines have 2 cores)
PRUNED = "pruned by the pose graph: "  # reason prefix of edges registration accepted and the pose graph rejected


@dataclass
class ScanOptions:
    input_dir: Path
    output: Path
    fmt: str = "auto"
    intrinsics: Path | None = None
    depth_scale: float | None = None
    mode: str = "auto"
    segment: bool = True
    resume: bool = False
    force: bool = False
    config: ScanConfig = field(default_factory=ScanConfig)
    obj_id: int | None = None  # BOP: the object to scan (its masks, ground truth); None: the first one listed
    color_topic: str | None = None  # recordings: the colour / depth image topics (None: detected)
    depth_topic: str | None = None


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
    problems: dict[str, str]
    keyframes: int = 0

    def to_json(self) -> dict:
        """The `scan --json` object of the CLI contract."""
        return {"output": str(self.output), "frames": self.frames, "registered": self.registered,
                "unregistered": list(self.unregistered),
                "edges": {"accepted": self.edges_accepted, "rejected": self.edges_rejected},
                "mode": self.mode, "mesh": {"vertices": self.mesh_vertices, "triangles": self.mesh_triangles},
                "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
                "skipped": dict(self.problems), "keyframes": self.keyframes}


@dataclass
class _Frame:
    frame: RGBDFrame
    feats: Features | None = None  # camera frame
    cloud: np.ndarray | None = None  # [P x 3] camera-frame points for ICP
    mask: np.ndarray | None = None  # [H x W] bool object mask (given or computed)
    plane_cam: Plane | None = None  # support plane found while computing a moving object's mask


def _register_params(cfg: ScanConfig, mode: str) -> RegisterParams:
    from gscan.matching.gmatch import GMatchParams

    m, r = cfg.match, cfg.registration
    eps_f = m.eps_f
    if eps_f is None and mode == STATIC_OBJECT:
        eps_f = WHOLE_FRAME_EPS_F.get(cfg.features.kind)
    gm = GMatchParams(eps_f=eps_f, eps_c=m.eps_c, eta=m.eta, T=m.T, L=m.L, constraint=m.constraint, order=m.order)
    return RegisterParams(method=m.method, gmatch=gm, min_matches=r.min_matches, verify=r.verify,
                          support_eps_scale=r.support_eps_scale, icp=r.icp,
                          icp_max_dist=r.icp_max_dist, icp_voxel=r.icp_voxel, min_fitness=r.min_fitness,
                          max_rmse=r.max_rmse, max_icp_shift_deg=r.max_icp_shift_deg,
                          max_icp_shift_m=r.max_icp_shift_m)


RESUME_KEYS = ("input", "format", "intrinsics_sha256", "depth_scale_option", "config", "mode_option", "segment",
               "obj_id_option", "topics_option")


def _scan_meta(opts: ScanOptions) -> dict:
    """The database's meta; a resumed scan must agree on every RESUME_KEYS value (what changes its result):
    the layout as detected (`--format auto` and the named layout agree), the --intrinsics file's content."""
    from gscan.io import detect_format

    return {"source": "scan", "input": str(opts.input_dir.resolve()),
            "format": detect_format(opts.input_dir) if opts.fmt == "auto" else opts.fmt,
            "intrinsics_sha256": None if opts.intrinsics is None else _sha256(Path(opts.intrinsics)),
            "depth_scale_option": opts.depth_scale, "config": opts.config.model_dump(), "mode_option": opts.mode,
            "segment": opts.segment, "obj_id_option": opts.obj_id, "descriptor": opts.config.features.kind,
            "topics_option": None if opts.color_topic is None and opts.depth_topic is None else
            [opts.color_topic, opts.depth_topic],
            "units": "m"}


def _sha256(path: Path) -> str:
    import hashlib

    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as e:
        raise InputError(path, f"cannot read the intrinsics file ({e.strerror or e})") from None


def _open_resumed(opts: ScanOptions) -> TemplateDB:
    """The interrupted scan's database; it must come from the same input and configuration."""
    meta = _scan_meta(opts)
    db = TemplateDB.open(opts.output, require_complete=False, writable=True)
    try:
        stored = {k: db.get_meta(k) for k in RESUME_KEYS}
        try:  # settings added to the configuration since the scan started take their defaults
            stored["config"] = json.loads(json.dumps(ScanConfig.model_validate(stored["config"]).model_dump()))
        except (ValueError, TypeError):
            pass  # not a configuration this version reads: it differs
        if stored != {k: json.loads(json.dumps(meta[k])) for k in stored}:
            raise InputError(opts.output, "was written from another input or configuration; use --force to start over")
    except BaseException:
        db.close()
        raise
    return db


def run_scan(opts: ScanOptions, progress: Progress | None = None) -> ScanResult:
    """Run the whole pipeline (see the module docstring). Raises InputError for bad input.

    The output is checked before any frame is read (so a bad output fails on one line); a new database
    is created only once the input holds a usable frame (`--force` keeps the old file until then).
    """
    from gscan.io import check_output_path, missing_folders, open_sequence, remove_empty_folders

    if opts.output.is_dir():
        raise InputError(opts.output, "output is a folder, expected a .gscan file path")
    if opts.output.exists() and not (opts.force or opts.resume):
        raise InputError(opts.output, "exists; pass --force to replace it or --resume to continue it")
    check_output_path(opts.output)
    resumed = opts.resume and opts.output.exists()
    db = _open_resumed(opts) if resumed else None
    timer = StageTimer(progress)
    try:
        seq = open_sequence(opts.input_dir, format=opts.fmt, intrinsics=opts.intrinsics,
                            depth_scale=opts.depth_scale, obj_id=opts.obj_id, color_topic=opts.color_topic,
                            depth_topic=opts.depth_topic)
        if opts.obj_id is not None and seq.format != "bop":
            raise InputError(opts.input_dir, f"--obj-id is for BOP scene folders, this is a {seq.format} folder")
        if opts.obj_id is not None and seq.gt_T_cam_obj is None:
            raise InputError(opts.input_dir / "scene_gt.json", "not found (--obj-id picks an object of its poses)")
        if opts.obj_id is not None and not seq.gt_T_cam_obj:
            raise InputError(opts.input_dir / "scene_gt.json", f"holds no pose of object {opts.obj_id} (--obj-id)")
        frames: list[_Frame] = []
        failed: list[tuple[str, InputError]] = []
        with timer.stage("load", total=len(seq)) as advance:
            for name in seq.names:
                try:
                    frames.append(_Frame(seq[name]))
                except InputError as e:
                    failed.append((name, e))
                advance(1)
        problems = dict(seq.problems)
        if not frames:  # one line (the CLI contract), no per-frame warnings before it
            first = next(iter(problems.items()), ("?", "?"))
            raise InputError(opts.input_dir, f"no usable frame ({len(problems)} unusable); first: {first[0]}: {first[1]}")
    except BaseException:
        if db is not None:
            db.close()
        raise
    for name, e in failed:
        log.warning("skipping frame %s: %s", name, e)

    made = missing_folders(opts.output)
    if db is None:
        # obj_id: the BOP object the scan followed (its ground truth and masks), for `gscan eval`
        db = TemplateDB.create(opts.output, force=opts.force, meta=_scan_meta(opts) | {"obj_id": seq.obj_id})
    try:
        if resumed:  # only once the input is known to hold frames: a complete database stays complete
            db.mark_partial()
        result = _scan_frames(frames, opts, db, resumed, timer, problems)
    except BaseException as e:
        db.close()
        # a failed scan leaves no output behind: neither the file nor folders made for it; Ctrl+C
        # keeps the partial file for --resume (as a killed scan does)
        if not resumed and not isinstance(e, KeyboardInterrupt):
            opts.output.unlink(missing_ok=True)
            remove_empty_folders(made)
        raise
    db.close()
    return result


def _scan_frames(frames: list[_Frame], opts: ScanOptions, db: TemplateDB, resumed: bool, timer: StageTimer,
                 problems: dict[str, str]) -> ScanResult:
    cfg = opts.config
    seg = _segment_params(cfg)
    with timer.stage("mode", total=1) as advance:
        mode, given_masks = _mode_and_masks(frames, opts.mode, seg)
        advance(1)
    db.set_meta("mode", mode)
    log.info("%s capture, %d frames%s", mode, len(frames), ", masks given" if given_masks else "")

    with timer.stage("features", total=len(frames)) as advance:
        _extract(frames, mode, cfg, db, resumed, advance)
    if not any(len(f.feats) for f in frames):  # every frame dark, textureless or without depth: nothing to scan
        raise InputError(opts.input_dir, f"no keypoint with depth in any of the {len(frames)} frames "
                         "(dark or textureless images, or no valid depth)")

    n = len(frames)
    with timer.stage("register", total=max(1, n - 1)) as advance:
        edges, restored = _register_edges(frames, _register_params(cfg, mode), cfg, db, resumed, advance)

    index = {f.frame.name: k for k, f in enumerate(frames)}
    with timer.stage("posegraph", total=1) as advance:
        T_world_cam, quality = _optimise(n, edges, index, frames, cfg)
        advance(1)
    registered = [k for k in range(n) if T_world_cam[k] is not None]
    if not registered:  # the pose graph always leaves a frame registered; a guard, not an expected path
        raise InputError(opts.input_dir, "no frame could be registered")

    with timer.stage("segment", total=1) as advance:
        masks, plane_world = _segment(frames, T_world_cam, mode, opts.segment, seg)
        advance(1)

    with timer.stage("fuse", total=1) as advance:
        model, T_obj_world = _fuse(frames, T_world_cam, masks, plane_world, cfg, opts.input_dir)
        advance(1)

    with timer.stage("database", total=n + 1) as advance:
        T_obj_cam = [None if T is None else T_obj_world @ T for T in T_world_cam]
        keyframes = _store_views(frames, T_obj_cam, masks, quality, cfg, db, advance)
        for e in edges:  # the pose graph's verdicts, also where a resumed run reaches another one
            if (e.reason and e.reason.startswith(PRUNED)) or (e.src, e.tgt) in restored:
                db.add_edge(e)
        V = transform_points(T_obj_world, model.vertices)
        db.set_mesh(V, model.triangles, model.vertex_colors)
        db.set_cloud(transform_points(T_obj_world, model.points), model.point_colors)
        unregistered = [f.frame.name for f, T in zip(frames, T_world_cam) if T is None]
        db.set_meta("unregistered", unregistered)
        db.set_meta("skipped", problems)
        db.set_meta("voxel_size", model.voxel_size)
        db.set_meta("support_plane", plane_world is not None)
        db.set_meta("timings_s", timer.timings)
        db.mark_complete()
        advance(1)
    stored_edges = db.edges()
    accepted = sum(1 for e in stored_edges if e.accepted)
    total_edges = len(stored_edges)
    return ScanResult(opts.output, len(frames) + len(problems), len(registered), unregistered + sorted(problems),
                      accepted, total_edges - accepted, mode, len(V), len(model.triangles), dict(timer.timings),
                      problems, len(keyframes))


def _fuse(frames: list[_Frame], T_world_cam: list[np.ndarray | None], masks: list[np.ndarray | None],
          plane_world: Plane | None, cfg: ScanConfig, input_dir: Path) -> tuple[FusedModel, np.ndarray]:
    """(TSDF model in the world frame, T_obj_world [4 x 4] of the template frame); InputError when
    nothing could be fused."""
    params = FusionParams(voxel_size=cfg.fusion.voxel, depth_max=cfg.fusion.depth_max)
    try:
        model = fuse_tsdf([f.frame for f in frames], T_world_cam, masks, params)
    except ValueError as e:  # no registered frame has object depth within fusion.depth_max
        raise InputError(input_dir, f"nothing could be fused: {e} (fusion.depth_max); check --depth-scale") from None
    registered = [k for k, T in enumerate(T_world_cam) if T is not None]
    if len(model.triangles) == 0 or len(model.vertices) < 3:
        raise InputError(input_dir, "nothing could be fused: no surface in the object depth of the "
                         f"{len(registered)} registered frame(s)")
    obj_pts = model.points if len(model.points) >= 3 else model.vertices
    return model, template_frame(obj_pts, plane_world, T_world_cam[registered[0]])


def _segment_params(cfg: ScanConfig) -> SegmentParams:
    s = cfg.segmentation
    return SegmentParams(depth_min=s.depth_min, depth_max=s.depth_max, height_max=s.height_max)


def _mode_and_masks(frames: list[_Frame], mode_option: str, seg: SegmentParams) -> tuple[str, bool]:
    """(capture mode, whether every frame came with a mask); sets each frame's object mask: the given
    one, or for a moving object one from background subtraction."""
    mode = detect_mode([f.frame for f in frames]).mode if mode_option == "auto" else mode_option
    given_masks = all(f.frame.mask is not None for f in frames)
    if given_masks:
        for f in frames:
            f.mask = f.frame.mask
    elif mode == MOVING_OBJECT:
        masks, planes = moving_object_masks([f.frame for f in frames], params=seg)
        for f, m, p in zip(frames, masks, planes):
            f.mask, f.plane_cam = m, p
    return mode, given_masks


def _extract(frames: list[_Frame], mode: str, cfg: ScanConfig, db: TemplateDB, resumed: bool,
             advance: Callable[[int], None]) -> None:
    """Sets each frame's registration keypoints (camera frame) and ICP cloud, and stores the keypoints
    at once; a resumed scan reuses the keypoints of views stored without a pose."""
    fparams = FeatureParams(kind=cfg.features.kind, max_keypoints=cfg.features.max_keypoints)
    stored = set(db.view_names()) if resumed else set()
    db_poses = {v.name: v.T_obj_cam for v in db.views()} if stored else {}

    def frame_work(k: int) -> tuple[Features | None, np.ndarray]:
        f = frames[k]
        reg_mask = f.mask if mode == MOVING_OBJECT else None
        reuse = f.frame.name in stored and db_poses.get(f.frame.name, 1) is None
        feats = None if reuse else extract_features(f.frame, fparams, mask=reg_mask)
        return feats, _icp_cloud(f.frame, reg_mask, cfg.registration.icp_voxel) if cfg.registration.icp else None

    # OpenCV and open3d release the GIL: two threads use both cores; results are per frame
    # and written in input order, so the output does not depend on the scheduling
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        for k, (feats, cloud) in enumerate(pool.map(frame_work, range(len(frames)))):
            f = frames[k]
            f.cloud = cloud
            if feats is None:  # stored by the interrupted run, still in the camera frame
                vf = db.features(f.frame.name)
                feats = Features(vf.pixels, vf.points_obj, vf.descriptors, vf.kind,
                                 vf.scales if vf.scales is not None else np.ones(len(vf.pixels), np.float32))
            else:
                view = View(f.frame.name, f.frame.intrinsics, None, f.frame.color, f.frame.depth, f.frame.mask,
                            keyframe=False, input_index=k)
                db.add_view(view, ViewFeatures(feats.pixels, feats.points, feats.descriptors, feats.kind,
                                               feats.scales), replace=f.frame.name in stored)
            f.feats = feats
            advance(1)


def _register_edges(frames: list[_Frame], rparams: RegisterParams, cfg: ScanConfig, db: TemplateDB, resumed: bool,
                    advance: Callable[[int], None]) -> tuple[list[Edge], set[tuple[str, str]]]:
    """Sequential edges (with fall-back to earlier frames), then loop closures; each stored as computed.

    Returns the edges in order and the stored edges a resumed scan accepted again (pruned by the
    interrupted run's pose graph, left for this run's pose graph to judge)."""
    from gscan.registration.posegraph import GraphEdge, LoopParams, select_loop_candidates, spanning_poses

    names = [f.frame.name for f in frames]
    done = {(e.src, e.tgt): e for e in db.edges()} if resumed else {}
    restored: set[tuple[str, str]] = set()

    def pair_work(pair: tuple[int, int]):
        i, j = pair
        if (names[i], names[j]) in done:
            return None
        return register_features(frames[i].feats, frames[j].feats, rparams, clouds=(frames[i].cloud, frames[j].cloud))

    def register_all(pairs: list[tuple[int, int]], kind: str, pool: ThreadPoolExecutor) -> list[Edge]:
        """Edges of `pairs`, computed on the pool (numba and OpenCV release the GIL), stored in order."""
        out = []
        for (i, j), r in zip(pairs, pool.map(pair_work, pairs)):
            if r is None:  # stored by the interrupted run
                e = done[(names[i], names[j])]
                if e.reason and e.reason.startswith(PRUNED):  # restore the registration verdict
                    e.accepted, e.reason = True, None
                    restored.add((e.src, e.tgt))
            else:
                # the edge keeps the correspondences its pose was solved from (GMatch's list grown by
                # the guided refinement of gscan.registration.pairwise), which also weigh it in the pose graph
                used = r.inliers if r.inliers is not None and len(r.inliers) else r.matches
                e = Edge(names[i], names[j], r.T_tgt_src, used, r.cost, r.rmse, r.fitness, kind, r.accepted, r.reason)
                db.add_edge(e)
            out.append(e)
        return out

    n = len(frames)
    index = {nm: k for k, nm in enumerate(names)}
    edges: list[Edge] = []
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        # each frame against its predecessor; a frame that fails is tried against earlier ones
        for e in register_all([(j - 1, j) for j in range(1, n)], "sequential", pool):
            edges.append(e)
            j = index[e.tgt]
            for i in range(j - 2, max(-1, j - 1 - MAX_SKIP), -1):
                if edges[-1].accepted:
                    break
                edges += register_all([(i, j)], "sequential", pool)
            advance(1)

        seq_graph = [GraphEdge(index[e.src], index[e.tgt], e.T_tgt_src) for e in edges if e.accepted]
        T_init = spanning_poses(n, seq_graph)
        existing = [(index[e.src], index[e.tgt]) for e in edges]
        lp = LoopParams(max_per_node=cfg.posegraph.loop_candidates, max_angle_deg=cfg.posegraph.max_view_angle_deg)
        # frames without any keypoint (textureless, dark) take no part: bag-of-words needs descriptors
        kp = [k for k in range(n) if len(frames[k].feats.descriptors)]
        sub = {k: s for s, k in enumerate(kp)}
        cands = [] if len(kp) < 2 else select_loop_candidates(
            [T_init[k] for k in kp], [frames[k].feats.descriptors for k in kp],
            [(sub[a], sub[b]) for a, b in existing if a in sub and b in sub], lp)
        edges += register_all([(kp[c.i], kp[c.j]) for c in cands], "loop", pool)
    return edges, restored


def _store_views(frames: list[_Frame], T_obj_cam: list[np.ndarray | None], masks: list[np.ndarray | None],
                 quality: dict[int, float], cfg: ScanConfig, db: TemplateDB,
                 advance: Callable[[int], None]) -> set[int]:
    """Writes every view with its pose, mask and keypoints in the object frame; chooses the keyframes
    and returns their indices.

    Keyframes also keep keypoints on the object alone, detected inside the object mask with the
    estimator's settings: the template's keypoints for pose estimation (registration keypoints of a
    static object are mostly on the table)."""
    dirs = {k: T[:3, 2] for k, T in enumerate(T_obj_cam) if T is not None}
    keyframes = set(select_keyframes(dirs, cfg.keyframes.min_angle_deg, cfg.keyframes.max_views))
    oparams = replace(OBJECT_FEATURES, kind=cfg.features.kind, max_keypoints=cfg.features.max_keypoints)

    def object_feats(k: int) -> Features | None:
        m = masks[k]
        return extract_features_in_mask(frames[k].frame, m, oparams) if k in keyframes and m is not None else None

    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        for k, obj in enumerate(pool.map(object_feats, range(len(frames)))):
            f, T = frames[k], T_obj_cam[k]
            pts = f.feats.points if T is None else transform_points(T, f.feats.points).astype(np.float32)
            view = View(f.frame.name, f.frame.intrinsics, T, f.frame.color, f.frame.depth,
                        masks[k] if T is not None else f.frame.mask, keyframe=k in keyframes,
                        quality=quality.get(k), input_index=k)
            db.add_view(view, ViewFeatures(f.feats.pixels, pts, f.feats.descriptors, f.feats.kind,
                                           f.feats.scales), replace=True)
            if obj is not None:
                db.add_features(f.frame.name, ViewFeatures(obj.pixels, transform_points(T, obj.points).astype(
                    np.float32), obj.descriptors, obj.kind, obj.scales), role="object")
            advance(1)
    return keyframes


def _icp_cloud(frame: RGBDFrame, mask: np.ndarray | None, voxel: float) -> np.ndarray:
    """[P x 3] camera-frame points for ICP: valid depth (inside `mask`), pixel stride, voxel grid."""
    import open3d as o3d

    s = ICP_VOXEL_STRIDE
    valid = frame.depth > 0
    if mask is not None:
        valid &= mask
    pts = backproject(frame.depth, frame.intrinsics)[::s, ::s][valid[::s, ::s]]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    if voxel > 0:
        pc = pc.voxel_down_sample(voxel)
    return np.asarray(pc.points)


def _optimise(n: int, edges: list[Edge], index: dict[str, int], frames: list[_Frame],
              cfg: ScanConfig) -> tuple[list[np.ndarray | None], dict[int, float]]:
    """Pose graph over accepted edges -> (T_world_cam per frame or None, quality in [0, 1] per frame)."""
    from gscan.registration.posegraph import (GraphEdge, PoseGraphParams, information_from_points, optimize_pose_graph,
                                 spanning_poses)

    use = [e for e in edges if e.accepted and e.T_tgt_src is not None]
    graph = []
    for e in use:
        i, j = index[e.src], index[e.tgt]
        pts_t = frames[j].feats.points[e.matches[:, 1]]  # accepted edges have >= min_matches matches
        # loop closures and weakly supported edges may be switched off by the line process: a
        # repetitive or symmetric texture can give a consistent but wrong list of L matches, which
        # then explains few other candidates (measured: wrong edges 27-40, right ones 63-700)
        doubtful = e.kind == "loop" or len(e.matches) < cfg.posegraph.certain_min_inliers
        graph.append(GraphEdge(i, j, e.T_tgt_src, information_from_points(pts_t), uncertain=doubtful))
    T0 = spanning_poses(n, graph, [len(e.matches) for e in use])
    ref = next((k for k in range(n) if T0[k] is not None), 0)  # the first frame with an edge
    params = PoseGraphParams(max_residual_deg=cfg.posegraph.prune_rot_deg,
                             max_residual_m=cfg.posegraph.prune_trans_m,
                             max_correspondence_distance=cfg.registration.icp_max_dist)
    res = optimize_pose_graph(n, graph, T0, params, reference_node=ref)
    best_rmse: dict[int, float] = {}
    for rep, e in zip(res.edges, use):
        # the pose graph's verdict joins the registration's: pruned edges are recorded as rejected
        if not rep.accepted:
            e.accepted = False
            e.reason = PRUNED + str(rep.reason)
        for k in (rep.src, rep.tgt):
            if rep.accepted and e.rmse is not None:
                best_rmse[k] = min(best_rmse.get(k, np.inf), float(e.rmse))
    # registration quality of a view in [0, 1] (1 = perfect): 1 - RMSE / QUALITY_RMSE of its best edge
    quality = {k: float(np.clip(1.0 - r / QUALITY_RMSE, 0.0, 1.0)) for k, r in best_rmse.items()}
    return res.T_world_node, quality


def _segment(frames: list[_Frame], T_world_cam: list[np.ndarray | None], mode: str, segment: bool,
             seg: SegmentParams) -> tuple[list[np.ndarray | None], Plane | None]:
    """Per-frame object masks for fusion and the support plane in the world frame (or None).

    The plane defines the template frame's z axis even when masks are given: for a static object
    it comes from the working volume over the registered frames; for a moving object from the
    reference frame alone (a turntable's plane moves with the object; an object in hand has none).
    """
    from gscan.scan.segment import segment_frame, segment_sequence

    if not segment:
        return [None] * len(frames), None
    reg = [k for k, T in enumerate(T_world_cam) if T is not None]
    if mode == MOVING_OBJECT:
        ref = frames[reg[0]]
        plane_cam = ref.plane_cam if ref.plane_cam is not None else segment_frame(
            RGBDFrame(ref.frame.name, ref.frame.color, ref.frame.depth, ref.frame.intrinsics), seg).plane_cam
        plane = None if plane_cam is None else plane_cam.transformed(T_world_cam[reg[0]])
        return [f.mask for f in frames], plane
    segs, vol = segment_sequence([f.frame for f in frames], T_world_cam, seg)  # given masks win
    return [s.mask for s in segs], (vol.plane_world if vol is not None else None)
