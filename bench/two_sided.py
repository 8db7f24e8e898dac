"""Two-sided templates: an object scanned upright only (one-sided) against upright and upside down (two-sided).

For every object, two static captures are rendered (gscan.synth.cases.two_sided_captures: --views views each on
orbit rings at 30 and 55 deg over a newspaper table; the second with the object upside down and turned 40 deg
against the table). The one-sided template is `gscan.scan(up)`, the two-sided one `gscan.scan([up, down])`
(each capture registered in its own world, then joined on the object's own keypoints). Per template:

- frames registered, and wrong frames: registered beyond 5 deg / 2 cm of the ground truth (`wrong_frames`: each
  frame's median relative pose error against the other registered frames of its capture, and a second capture
  joined at a wrong pose counts all its frames); must be 0;
- completeness: the share of the true surface (20,000 points sampled by area, seeded) within 5 mm of the
  template's fused cloud (`TemplateDB.cloud()`), the template placed on the ground truth by its own frames
  (`template_to_gt`, never a test scene); "bottom": the same over the faces that look down when the object stands
  upright (normal z < -0.5), which the up capture cannot see;
- pose estimation (`Estimator.estimate`, whole image, no mask) on rendered cluttered scenes built and scored by
  bench/recall.py's helpers (`render_query`, `score`, `summarise`): the object among two shared meshes on another
  table, upright in 3 of every 5 scenes, on a side (90 deg about x or y) in 1 and upside down in 1 (40 % not
  upright), plus one negative scene per object (its distractors alone: a pose found there is wrong). Both
  templates estimate the same scenes. found %, within 5 deg / 1 cm %, AUC ADD-S (0-10 cm), and the wrong poses
  accepted (ADD > 10 % of the diameter, or any pose in a negative scene): must be 0;
- time: the join stage's seconds, and the seconds per frame the second capture's registration took against the
  first's (`ScanResult.to_json()["captures"][i]["timings_s"]`, summed over its stages).
- the CPU time per estimate with the single estimate's search elsewhere (`rivals.elsewhere`, the default)
  against without it: every scene estimated both ways, the order alternating between scenes (the poses scored
  are the default's).

Splits: this benchmark tunes nothing. "tune" holds objects gscan's scan and estimation were developed on (the
tests' box, Frozen_Scrabble_Jr, Crayola_Bonus_64_Crayons, and the tall box whose misses the keyframe selection was
changed on); "heldout" holds shared meshes that no test or other benchmark uses and procedural boxes with other
prints and sizes. The shared meshes are read in place from
../shared/data/meshes beside the repository (bench/recall.py's MESHES).

    python bench/two_sided.py --quick                 # one tune object, two held-out ones, 5 scenes each
    python bench/two_sided.py --json out.json         # every object, 10 scenes each
    python bench/two_sided.py --objects box_tall,box_flat   # those objects only
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from recall import (
    DISTRACTOR_POOL,
    QUERY_TABLES,
    ObjectSpec,
    build_mesh,
    distractor_pool,
    render_query,
    score,
    summarise,
)

from gscan.estimate.params import DEFAULT_PARAMS
from gscan.evaluate.bop19 import template_to_gt
from gscan.evaluate.metrics import frame_errors
from gscan.geometry.transforms import inv_T, pose_error, rotvec_to_R, transform_points
from gscan.io import open_sequence
from gscan.io.camera import RGBDFrame
from gscan.synth import DEFAULT_INTRINSICS, TexturedMesh
from gscan.synth.cases import two_sided_captures
from gscan.template.db import TemplateDB

WRONG_FRAME = (5.0, 0.02)  # deg, m
NEAR_M = 0.005  # a surface sample within this of the template's cloud is covered
N_SAMPLES = 20000
WITHOUT_ELSEWHERE = replace(DEFAULT_PARAMS, rivals=replace(DEFAULT_PARAMS.rivals, elsewhere=False))

OBJECTS = (  # (spec, in the quick run); kind "side" is bench/recall.py's, unused here
    (ObjectSpec("box_tests", "tune", "side", "box:0.14x0.09x0.07:3"), True),
    (ObjectSpec("scrabble", "tune", "side", "Frozen_Scrabble_Jr"), False),
    (ObjectSpec("crayola", "tune", "side", "Crayola_Bonus_64_Crayons"), False),
    (ObjectSpec("lego_calendar", "heldout", "side", "LEGO_City_Advent_Calendar"), True),
    (ObjectSpec("box_tall", "tune", "side", "box:0.10x0.07x0.16:21"), True),
    (ObjectSpec("pepsi_pack", "heldout", "side", "Pepsi_Caffeine_Free_Diet_12_CT"), False),
    (ObjectSpec("tena_pads", "heldout", "side", "Tena_Pads_Heavy_Long_42_pads"), False),
    (ObjectSpec("box_flat", "heldout", "side", "box:0.18x0.12x0.05:33"), False),
    (ObjectSpec("crunch_cookies", "heldout", "side",
                "Nestl_Crunch_Girl_Scouts_Cookie_Flavors_Caramel_Coconut_78_oz_box"), False),
    (ObjectSpec("box_upright", "heldout", "side", "box:0.12x0.08x0.20:47"), False),
    (ObjectSpec("box_cube", "heldout", "side", "box:0.15x0.10x0.09:58"), False),
)


def surface_samples(mesh: TexturedMesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """([n x 3] points on the mesh surface drawn by area, [n] whether each lies on a face looking down)."""
    rng = np.random.default_rng([seed, 0x5A5])
    tri = mesh.vertices[mesh.triangles]  # [F x 3 x 3]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    f = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    pts = ((1 - r1)[:, None] * tri[f, 0] + (r1 * (1 - r2))[:, None] * tri[f, 1] + (r1 * r2)[:, None] * tri[f, 2])
    nz = cross[f, 2] / np.maximum(2 * area[f], 1e-12)
    return pts, nz < -0.5


def completeness(tpl: Path, T_obj_gt: np.ndarray, samples: np.ndarray, bottom: np.ndarray) -> tuple[float, float]:
    """(share of all samples, share of the bottom ones) within NEAR_M of the template's fused cloud."""
    from scipy.spatial import cKDTree

    with TemplateDB.open(tpl) as db:
        cloud = db.cloud()
    if cloud is None or not len(cloud[0]):
        return 0.0, 0.0
    pts = transform_points(inv_T(T_obj_gt), cloud[0])  # template frame -> ground-truth frame
    d, _ = cKDTree(pts).query(samples)
    near = d <= NEAR_M
    return float(near.mean()), float(near[bottom].mean()) if bottom.any() else float("nan")


def scan_both(spec: ObjectSpec, mesh: TexturedMesh, work: Path, views: int) -> dict[str, dict]:
    """The one-sided and two-sided templates of an object (cached under `work`): kind -> {tpl, result, gt}."""
    from gscan.scanning.api import scan

    caps = work / f"{spec.name}_v{views}"
    if not (caps / "down").exists():
        two_sided_captures(mesh, caps, n_views=views)
    truth = {side: open_sequence(caps / side).gt_T_cam_obj for side in ("up", "down")}
    out = {}
    for kind, sources, gt in (("one-sided", [caps / "up"], truth["up"]),
                              ("two-sided", [caps / "up", caps / "down"],
                               {f"{s}/{n}": T for s in ("up", "down") for n, T in truth[s].items()})):
        tpl, res_json = work / f"{spec.name}_v{views}_{kind}.gscan", work / f"{spec.name}_v{views}_{kind}.json"
        if not res_json.exists():
            tpl.unlink(missing_ok=True)
            res = scan(sources if len(sources) > 1 else sources[0], tpl)
            res_json.write_text(json.dumps(res.to_json()))
        out[kind] = {"tpl": tpl, "result": json.loads(res_json.read_text()), "gt": gt}
    return out


def wrong_frames(poses: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """Registered frames beyond WRONG_FRAME -> their (deg, m) errors. poses: frame -> T_obj_cam; gt: frame ->
    its ground-truth counterpart. Within a capture (the frames' `CAPTURE/` prefix), each frame's median relative
    pose error against the capture's other frames (`frame_errors`); a capture after the first whose frames'
    median relative pose error against the first capture's frames is beyond the bound was joined at a wrong
    pose: all its frames are wrong (frame_errors over both captures would mark every frame of both when half
    are off)."""
    groups: dict[str, list[str]] = {}
    for n in poses:
        if n in gt:
            groups.setdefault(n.rpartition("/")[0], []).append(n)
    wrong: dict[str, tuple[float, float]] = {}
    for names in groups.values():
        fe = frame_errors({n: poses[n] for n in names}, {n: gt[n] for n in names})
        wrong |= {n: (fe.rot_deg[n], fe.trans_m[n]) for n in fe.wrong(*WRONG_FRAME)}
    first, *others = list(groups.values()) or [[]]
    for names in others:
        e = np.array([pose_error(inv_T(poses[a]) @ poses[b], inv_T(gt[a]) @ gt[b]) for a in first for b in names])
        deg, m = np.median(e[:, 0]), np.median(e[:, 1])
        if deg > WRONG_FRAME[0] or m > WRONG_FRAME[1]:
            wrong |= {n: (float(deg), float(m)) for n in names}
    return wrong


def scan_record(spec: ObjectSpec, kind: str, s: dict, samples: np.ndarray, bottom: np.ndarray) -> dict:
    """Frames registered / wrong, completeness and times of one template."""
    res, gt = s["result"], s["gt"]
    with TemplateDB.open(s["tpl"]) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    wrong = wrong_frames(poses, {n: inv_T(T) for n, T in gt.items()})
    T_obj_gt = template_to_gt(s["tpl"], gt)
    full, low = completeness(s["tpl"], T_obj_gt, samples, bottom)
    caps = res.get("captures", [])
    per_frame = [sum(c["timings_s"].values()) / max(1, c["frames"]) for c in caps]
    return {"object": spec.name, "split": spec.split, "template": kind, "frames": res["frames"],
            "registered": res["registered"], "wrong_frames": len(wrong),
            "wrong": {n: list(e) for n, e in wrong.items()},
            "joined": all(c["joined"] for c in caps) if caps else None,
            "completeness": full, "bottom": low, "join_s": res["timings_s"].get("join"),
            "s_per_frame": per_frame, "total_s": sum(res["timings_s"].values()), "T_obj_gt": T_obj_gt}


def query_rotation(rng: np.random.Generator, k: int) -> np.ndarray:
    """R_world_obj of scene k: upright (3 of 5), on a side (1 of 5, about x or y, either way), upside down (1 of 5);
    each turned about the vertical at random."""
    yaw = rotvec_to_R([0.0, 0.0, rng.uniform(0, 2 * np.pi)])
    if k % 5 == 1:
        axis = np.array([1.0, 0.0, 0.0] if k // 5 % 2 == 0 else [0.0, 1.0, 0.0])
        return yaw @ rotvec_to_R((1.0 if k // 10 % 2 == 0 else -1.0) * np.pi / 2 * axis)
    if k % 5 == 3:
        return yaw @ rotvec_to_R([np.pi, 0.0, 0.0])
    return yaw


def scenes(spec: ObjectSpec, oi: int, mesh: TexturedMesh, pool: dict[str, TexturedMesh], n: int):
    """Yields (label, pose kind, RGBDFrame, T_cam_gt or None for the negative scene) of one object."""
    for k in range(n + 1):
        seed = 1000 + 100 * oi + k
        rng = np.random.default_rng([seed, 0x25])
        names = [d for d in DISTRACTOR_POOL if d != spec.source]
        distractors = [pool[d] for d in rng.choice(names, 2, replace=False)]
        R = query_rotation(rng, k)
        el, az = rng.uniform(25, 70), rng.uniform(0, 360)
        table = QUERY_TABLES[(oi + k) % len(QUERY_TABLES)]
        pose = {1: "side", 3: "upside down"}.get(k % 5, "upright")
        r, T_gt = render_query(mesh, R, el, az, distractors, seed, table, with_target=k < n)
        label = f"{spec.name}/{k}" if k < n else f"{spec.name}/empty"
        yield label, pose if k < n else "none", RGBDFrame(label.replace("/", "_"), r.color, r.depth,
                                                          DEFAULT_INTRINSICS), (T_gt if k < n else None)


def timed_pair(est, plain, frame: RGBDFrame, first: bool):
    """(CPU ms of est.estimate(frame), of plain.estimate(frame), est's result); est first when `first` (the
    order alternates between scenes, so that neither is always the warmer)."""
    out = {}
    for e in ((est, plain) if first else (plain, est)):
        t1 = time.process_time()
        r = e.estimate(frame)
        out[id(e)] = ((time.process_time() - t1) * 1e3, r)
    return out[id(est)][0], out[id(plain)][0], out[id(est)][1]


def run(args: argparse.Namespace) -> dict:
    from gscan.estimate.estimator import Estimator

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    pool = distractor_pool()
    scan_recs: list[dict] = []
    est_recs: list[dict] = []
    n_scenes = args.scenes if args.scenes is not None else (5 if args.quick else 10)
    for oi, (spec, quick) in enumerate(OBJECTS):
        if (args.quick and not quick) or (args.split != "all" and spec.split != args.split):
            continue
        if args.objects and spec.name not in args.objects.split(","):
            continue
        mesh = build_mesh(spec)
        t0 = time.perf_counter()
        built = scan_both(spec, mesh, work, args.views)
        samples, bottom = surface_samples(mesh, N_SAMPLES)
        recs = {kind: scan_record(spec, kind, s, samples, bottom) for kind, s in built.items()}
        for r in recs.values():
            print(f"{spec.name:14s} {r['template']:9s} registered {r['registered']}/{r['frames']} wrong "
                  f"{r['wrong_frames']} joined {r['joined']} complete {100 * r['completeness']:.1f} % bottom "
                  f"{100 * r['bottom']:.1f} % ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        ests = {kind: Estimator.from_path(s["tpl"]) for kind, s in built.items()}
        # the same estimate without the search elsewhere (rivals.elsewhere), timed alternately: its cost
        plain = {kind: Estimator.from_path(s["tpl"], WITHOUT_ELSEWHERE) for kind, s in built.items()}
        diameter = float(np.linalg.norm(mesh.extent))
        for k, (label, pose, frame, T_gt) in enumerate(scenes(spec, oi, mesh, pool, n_scenes)):
            for kind, est in ests.items():
                if k == 0:
                    est.estimate(frame)  # untimed: the first call
                    plain[kind].estimate(frame)
                cpu, cpu_plain, res = timed_pair(est, plain[kind], frame, first=k % 2 == 0)
                base = {"scene": label, "split": spec.split, "template": kind, "pose": pose,
                        "positive": T_gt is not None, "diameter": diameter, "n_matches": res.n_matches,
                        "score": res.score, "reason": res.reason, "cpu_ms": cpu,
                        "cpu_ms_without_elsewhere": cpu_plain}
                rec = score(base, res.T_cam_obj, recs[kind]["T_obj_gt"], T_gt, mesh)
                est_recs.append(rec)
                err = ("not found: " + str(res.reason)) if not res.found else (
                    "FOUND (negative scene)" if T_gt is None else f"{rec['deg']:.1f} deg {rec['cm']:.2f} cm")
                print(f"  {label:18s} {pose:11s} {kind:9s} n={res.n_matches:2d} {cpu:6.0f} ms  {err}",
                      file=sys.stderr, flush=True)
        for r in recs.values():
            r["T_obj_gt"] = r["T_obj_gt"].tolist()
            scan_recs.append(r)
    return {"scans": scan_recs, "estimates": est_recs, "summary": summary(scan_recs, est_recs),
            "settings": {"views": args.views, "scenes": n_scenes, "quick": args.quick}}


def summary(scan_recs: list[dict], est_recs: list[dict]) -> dict:
    """split -> template kind -> the figures of the table."""
    out: dict = {}
    for split in ("tune", "heldout", "all"):
        for kind in ("one-sided", "two-sided"):
            ss = [r for r in scan_recs if r["template"] == kind and split in ("all", r["split"])]
            if not ss:
                continue
            es = summarise([r for r in est_recs if r["template"] == kind]).get(split, {})
            nonup = [r for r in est_recs if r["template"] == kind and r["pose"] in ("side", "upside down")
                     and split in ("all", r["split"])]
            two = [r for r in ss if r["s_per_frame"]]
            es_kind = [r for r in est_recs if r["template"] == kind and split in ("all", r["split"])]
            out.setdefault(split, {})[kind] = {
                "objects": len(ss), "frames": sum(r["frames"] for r in ss),
                "registered": sum(r["registered"] for r in ss), "wrong frames": sum(r["wrong_frames"] for r in ss),
                "joined": sum(bool(r["joined"]) for r in ss) if two else None,
                "completeness %": 100 * float(np.mean([r["completeness"] for r in ss])),
                "bottom %": 100 * float(np.mean([r["bottom"] for r in ss])),
                "found %": es.get("found %"), "found not upright %": 100 * float(np.mean([r["found"] for r in nonup]))
                if nonup else None,
                "within 5deg/1cm %": es.get("within 5deg/1cm %"), "AUC ADD-S": es.get("AUC ADD-S"),
                "wrong accepted": es.get("wrong accepted"), "scenes": es.get("scenes"),
                "negatives": es.get("negatives"),
                "join s": float(np.mean([r["join_s"] for r in two])) if two else None,
                "second / first s per frame": float(np.mean([r["s_per_frame"][1] / r["s_per_frame"][0] for r in two]))
                if two else None,
                "cpu with / without elsewhere": float(sum(r["cpu_ms"] for r in es_kind) /
                                                      sum(r["cpu_ms_without_elsewhere"] for r in es_kind))
                if es_kind else None,
                # the stages' seconds; not in the table: the process's first scan also compiles the kernels
                "scan s": float(np.mean([r["total_s"] for r in ss])),
            }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="three objects (one tune, two held-out), 5 scenes each")
    ap.add_argument("--split", default="all", choices=("all", "tune", "heldout"))
    ap.add_argument("--objects", default="", help="comma-separated object names (default: all of the split)")
    ap.add_argument("--views", type=int, default=12, help="views per capture")
    ap.add_argument("--scenes", type=int, default=None, help="positive scenes per object (default 10, quick 5)")
    ap.add_argument("--work", default="/tmp/gscan-bench-two-sided", help="cache of captures and templates")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = run(args)
    print("\n| split | template | objects | frames registered | wrong frames | joined | completeness % | bottom % | "
          "found % | found, not upright % | within 5 deg / 1 cm % | AUC ADD-S | wrong accepted (incl. negatives) | "
          "join s | s per frame, 2nd / 1st capture | CPU per estimate, with / without the search elsewhere |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")

    def f(v: float | None, fmt: str = ".1f") -> str:
        return "-" if v is None else format(v, fmt)

    for split, kinds in out["summary"].items():
        for kind, v in kinds.items():
            joined = "-" if v["joined"] is None else f"{v['joined']}/{v['objects']}"
            print(f"| {split} | {kind} | {v['objects']} | {v['registered']}/{v['frames']} | {v['wrong frames']} | "
                  f"{joined} | {f(v['completeness %'])} | "
                  f"{f(v['bottom %'])} | {f(v['found %'])} | {f(v['found not upright %'])} | "
                  f"{f(v['within 5deg/1cm %'])} | {f(v['AUC ADD-S'])} | {v['wrong accepted']} | {f(v['join s'])} | "
                  f"{f(v['second / first s per frame'], '.2f')} | {f(v['cpu with / without elsewhere'], '.2f')} |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
