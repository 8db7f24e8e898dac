"""Plain objects: pairwise registration on image keypoints (SIFT), depth keypoints (ISS + FPFH) or both.

Each object is a shared mesh with its texture replaced by its mean colour, rendered on a plain table as a
turntable capture (36 frames, 10 deg apart; the renderer's object masks, as a moving-object scan segments
them). Every consecutive pair is registered by `gscan.registration.pairwise.register_features` with the depth
samples (rule 3), once per keypoint source. A pair is registered when accepted, wrong when accepted beyond
5 deg or 2 cm (at the object's centre) of the truth. Time: keypoints + registration per pair, as a ratio to
SIFT-only in the same run.

Split: the depth-alone thresholds (`RegisterParams.max_see_through_shape`, `max_outside_shape`) and
FPFH_EPS_F were set on TUNE; HELD_OUT was not looked at before.

With --scans, whole scans instead (`scan_object`): registered and wrong frames per object on sift and both.
With --residuals, how well each kind of keypoint is located (`residuals`): on `both` keypoints, the distances at
the true pose of the inlier pairs of the accepted consecutive pairs, and of the true pairs (mutual nearest
keypoints of a kind within 2 cm under the truth), in units of the sensor's s and of s with the keypoints' location
sigma (`Features.location_sigma`).

    python bench/plain.py [--objects NAME ...] [--frames 36] [--scans | --residuals]
"""
from __future__ import annotations

import argparse
import time
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

MESHES = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "meshes"
TUNE = ["ReadytoUse_Rolled_Fondant_Pure_White_24_oz_box"]
HELD_OUT = ["Crayola_Bonus_64_Crayons", "Nestle_Raisinets_Milk_Chocolate_35_oz_992_g",
            "Pepsi_Caffeine_Free_Diet_12_CT"]
SOURCES = ("sift", "depth", "both")


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


def scan_object(name: str, n: int, keypoints: str, work: Path) -> dict[str, int]:
    """A whole scan (`gscan.scanning.api.scan`, the defaults but `features.keypoints`) of one object's capture:
    {"frames", "registered", "wrong", "turn_refused"}; wrong: beyond 5 deg / 2 cm of the truth relative to the
    other registered frames (`frame_errors`); turn_refused: loop closures refused as the object's half turn."""
    from gscan.evaluate.metrics import frame_errors
    from gscan.io import open_sequence
    from gscan.registration.edges import LOOP_TURN
    from gscan.scanning.api import scan
    from gscan.scanning.config import ScanConfig
    from gscan.template.db import TemplateDB

    cap = work / f"{name}_{n}"
    if not cap.exists():
        render_capture(plain(name), cap, n, mode="turntable", seed=0, table_kind="plain")
    out = work / f"{name}_{n}_{keypoints}.gscan"
    res = scan(cap, out, config=ScanConfig(features=FeatureParams(keypoints=keypoints)))
    with TemplateDB.open(out) as db:
        poses = {k: np.asarray(T) for k, T in db.poses()["frames"].items()}
        turned = sum(1 for e in db.edges() if (e.reason or "").startswith(LOOP_TURN.split("{")[0]))
    gt = open_sequence(cap).gt_T_cam_obj
    wrong = frame_errors(poses, {k: inv_T(T) for k, T in gt.items()}).wrong(5.0, 0.02)
    return {"frames": n, "registered": res.registered, "wrong": len(wrong), "turn_refused": turned}


def scans(objects: list[str], n: int) -> None:
    """Whole scans of each object on `sift` and on `both`, printed one line each."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for name in objects:
            split = "tune" if name in TUNE else "held-out"
            for kp in ("sift", "both"):
                r = scan_object(name, n, kp, Path(tmp))
                print(f"{split:8s} {name[:40]:40s} scan {kp:5s} registered {r['registered']:2d}/{r['frames']} wrong "
                      f"{r['wrong']:2d} loop closures refused as a half turn {r['turn_refused']}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="*", default=TUNE + HELD_OUT)
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--scans", action="store_true", help="whole scans (sift and both) instead of pairs")
    ap.add_argument("--residuals", action="store_true", help="the keypoints' distances at the true pose")
    a = ap.parse_args()
    if a.residuals:
        for name in a.objects:
            residuals(name, a.frames)
        return
    if a.scans:
        scans(a.objects, a.frames)
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
