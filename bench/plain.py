"""Plain objects: pairwise registration on image keypoints (SIFT), depth keypoints (ISS + FPFH) or both.

Each object is a shared mesh with its texture replaced by its mean colour, rendered on a plain table as a
turntable capture (36 frames, 10 deg apart; the renderer's object masks, as a moving-object scan segments
them). Every consecutive pair is registered by `gscan.registration.pairwise.register_features` with the depth
samples (rule 3), once per keypoint source. A pair is registered when accepted, wrong when accepted beyond
5 deg or 2 cm (at the object's centre) of the truth. Time: keypoints + registration per pair, as a ratio to
SIFT-only in the same run.

Split: the depth-alone thresholds (`RegisterParams.max_see_through_shape`, `max_outside_shape`) and
FPFH_EPS_F were set on TUNE; HELD_OUT was not looked at before.

With --scans, whole scans instead (`scan_object`): registered / wrong frames and ATE per object on sift, depth
and both, beside the peers on the object's masked depth (`scan_peers`: bench/peers.py's FPFH + RANSAC + ICP chain and
OpenCV's point-pair features + ICP chain); time per frame as a ratio to sift's scan.

With --residuals, how well each kind of keypoint is located (`residuals`): on `both` keypoints, the distances at
the true pose of the inlier pairs of the accepted consecutive pairs, and of the true pairs (mutual nearest
keypoints of a kind within 2 cm under the truth), in units of the sensor's s and of s with the keypoints' location
sigma (`Features.location_sigma`).

With --estimate, pose estimation in clutter (`estimates`): each object's templates scanned on sift, depth and both
(the last two estimated with the query's depth keypoints, `query.depth_keypoints`), and the two peers with the both
template's mesh as their model (`PeerEstimator`), in `--scenes` cluttered scenes with the object and `--negatives`
without it (`estimate_scenes`). The estimator's rules for a pose the depth alone decides (the local support of
depth keypoints, the silhouettes with a margin of two template samples, the keyframes' texture) were set on TUNE's
scenes; HELD_OUT's were run once after. With --lookalikes N, a plain CAD box beside boxes of about its size
(`lookalikes`), the case that decides when a pose the depth alone decided may be taken (`query.depth_keypoints`).

The PPF peer runs OpenCV's contrib module in a child process (bench/ppf_child.py); without it the benchmark says
so and runs the others. Install it beside the venv (the same OpenCV version):

    .venv/bin/python -m pip install --no-deps --target .venv/opencv-contrib opencv-contrib-python-headless==VERSION

    python bench/plain.py [--objects NAME ...] [--frames 36] [--scans [--work DIR] | --residuals]
    python bench/plain.py --estimate [--scenes 8] [--negatives 3] [--work DIR]
    python bench/plain.py --lookalikes 8
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from gscan.features import FeatureParams
from gscan.features.depth import extract_keypoints
from gscan.geometry.transforms import inv_T, pose_error, transform_points
from gscan.io.camera import RGBDFrame
from gscan.registration.dense import DenseGeometry
from gscan.registration.noise import DepthNoise
from gscan.registration.pairwise import RegisterParams, register_features
from gscan.synth.capture import render_capture
from gscan.synth.mesh import TexturedMesh, load_textured_mesh, plain_mesh

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/'s modules: peers, scan, recall

MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data") / "meshes"
TUNE = ["ReadytoUse_Rolled_Fondant_Pure_White_24_oz_box"]
HELD_OUT = ["Crayola_Bonus_64_Crayons", "Nestle_Raisinets_Milk_Chocolate_35_oz_992_g",
            "Pepsi_Caffeine_Free_Diet_12_CT"]
SOURCES = ("sift", "depth", "both")
PEER_DEPTH_MAX = 2.0  # m: the peers' working range (the scenes lie within 1.2 m)
PEER_TABLE_DIST = 0.01  # m: points this near the scene's dominant plane are the table's (peers' estimation)


def plain(name: str) -> TexturedMesh:
    """The shared mesh `name` with its texture replaced by its mean colour."""
    return plain_mesh(load_textured_mesh(MESHES / name / "model_0.obj"))


def run(name: str, n: int) -> dict[str, dict[str, float]]:
    """source -> {"pairs", "registered", "wrong", "s_per_pair"} on one object's capture."""
    frames = render_capture(plain(name), None, n, mode="turntable", seed=0, table_kind="plain")
    rgbd = [RGBDFrame(f"{k:06d}", f.color, f.depth, f.intrinsics) for k, f in enumerate(frames)]
    dense = [DenseGeometry.from_depth(f.depth, f.intrinsics, f.mask, image=f.color) for f in frames]
    noise, fp, params = DepthNoise(), FeatureParams(), RegisterParams(dense_refine=True)
    out = {}
    for source in SOURCES:
        t0 = time.perf_counter()
        feats = [extract_keypoints(r, fp, source, noise.sigma, mask=f.mask) for r, f in zip(rgbd, frames, strict=True)]
        ok = wrong = 0
        for k in range(1, n):
            r = register_features(feats[k - 1], feats[k], params, dense=(dense[k - 1], dense[k]))
            if not r.accepted or r.T_tgt_src is None:
                continue
            gt = frames[k].T_cam_obj @ inv_T(frames[k - 1].T_cam_obj)
            c = frames[k - 1].T_cam_obj[:3, 3][None]
            moved = float(np.linalg.norm(transform_points(r.T_tgt_src, c) - transform_points(gt, c)))
            if pose_error(r.T_tgt_src, gt)[0] > 5.0 or moved > 0.02:
                wrong += 1
            else:
                ok += 1
        out[source] = {"pairs": n - 1, "registered": ok + wrong, "wrong": wrong,
                       "s_per_pair": (time.perf_counter() - t0) / (n - 1)}
    return out


def residuals(name: str, n: int) -> None:
    """Print, per keypoint kind, the median distance at the true pose in s (sensor only / with location sigma) of
    the accepted consecutive pairs' inliers and of the true pairs (module docstring) of one object's capture."""
    from scipy.spatial import cKDTree

    frames = render_capture(plain(name), None, n, mode="turntable", seed=0, table_kind="plain")
    dense = [DenseGeometry.from_depth(f.depth, f.intrinsics, f.mask, image=f.color) for f in frames]
    noise, fp, params = DepthNoise(), FeatureParams(), RegisterParams(dense_refine=True)
    feats = [extract_keypoints(RGBDFrame(f"{k:06d}", f.color, f.depth, f.intrinsics), fp, "both", noise.sigma,
                               mask=f.mask) for k, f in enumerate(frames)]
    got: dict[tuple[str, bool], list[np.ndarray]] = {}
    for k in range(1, n):
        a, b = feats[k - 1], feats[k]
        gt = frames[k].T_cam_obj @ inv_T(frames[k - 1].T_cam_obj)
        q, p = transform_points(gt, a.points.astype(np.float64)), b.points.astype(np.float64)
        j = cKDTree(p).query(q)[1]
        i = cKDTree(q).query(p)[1]
        true = np.flatnonzero((i[j] == np.arange(len(q))) & (a.from_depth == b.from_depth[j])
                              & (np.linalg.norm(q - p[j], axis=1) < 0.02))
        sets = {"true pairs": np.stack([true, j[true]], 1)}
        r = register_features(a, b, params, dense=(dense[k - 1], dense[k]))
        if r.accepted and r.inliers is not None:
            sets["accepted inliers"] = r.inliers
        for what, m in sets.items():
            d = np.linalg.norm(q[m[:, 0]] - p[m[:, 1]], axis=1)
            s0 = noise.pair_sigma(q[m[:, 0], 2], p[m[:, 1], 2])
            s1 = noise.pair_sigma(q[m[:, 0], 2], p[m[:, 1], 2],
                                  np.hypot(a.location_sigma[m[:, 0]], b.location_sigma[m[:, 1]]))
            for depth in (False, True):
                keep = a.from_depth[m[:, 0]] == depth
                got.setdefault((what, depth), []).append(np.stack([d[keep] / s0[keep], d[keep] / s1[keep]], 1))
    for (what, depth), parts in sorted(got.items()):
        x = np.concatenate(parts)
        print(f"{name[:40]:40s} {what:16s} {'depth' if depth else 'image'} keypoints: {len(x)} pairs, median "
              f"{np.median(x[:, 0]):.2f} s (sensor), {np.median(x[:, 1]):.2f} s (with location sigma); a chi "
              f"distribution of 3 axes: 1.54", flush=True)


def scan_object(name: str, n: int, keypoints: str, work: Path) -> dict:
    """A whole scan (`gscan.scanning.api.scan`, the defaults but `features.keypoints`, and on `sift` the keyframes'
    keypoints) of one object's capture, scored by bench/scan.py's `score` ("registered", "wrong": beyond 5 deg / 2 cm of
    the truth relative to the other registered frames, "ate_rmse"), with "turn_refused" (loop closures refused as the
    object's half turn) and "s_per_frame" (wall time)."""
    from scan import gt_T_world_cam, score

    from gscan.registration.edges import LOOP_TURN
    from gscan.scanning.api import scan
    from gscan.scanning.config import ScanConfig
    from gscan.scanning.keyframes import KeyframeParams
    from gscan.template.db import TemplateDB

    cap = capture(name, n, work)
    out = work / f"{name}_{n}_{keypoints}.gscan"
    t0 = time.perf_counter()
    # `sift`: the image's keypoints alone, also on the keyframes (auto would add the plain object's depth keypoints)
    keyframes = KeyframeParams(object_keypoints="sift" if keypoints == "sift" else "auto")
    config = ScanConfig(features=FeatureParams(keypoints=keypoints), keyframes=keyframes)
    res = scan(cap, out, config=config, force=True)
    seconds = time.perf_counter() - t0
    with TemplateDB.open(out) as db:
        poses = {k: np.asarray(T) for k, T in db.poses()["frames"].items()}
        turned = sum(1 for e in db.edges() if (e.reason or "").startswith(LOOP_TURN.split("{")[0]))
    return score(poses, gt_T_world_cam(cap)) | {"turn_refused": turned, "s_per_frame": seconds / res.frames}


def capture(name: str, n: int, work: Path) -> Path:
    """The object's turntable capture folder in `work` (rendered on first use)."""
    cap = work / f"{name}_{n}"
    if not cap.exists():
        render_capture(plain(name), cap, n, mode="turntable", seed=0, table_kind="plain")
    return cap


def scan_peers(name: str, n: int, work: Path, ppf) -> dict[str, dict]:
    """bench/peers.py's FPFH + RANSAC + ICP chain and, with `ppf` (a `PPFPeer`, or None), its PPF + ICP chain on
    the object's masked depth (depth outside the rendered mask set to 0, as bench/scan.py's masked peers), scored
    as `scan_object`. Working range: 2 m."""
    from peers import fpfh_ransac_icp_chain, ppf_icp_chain
    from scan import gt_T_world_cam, score

    from gscan.io import open_sequence

    cap = capture(name, n, work)
    seq = open_sequence(cap)
    frames = [seq[k] for k in seq.names]
    for f in frames:
        f.depth = np.where(f.mask, f.depth, 0.0).astype(np.float32)
        f.mask = None
    chains = {"fpfh": lambda: fpfh_ransac_icp_chain(frames, PEER_DEPTH_MAX)}
    if ppf is not None:
        chains["ppf"] = lambda: ppf_icp_chain(frames, PEER_DEPTH_MAX, ppf)
    out = {}
    for key, chain in chains.items():
        r = chain()
        out[key] = score(r.T_world_cam, gt_T_world_cam(cap)) | {"turn_refused": 0, "s_per_frame": r.seconds / n}
    return out


def open_ppf():
    """A `PPFPeer`, or None (printing why) when opencv-contrib is not installed."""
    from peers import PeerUnavailable, PPFPeer

    try:
        return PPFPeer()
    except PeerUnavailable as e:
        print(f"PPF peer skipped: {e}", flush=True)
        return None


def scans(objects: list[str], n: int, work: Path) -> None:
    """Whole scans of each object on `sift`, `depth` and `both` (templates and captures kept in `work`), and the
    peers' chains, printed one line each: registered / wrong / ATE, and the time per frame as a ratio to `sift`'s."""
    from contextlib import nullcontext

    ppf = open_ppf()
    with ppf or nullcontext():
        for name in objects:
            split = "tune" if name in TUNE else "held-out"
            rows = {kp: scan_object(name, n, kp, work) for kp in SOURCES}
            rows |= scan_peers(name, n, work, ppf)
            for kp, r in rows.items():
                print(f"{split:8s} {name[:40]:40s} scan {kp:5s} registered {r['registered']:2d}/{r['frames']} wrong "
                      f"{len(r['wrong']):2d} ATE {1000 * r['ate_rmse']:6.2f} mm loop closures refused as a half turn "
                      f"{r['turn_refused']:2d} time x{r['s_per_frame'] / rows['sift']['s_per_frame']:.2f} of sift",
                      flush=True)


def estimate_scenes(name: str, oi: int, n: int, printed: dict[str, TexturedMesh], negatives: int):
    """Yields (label, RGBDFrame, T_cam_gt or None for a negative) of one plain object's cluttered scenes: the object
    upright at a random yaw among one printed shared mesh and one other plain object (a realistic shelf holds
    both), on a wood, fabric, plain or newspaper table, seen from 20-50 deg elevation (the scan's turntable looked
    from 30), then `negatives` scenes of the two others alone (bench/recall.py's scene maker)."""
    from recall import QUERY_TABLES, render_query

    from gscan.geometry.transforms import rotvec_to_R
    from gscan.synth import DEFAULT_INTRINSICS

    target = plain(name)
    others = [o for o in TUNE + HELD_OUT if o != name]
    for k in range(n + negatives):
        seed = 1000 + 100 * oi + k
        rng = np.random.default_rng([seed, 0x9A1])
        names = sorted(printed)
        distractors = [printed[names[int(rng.integers(len(names)))]], plain(others[int(rng.integers(len(others)))])]
        R = rotvec_to_R([0.0, 0.0, rng.uniform(0, 2 * np.pi)])
        el, az = rng.uniform(20, 50), rng.uniform(0, 360)
        table = QUERY_TABLES[(oi + k) % len(QUERY_TABLES)]
        r, T_gt = render_query(target, R, el, az, distractors, seed, table, with_target=k < n)
        label = f"{name[:24]}/{k}" if k < n else f"{name[:24]}/empty{k - n}"
        yield label, RGBDFrame(label, r.color, r.depth, DEFAULT_INTRINSICS), (T_gt if k < n else None)


class PeerEstimator:
    """A peer's pose estimate of a template's object in a whole frame (within PEER_DEPTH_MAX): bench/peers.py's
    FPFH + RANSAC + ICP or PPF + ICP, the model the template's fused mesh (the template's frame). A pose is found
    when at least MIN_FITNESS of the model's points facing the camera under it have a scene point within two
    FPFH voxels (the chains' rule, on the side a camera sees: a model's points are at most half in view). The
    scene's dominant plane (the table: RANSAC, PEER_TABLE_DIST) is removed first, as peer pipelines do."""

    def __init__(self, method: str, tpl: Path, ppf=None):
        from peers import FPFH_VOXEL, PPF_VOXEL, fpfh, mesh_cloud, unit_normals

        from gscan.template.db import TemplateDB

        with TemplateDB.open(tpl) as db:
            mesh = db.mesh()
        if mesh is None:
            raise ValueError(f"{tpl}: no mesh")
        self.method, self.ppf, self.key = method, ppf, str(tpl)
        model = mesh_cloud(mesh.vertices, mesh.triangles)
        diameter = float(np.linalg.norm(model.get_max_bound() - model.get_min_bound()))
        self.voxel = FPFH_VOXEL if method == "fpfh" else PPF_VOXEL * diameter
        self.model = model if method == "fpfh" else unit_normals(model.voxel_down_sample(self.voxel))
        self.features = fpfh(self.model) if method == "fpfh" else None
        self.trained = False

    def estimate(self, frame: RGBDFrame) -> tuple[np.ndarray | None, float]:
        """(T_cam_obj [4 x 4] or None, CPU seconds: this process's and the PPF child's)."""
        import open3d as o3d
        from peers import FPFH_VOXEL, MIN_FITNESS, fitness, fpfh, fpfh_ransac_icp, frame_cloud

        t0 = time.process_time()
        scene = frame_cloud(frame, PEER_DEPTH_MAX, self.voxel)
        o3d.utility.random.seed(0)
        _, table = scene.segment_plane(PEER_TABLE_DIST, 3, 1000)
        scene = scene.select_by_index(table, invert=True)
        child = 0.0
        if self.method == "fpfh":
            T, _ = fpfh_ransac_icp((self.model, self.features), (scene, fpfh(scene)), min_fitness=0.0)
        else:
            T, child = self.ppf.register(self.key, None if self.trained else self.model, scene, self.voxel)
            self.trained = True
        if T is not None and fitness(self.model, scene, T, 2 * FPFH_VOXEL, facing=True) < MIN_FITNESS:
            T = None
        return T, time.process_time() - t0 + child


def estimates(objects: list[str], n: int, frames: int, negatives: int, work: Path) -> None:
    """Each object's templates scanned on `sift`, `depth` and `both` (`scan_object`, cached in `work`), the latter
    two estimated with the query's depth keypoints too (`query.depth_keypoints`, the default), and the peers
    (`PeerEstimator`, model: the `both` template's mesh), in its cluttered scenes (`estimate_scenes`): per method
    found / wrong accepted (ADD-S beyond 2 cm, or any pose in a negative) / AUC ADD-S (0-10 cm) / depth-only poses,
    and the CPU time per estimate as a ratio to sift's on the same scenes. Every scene's row is printed, then each
    split's totals."""
    from contextlib import nullcontext

    from recall import DISTRACTOR_POOL
    from recall import MESHES as RECALL_MESHES

    from gscan.errors import InputError
    from gscan.estimate import Estimator
    from gscan.estimate.params import DEFAULT_PARAMS
    from gscan.evaluate.bop19 import template_to_gt
    from gscan.evaluate.metrics import adds, auc
    from gscan.io import open_sequence

    printed = {d: load_textured_mesh(RECALL_MESHES / d / "model_0.obj") for d in DISTRACTOR_POOL
               if d not in TUNE + HELD_OUT + objects}  # a plain object's printed self: its colour, size and shape
    work.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    ppf = open_ppf()
    methods = SOURCES + (("fpfh", "ppf") if ppf is not None else ("fpfh",))
    with ppf or nullcontext():
        for name in objects:
            split = "tune" if name in TUNE else "held-out"
            known = TUNE + HELD_OUT  # the scenes' seeds: another object's after theirs
            oi = known.index(name) if name in known else len(known) + [o for o in objects if o not in known].index(name)
            ests, to_gt = {}, {}
            for kp in SOURCES:
                tpl = work / f"{name}_{frames}_{kp}.gscan"
                if not tpl.exists():
                    scan_object(name, frames, kp, work)
                try:
                    to_gt[kp] = template_to_gt(tpl, open_sequence(work / f"{name}_{frames}").gt_T_cam_obj)
                except InputError as e:  # a scan of one registered frame: no template to estimate with
                    print(f"{split:8s} {name[:32]:32s} {kp:5s} template unusable: {e.reason}", flush=True)
                    continue
                ests[kp] = Estimator.from_path(tpl, DEFAULT_PARAMS)
            if "both" in ests:
                for peer in methods[len(SOURCES):]:  # the peers' model: the both template's mesh
                    ests[peer] = PeerEstimator(peer, work / f"{name}_{frames}_both.gscan", ppf)
                    to_gt[peer] = to_gt["both"]
            verts = plain(name).vertices
            for label, frame, T_gt in estimate_scenes(name, oi, n, printed, negatives):
                for kp in methods:
                    row = {"split": split, "kp": kp, "label": label, "positive": T_gt is not None, "found": False,
                           "adds": None, "wrong": False, "cpu": float("nan"), "depth_only": False}
                    rows.append(row)
                    if kp not in ests:
                        continue
                    est, reason, depth_only = ests[kp], "", False
                    if isinstance(est, PeerEstimator):
                        T, cpu = est.estimate(frame)
                    else:
                        est.estimate(frame)  # untimed once: the first call of a template loads its kernels
                        t0 = time.process_time()
                        res = est.estimate(frame)
                        cpu = time.process_time() - t0
                        T, reason, depth_only = res.T_cam_obj if res.found else None, str(res.reason), res.depth_only
                    e = None if T is None or T_gt is None else adds(verts, T @ to_gt[kp], T_gt)
                    wrong = T is not None and (T_gt is None or e is None or e > 0.02)
                    row.update(found=T is not None, adds=e, wrong=wrong, cpu=cpu, depth_only=depth_only)
                    print(f"{split:8s} {label:32s} {kp:5s} {'found' if T is not None else 'none ':5s} "
                          f"{'' if e is None else f'ADD-S {1000 * e:6.1f} mm'} {'WRONG ' if wrong else ''}"
                          f"{'depth-only ' if depth_only else ''}{cpu:.2f} s"
                          f"{' (' + reason[:90] + ')' if T is None and reason else ''}", flush=True)
    for split in ("tune", "held-out", "all"):
        rs = [r for r in rows if split == "all" or r["split"] == split]
        if not rs:
            continue
        timed = {r["label"] for r in rs if r["kp"] == "sift" and np.isfinite(r["cpu"])}  # scenes sift estimated
        base = np.mean([r["cpu"] for r in rs if r["kp"] == "sift" and r["label"] in timed])
        for kp in methods:
            k = [r for r in rs if r["kp"] == kp]
            pos = [r for r in k if r["positive"]]
            print(f"{split:8s} {kp:5s} found {sum(r['found'] for r in pos)}/{len(pos)} wrong "
                  f"{sum(r['wrong'] for r in k)} (of {len(k)} scenes, {len(k) - len(pos)} negative) AUC ADD-S "
                  f"{auc([r['adds'] if r['found'] and r['adds'] is not None else float('inf') for r in pos]):.3f} "
                  f"depth-only {sum(r['depth_only'] for r in k)} time x"
                  f"{np.nanmean([r['cpu'] for r in k if r['label'] in timed]) / base:.2f} "
                  f"of sift", flush=True)


def lookalikes(n: int, work: Path, first: int = 0) -> None:
    """A CAD template of a one-colour box (`gscan.synth.cases.plain_part_meshes`, 24 views, image and depth
    keypoints) estimated with the query's depth keypoints in `n` frames of it beside a printed box of about its size
    and a flat plain box, and in `n` frames of those two alone (`plain_part_scene`): found / wrong (beyond 5 deg /
    2 cm up to the box's half turns, or any pose without the box) / depth-only; seeds first .. first + n - 1."""
    from gscan.estimate import Estimator
    from gscan.estimate.params import DEFAULT_PARAMS
    from gscan.features import OBJECT_FEATURES
    from gscan.scanning.cad import template_from_mesh
    from gscan.synth import DEFAULT_INTRINSICS
    from gscan.synth.cases import plain_part_meshes, plain_part_scene
    from gscan.synth.mesh import save_textured_mesh

    work.mkdir(parents=True, exist_ok=True)
    part = plain_part_meshes()[0]
    tpl = work / "plain_part.gscan"
    if not tpl.exists():
        template_from_mesh(save_textured_mesh(part, work / "plain_part.obj"), tpl, n_views=24,
                           feature_params=replace(OBJECT_FEATURES, keypoints="both"))
    est = Estimator.from_path(tpl, DEFAULT_PARAMS)
    turns = [np.eye(3)] + [2.0 * np.outer(a, a) - np.eye(3) for a in np.eye(3)]
    counts = {True: [0, 0, 0], False: [0, 0, 0]}
    for seed in range(first, first + n):
        for with_part in (True, False):
            r, T_gt = plain_part_scene(seed, with_part)
            res = est.estimate(RGBDFrame(f"part_{seed}", r.color, r.depth, DEFAULT_INTRINSICS))
            wrong = False
            if res.T_cam_obj is not None:
                errs = []
                for R in turns:
                    S = np.eye(4)
                    S[:3, :3] = R
                    errs.append(pose_error(res.T_cam_obj @ S, T_gt))
                deg, m = min(errs)
                wrong = not with_part or deg > 5.0 or m > 0.02
            counts[with_part] = [x + y for x, y in zip(counts[with_part], [res.found, wrong, res.depth_only],
                                                       strict=True)]
            print(f"look-alikes seed {seed} {'with the part' if with_part else 'without it  '} "
                  f"{'found' if res.found else 'none '} {'WRONG ' if wrong else ''}"
                  f"{'depth-only' if res.depth_only else ''} {'' if res.found else str(res.reason)[:100]}", flush=True)
    for with_part, (found, wrong, depth) in counts.items():
        print(f"look-alikes {'with the part' if with_part else 'without it'}: found {found}/{n} wrong {wrong} "
              f"depth-only {depth}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="*", default=TUNE + HELD_OUT)
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--scans", action="store_true", help="whole scans (sift and both) instead of pairs")
    ap.add_argument("--residuals", action="store_true", help="the keypoints' distances at the true pose")
    ap.add_argument("--estimate", action="store_true", help="estimation in clutter with sift and both templates")
    ap.add_argument("--scenes", type=int, default=8, help="--estimate: scenes with the object, per object")
    ap.add_argument("--negatives", type=int, default=3, help="--estimate: scenes without it, per object")
    ap.add_argument("--work", type=Path, default=None, help="--scans, --estimate: keep captures and templates here")
    ap.add_argument("--lookalikes", type=int, default=0, help="frames of a plain CAD box beside look-alike boxes")
    ap.add_argument("--first-seed", type=int, default=0, help="--lookalikes: the first scene's seed")
    a = ap.parse_args()
    if a.lookalikes:
        with tempfile.TemporaryDirectory() as tmp:
            lookalikes(a.lookalikes, Path(tmp) if a.work is None else a.work, a.first_seed)
        return
    if a.estimate:
        with tempfile.TemporaryDirectory() as tmp:
            estimates(a.objects, a.scenes, a.frames, a.negatives, Path(tmp) if a.work is None else a.work)
        return
    if a.residuals:
        for name in a.objects:
            residuals(name, a.frames)
        return
    if a.scans:
        with tempfile.TemporaryDirectory() as tmp:
            scans(a.objects, a.frames, Path(tmp) if a.work is None else a.work)
        return
    total = {s: np.zeros(3) for s in SOURCES}
    for name in a.objects:
        res = run(name, a.frames)
        split = "tune" if name in TUNE else "held-out"
        base = res["sift"]["s_per_pair"]
        for s in SOURCES:
            r = res[s]
            total[s] += [r["registered"], r["wrong"], r["pairs"]]
            print(f"{split:8s} {name[:40]:40s} {s:5s} registered {r['registered']:2d}/{r['pairs']} wrong "
                  f"{r['wrong']:2d} time x{r['s_per_pair'] / base:.2f} of sift", flush=True)
    for s in SOURCES:
        reg, wrong, pairs = total[s]
        print(f"all {s:5s} registered {int(reg)}/{int(pairs)} wrong {int(wrong)}")


if __name__ == "__main__":
    main()
