"""Benchmark of pose estimation (gscan.estimate.estimator) on cluttered rendered scenes, against a baseline.

For every shared mesh (or --meshes): a CAD template (`template_from_mesh`, --views views,
cached under --work), then --scenes scenes: the target resting on a textured table in a random
orientation with two other shared meshes beside it as distractors, seen from a random viewpoint
(elevation 20-65 deg, distance 0.95-1.3 x the 45 %-fill distance); every other scene looks at the
target past a distractor from low (elevation 15-35 deg), so the distractor partly occludes it
(viewpoints leaving less than 30 % of the target visible are re-drawn). Depth noise and holes as rendered.

Methods, same templates, same query features, same retrieval, same ICP / scoring / acceptance:
- gscan: `Estimator` (GMatch per retrieved view), full frame, ICP on.
- gscan-mask-noicp: the same with the ground-truth mask as --mask and no ICP (speed target).
- gscan-scanned (--scanned N): the first N meshes also scanned (gscan.scanning.pipeline) from a rendered 24-frame
  capture on a table; the scanned template's frame is mapped to the ground truth by the mean of
  T_obj_cam[f] @ T_cam_gt[f] over the capture frames; full frame, ICP on.
- baseline: gscan.matching.baselines "ratio" per retrieved view (nearest neighbour + Lowe ratio 0.75, then
  open3d correspondence RANSAC with a 1 cm inlier distance, seeded), the view with the most inliers,
  then the same Kabsch / ICP / score / acceptance as gscan.

Reports per method: found %, AUC of ADD and ADD-S (YCB-Video, 0-10 cm; not found = failure),
ADD < 10 % of the diameter, the wrong results accepted (poses returned with ADD above 10 % of the diameter:
count and % of the scenes) and the median milliseconds of every stage.

    python bench/estimate.py                      # all 21 meshes, 4 scenes each
    python bench/estimate.py --meshes 3 --scenes 2 --json out.json
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from gscan.estimate.estimator import STAGES, EstimateParams, Estimator
from gscan.estimate.hypotheses import QueryKeypoints
from gscan.estimate.retrieval import TemplateIndex
from gscan.evaluate.metrics import add, adds, auc
from gscan.geometry.transforms import look_at, rotvec_to_R, transform_points
from gscan.io.camera import RGBDFrame
from gscan.matching.baselines import run_baseline
from gscan.scanning.cad import template_from_mesh
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    default_distance,
    load_textured_mesh,
    place_distractors,
    rest_on_table,
)

ROOT = Path(__file__).resolve().parents[1]
MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"


def ratio_ransac_lists(index: TemplateIndex, v: int, qk: QueryKeypoints) -> list[tuple[np.ndarray, float]]:
    """Baseline `Matcher`: gscan.matching.baselines "ratio" (NN + Lowe ratio 0.75 -> open3d correspondence RANSAC,
    1 cm, seeded) in place of GMatch on each retrieved view neighbourhood; everything else (features, retrieval,
    pre-scoring, Kabsch, ICP, verification) is shared."""
    nb = index.neighbourhoods[v]
    feats = qk.feats
    if len(nb.idx) < 3 or len(feats) < 3:
        return [(np.zeros((0, 2), np.int64), 1.0)]
    dist = index.distances(qk.similarity(nb.idx)).T  # [N_neighbourhood x M_query]
    res = run_baseline("ratio", nb.points, feats.points, dist)
    if res.T_tgt_src is None or len(res.matches) == 0:
        return [(np.zeros((0, 2), np.int64), 1.0)]
    m = np.asarray(res.matches, dtype=np.int64)
    r = np.linalg.norm(nb.points[m[:, 0]] @ res.T_tgt_src[:3, :3].T + res.T_tgt_src[:3, 3]
                       - feats.points[m[:, 1]], axis=1)
    return [(np.stack([nb.idx[m[:, 0]], m[:, 1]], 1), float(r.mean()))]


def make_scene(target, distractors, seed: int, occlude: bool, min_visible: float = 0.3):
    """(RenderedFrame, visible fraction of the target) of one cluttered scene; viewpoints leaving less
    than `min_visible` of the target visible are re-drawn (seeded), as BOP skips such annotations."""
    rng = np.random.default_rng([seed, 0xE57])
    T_wt = rest_on_table(target, rotvec_to_R([0.0, 0.0, rng.uniform(0, 2 * np.pi)]))
    d_poses = place_distractors(target, T_wt, distractors, rng)
    scene = SynthScene([(target, T_wt)] + list(zip(distractors, d_poses, strict=True)), seed=seed)
    alone = SynthScene([(target, T_wt)], table=False, seed=seed)
    c = transform_points(T_wt, target.center[None])[0]
    for _ in range(20):
        if occlude:  # look at the target past the first distractor, from low
            el = np.radians(rng.uniform(15, 35))
            dc = transform_points(d_poses[0], distractors[0].center[None])[0]
            az = np.arctan2(dc[1] - c[1], dc[0] - c[0]) + np.radians(rng.uniform(-25, 25))
        else:
            el = np.radians(rng.uniform(20, 65))
            az = rng.uniform(0, 2 * np.pi)
        dist = default_distance(target, fill=0.45) * rng.uniform(0.95, 1.3)
        eye = c + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        r = scene.render(look_at(eye, c), DEFAULT_INTRINSICS, rng=np.random.default_rng([seed, 1]))
        full = alone.render(look_at(eye, c), DEFAULT_INTRINSICS, noise=False, shading=False).mask.sum()
        visible = float(r.mask.sum()) / max(1, int(full))
        if visible >= min_visible:
            break
    return r, visible


def scanned_template(name: str, mesh, work: Path, n_frames: int) -> tuple[Path, np.ndarray]:
    """Scan a rendered capture of `mesh` (gscan.scanning.pipeline, static object on a textured table) into a template;
    returns (template path, T_obj_gt [4 x 4]): the template->ground-truth alignment, the mean of
    T_obj_cam[f] @ T_cam_gt[f] over the capture frames, never from the test scenes."""
    from gscan.evaluate.bop19 import template_to_gt
    from gscan.io import open_sequence
    from gscan.scanning.api import scan
    from gscan.synth import render_capture

    cap, tpl = work / f"{name}_capture{n_frames}", work / f"{name}_scan{n_frames}.gscan"
    if not cap.exists():
        render_capture(mesh, cap, n_frames, seed=11)
    if not tpl.exists():
        scan(cap, tpl)
    T_obj_gt = template_to_gt(tpl, open_sequence(cap).gt_T_cam_obj)
    return tpl, T_obj_gt


def run(args: argparse.Namespace) -> dict:
    names = sorted(p.name for p in MESHES.iterdir() if (p / "model_0.obj").is_file())
    if args.meshes:
        wanted = args.meshes.split(",")
        names = names[: int(args.meshes)] if args.meshes.isdigit() else [n for n in names if n in wanted]
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    all_meshes = {n: load_textured_mesh(MESHES / n / "model_0.obj") for n in sorted(p.name for p in MESHES.iterdir()
                                                                                   if (p / "model_0.obj").is_file())}
    methods = ("gscan", "gscan-mask-noicp", "baseline")
    recs: dict[str, list[dict]] = {m: [] for m in methods + ("gscan-scanned",)}
    t_build = []
    for ti, name in enumerate(names):
        ct = EstimateParams().features.sift_contrast_threshold  # cache key: the template's keypoint settings
        tpl = work / f"{name}_v{args.views}_c{ct:g}.gscan"
        if not tpl.exists():
            t0 = time.perf_counter()
            template_from_mesh(MESHES / name / "model_0.obj", tpl, n_views=args.views)
            t_build.append(time.perf_counter() - t0)
        est = {"gscan": Estimator.from_path(tpl), "baseline": Estimator.from_path(tpl, matcher=ratio_ransac_lists)}
        est["gscan-mask-noicp"] = est["gscan"]
        target = all_meshes[name]
        scanned = None
        if ti < args.scanned:
            tpl_s, T_obj_gt = scanned_template(name, target, work, args.scan_frames)
            scanned = (Estimator.from_path(tpl_s), T_obj_gt)
        pts = target.vertices
        diameter = float(np.linalg.norm(target.extent))
        others = [n for n in all_meshes if n != name]
        for k in range(args.scenes):
            seed = 1000 * ti + k
            rng = np.random.default_rng([seed, 7])
            distractors = [all_meshes[n] for n in rng.choice(others, 2, replace=False)]
            r, visible = make_scene(target, distractors, seed, occlude=(k % 2 == 1))
            frame = RGBDFrame(f"{name}_{k}", r.color, r.depth, DEFAULT_INTRINSICS)
            for m in methods:
                mask, refine = (r.mask, False) if m == "gscan-mask-noicp" else (None, True)
                res = est[m].estimate(frame, mask=mask, refine=refine)
                e_add = add(pts, res.T_cam_obj, r.T_cam_obj) if res.found else float("inf")
                e_adds = adds(pts, res.T_cam_obj, r.T_cam_obj) if res.found else float("inf")
                recs[m].append({"mesh": name, "scene": k, "visible": visible, "found": res.found, "add": e_add,
                                "adds": e_adds, "diameter": diameter, "n_matches": res.n_matches,
                                "timings_ms": res.timings_ms, "reason": res.reason})
            if scanned is not None:  # same scene, scanned template, pose mapped to the ground-truth frame
                res = scanned[0].estimate(frame)
                T = None if res.T_cam_obj is None else res.T_cam_obj @ scanned[1]
                recs["gscan-scanned"].append({
                    "mesh": name, "scene": k, "visible": visible, "found": res.found,
                    "add": add(pts, T, r.T_cam_obj) if res.found else float("inf"),
                    "adds": adds(pts, T, r.T_cam_obj) if res.found else float("inf"), "diameter": diameter,
                    "n_matches": res.n_matches, "timings_ms": res.timings_ms, "reason": res.reason})
            line = "  ".join(f"{m}: {'%.1f mm' % (recs[m][-1]['add'] * 1e3) if recs[m][-1]['found'] else 'not found'}"
                             for m in methods)
            print(f"{name[:28]:28s} scene {k} visible {visible:4.0%}  {line}", file=sys.stderr, flush=True)
    summary = {}
    for m in recs:
        rs = recs[m]
        if not rs:
            continue
        add_e = [r["add"] for r in rs]
        summary[m] = {
            "scenes": len(rs), "found %": 100.0 * np.mean([r["found"] for r in rs]),
            "AUC ADD": auc(add_e), "AUC ADD-S": auc([r["adds"] for r in rs]),
            "ADD<0.1d %": 100.0 * np.mean([r["add"] < 0.1 * r["diameter"] for r in rs]),
            "wrong found %": 100.0 * np.mean([r["found"] and r["add"] > 0.1 * r["diameter"] for r in rs]),
            "wrong found": int(sum(r["found"] and r["add"] > 0.1 * r["diameter"] for r in rs)),
            "median ms": {s: float(np.median([r["timings_ms"].get(s, 0.0) for r in rs])) for s in STAGES},
        }
    return {"meshes": names, "views": args.views, "scenes_per_mesh": args.scenes, "summary": summary,
            "template_build_s_median": float(np.median(t_build)) if t_build else None,
            "records": {m: [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()}
                            for r in recs[m]] for m in recs}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--meshes", default="", help="number of meshes (first N sorted) or comma-separated names")
    ap.add_argument("--scenes", type=int, default=4, help="scenes per mesh")
    ap.add_argument("--views", type=int, default=36, help="template views")
    ap.add_argument("--scanned", type=int, default=0, help="also scan a rendered capture of the first N meshes "
                    "(gscan.scanning.pipeline) and estimate the same scenes with that template")
    ap.add_argument("--scan-frames", type=int, default=24, help="frames of each scanned capture")
    ap.add_argument("--work", default="/tmp/gscan-bench-estimate", help="template cache folder")
    ap.add_argument("--json", default=None, help="write the full results here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    out = run(args)
    s = out["summary"]
    print(f"\n{len(out['meshes'])} meshes x {out['scenes_per_mesh']} scenes, {out['views']}-view CAD templates"
          + (f"; gscan-scanned: the first {args.scanned} meshes, {args.scan_frames}-frame scans"
             if args.scanned else ""))
    print("| method | scenes | found % | AUC ADD | AUC ADD-S | ADD<0.1d % | wrong results accepted (ADD > 0.1 d) |")
    print("|---|---|---|---|---|---|---|")
    for m, v in s.items():
        print(f"| {m} | {v['scenes']} | {v['found %']:.1f} | {v['AUC ADD']:.1f} | {v['AUC ADD-S']:.1f} | "
              f"{v['ADD<0.1d %']:.1f} | {v['wrong found']} ({v['wrong found %']:.1f} %) |")
    print("\n| method | " + " | ".join(STAGES) + " |  (median ms)")
    print("|---|" + "---|" * len(STAGES))
    for m, v in s.items():
        print(f"| {m} | " + " | ".join(f"{v['median ms'][k]:.0f}" for k in STAGES) + " |")
    if out["template_build_s_median"] is not None:
        print(f"\ntemplate build: median {out['template_build_s_median']:.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
