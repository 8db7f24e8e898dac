"""Recall of pose estimation with templates gscan scanned itself, on hard cases (thin, lying, small, curved, unseen).

Every object is scanned (gscan.scanning.pipeline) from a rendered 16-frame capture of it standing on a newspaper
table (orbit rings at 30 and 55 deg elevation); the template->ground-truth alignment is the mean of
T_obj_cam[f] @ T_cam_gt[f] over the capture's frames, never from a test scene. Query scenes are
rendered with the object among two shared meshes on another table (wood, fabric, plain or newspaper), whole
640x480 image, no mask, the camera 0.45 m or more from the object (the object spanning 25-45 % of the image
width otherwise), viewpoints leaving less than 30 % of the object visible re-drawn, in poses the scan did
not see:

- thin: a flat printed box 2.5-3 cm thick (gscan.synth.box_mesh), lying flat, seen from 15-80 deg elevation;
- side: an object lying on a side (turned 90 deg about a horizontal axis) relative to its scan;
- small: a small object (a shared mesh scaled to about 60 %) with few keypoints per view, upright or lying;
- curved: a can with a wrapped label (gscan.synth.mesh.cylinder_mesh), standing or lying on its side;
- between: an upright object seen between the scan's keyframes (azimuth halfway, elevation 12-20 or 68-80 deg).

Objects are split into a tuning set and a held-out set (other meshes, other textures, other sizes): the
estimator's acceptance was tuned on the first only. Every object also has one negative scene (its
distractors without it: a pose found there is wrong), and each thin box has a look-alike negative (a box of
the same size with another print, where the depth alone would confirm a pose).

Reported per split: found %, within 5 deg / 1 cm %, AUC ADD and ADD-S (0-10 cm, YCB-Video), and the wrong
poses accepted (found with ADD > 10 % of the diameter, or found at all in a negative scene).

With --compare DIR, another gscan tree (DIR holds its `gscan` package: a checkout of an older commit) estimates
every scene too, in a child process, each scene right after this tree's (both see the same load), with the same
templates: its rows are scored alike, and the table gains the ratio of this tree's median CPU per frame to
that tree's. Each estimator's first scene of an object is estimated once untimed before it is timed (the first
call of an older tree may load compiled kernels); so is this tree's without --compare.

    python bench/recall.py                         # both splits
    python bench/recall.py --split tune --json out.json
    git archive <commit> | tar -x -C /tmp/old; python bench/recall.py --compare /tmp/old
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscan.evaluate.metrics import add, adds, auc
from gscan.geometry.transforms import look_at, pose_error, rotvec_to_R, transform_points
from gscan.io.camera import RGBDFrame
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    TexturedMesh,
    box_mesh,
    default_distance,
    load_textured_mesh,
    place_distractors,
    procedural_box_texture,
    render_capture,
    rest_on_table,
)
from gscan.synth.mesh import cylinder_mesh

ROOT = Path(__file__).resolve().parents[1]
MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"  # as tests/conftest.py
DISTRACTOR_POOL = ("Apples_to_Apples_Kids_Edition", "Crunch_Girl_Scouts_Candy_Bars_Peanut_Butter_Creme_78_oz_box",
                   "Diet_Pepsi_Soda_Cola12_Pack_12_oz_Cans", "Nestle_Carnation_Cinnamon_Coffeecake_Kit_1913OZ",
                   "The_Coffee_Bean_Tea_Leaf_KCup_Packs_Jasmine_Green_Tea_16_count",
                   "Whey_Protein_Chocolate_12_Packets",
                   "Vans_Cereal_Honey_Nut_Crunch_11_oz_box", "ReadytoUse_Rolled_Fondant_Pure_White_24_oz_box")
QUERY_TABLES = ("wood", "fabric", "plain", "newspaper")
MIN_DISTANCE = 0.45  # m, camera to object centre (a RealSense sees nothing nearer than about 0.3 m)


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    split: str  # "tune" | "heldout"
    kind: str  # "thin" | "side" | "small" | "curved" | "between"
    source: str  # shared mesh name, "box:WxDxH:seed" or "can:R:H:seed"
    scale: float = 1.0


OBJECTS = (
    ObjectSpec("thinbox_a", "tune", "thin", "box:0.20x0.14x0.03:3"),
    ObjectSpec("scrabble_side", "tune", "side", "Frozen_Scrabble_Jr"),
    ObjectSpec("raisinets_small", "tune", "small", "Nestle_Raisinets_Milk_Chocolate_35_oz_992_g", 0.6),
    ObjectSpec("can_a", "tune", "curved", "can:0.035:0.12:5"),
    ObjectSpec("crayola_between", "tune", "between", "Crayola_Bonus_64_Crayons"),
    ObjectSpec("thinbox_b", "heldout", "thin", "box:0.17x0.12x0.025:8"),
    ObjectSpec("debbie_side", "heldout", "side", "Little_Debbie_Cloud_Cakes_10_ct"),
    ObjectSpec("herring_small", "heldout", "small", "Polar_Herring_Fillets_Smoked_Peppered_705_oz_total", 0.6),
    ObjectSpec("can_b", "heldout", "curved", "can:0.03:0.10:9"),
    ObjectSpec("cardboard_between", "heldout", "between", "Google_Cardboard_Original_package"),
    ObjectSpec("skipbo_side", "heldout", "side", "Mattel_SKIP_BO_Card_Game"),
    ObjectSpec("kotex_small", "heldout", "small", "Kotex_U_Barely_There_Liners_Thin_60_count", 0.7),
)


def distractor_pool() -> dict[str, TexturedMesh]:
    """The shared meshes the query scenes place around their targets, by name."""
    return {d: load_textured_mesh(MESHES / d / "model_0.obj") for d in DISTRACTOR_POOL}


def build_mesh(spec: ObjectSpec) -> TexturedMesh:
    """The object's textured mesh (mesh frame = ground-truth object frame)."""
    if spec.source.startswith("box:"):
        _, dims, seed = spec.source.split(":")
        return box_mesh(tuple(float(x) for x in dims.split("x")), procedural_box_texture(int(seed), (256, 384)),
                        name=spec.name)
    if spec.source.startswith("can:"):
        _, r, h, seed = spec.source.split(":")
        return cylinder_mesh(float(r), float(h), procedural_box_texture(int(seed), (256, 512)), name=spec.name)
    return load_textured_mesh(MESHES / spec.source / "model_0.obj", scale=spec.scale)


def lookalike_mesh(spec: ObjectSpec) -> TexturedMesh:
    """A box of the same size as a thin box with another print (negative scene)."""
    _, dims, seed = spec.source.split(":")
    return box_mesh(tuple(float(x) for x in dims.split("x")), procedural_box_texture(int(seed) + 1000, (256, 384)),
                    name=spec.name + "_lookalike")


def scan_template(spec: ObjectSpec, mesh: TexturedMesh, work: Path, frames: int) -> tuple[Path, np.ndarray]:
    """Scanned template of `mesh` (cached under `work`) and its T_obj_gt [4 x 4]."""
    from gscan.evaluate.bop19 import template_to_gt
    from gscan.io import open_sequence
    from gscan.scanning.api import scan

    cap, tpl = work / f"{spec.name}_cap{frames}", work / f"{spec.name}_scan{frames}.gscan"
    if not cap.exists():
        render_capture(mesh, cap, frames, seed=11)
    if not tpl.exists():
        scan(cap, tpl)
    return tpl, template_to_gt(tpl, open_sequence(cap).gt_T_cam_obj)


def query_pose(spec: ObjectSpec, mesh: TexturedMesh, rng: np.random.Generator, k: int) -> tuple[np.ndarray, float,
                                                                                                float]:
    """(R_world_obj, camera elevation deg, azimuth deg) of scene k of an object."""
    yaw = rotvec_to_R([0.0, 0.0, rng.uniform(0, 2 * np.pi)])
    el = rng.uniform(25, 70)
    az = rng.uniform(0, 360)
    if spec.kind == "thin":
        el = rng.uniform(15, 80)
        return yaw, el, az
    if spec.kind == "side" or (spec.kind in ("small", "curved") and k % 2 == 1):
        ax = [1.0, 0.0, 0.0] if k % 2 == 0 or spec.kind == "curved" else [0.0, 1.0, 0.0]
        sign = 1.0 if k // 2 % 2 == 0 else -1.0
        return yaw @ rotvec_to_R(sign * np.pi / 2 * np.asarray(ax)), el, az
    if spec.kind == "between":
        el = rng.uniform(12, 20) if k % 2 == 0 else rng.uniform(68, 80)
        az = 45.0 * int(rng.integers(0, 8)) + (11.25 if k % 2 == 0 else 33.75)  # between the two rings' keyframes
        return np.eye(3), el, az
    return yaw, el, az


def render_query(target: TexturedMesh, R_world_obj: np.ndarray, el: float, az: float, distractors: list[TexturedMesh],
                 seed: int, table_kind: str, with_target: bool = True, replace_target: TexturedMesh | None = None):
    """(RenderedFrame, T_cam_obj of the target's place) of a cluttered scene."""
    rng = np.random.default_rng([seed, 0x5CE])
    T_wt = rest_on_table(target, R_world_obj)
    d_poses = place_distractors(target, T_wt, distractors, rng)
    first = replace_target if replace_target is not None else target
    objs = ([(first, T_wt)] if with_target else []) + list(zip(distractors, d_poses, strict=True))
    scene = SynthScene(objs, seed=seed, table_kind=table_kind)
    alone = SynthScene([(target, T_wt)], table=False, seed=seed)
    c = transform_points(T_wt, target.center[None])[0]
    for attempt in range(20):  # viewpoints leaving less than 30 % of the target visible are re-drawn (seeded)
        if attempt:
            el = float(np.clip(el + rng.uniform(-10, 10), 10, 85))
            az = az + rng.uniform(20, 60)
        e, a = np.radians(el), np.radians(az)
        dist = max(MIN_DISTANCE, default_distance(target, fill=rng.uniform(0.25, 0.45)))
        eye = c + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        T_wc = look_at(eye, c)
        r = scene.render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng([seed, 1]))
        if not with_target or replace_target is not None:
            break
        full = alone.render(T_wc, DEFAULT_INTRINSICS, noise=False, shading=False).mask.sum()
        if r.mask.sum() >= 0.3 * max(1, int(full)):
            break
    return r, np.linalg.inv(T_wc) @ T_wt


def scenes_of(spec: ObjectSpec, oi: int, mesh: TexturedMesh, pool: dict[str, TexturedMesh], n: int):
    """Yields (label, RGBDFrame, T_cam_gt or None for a negative scene) for one object."""
    for k in range(n + 1 + (spec.kind == "thin")):
        seed = 100 * oi + k
        rng = np.random.default_rng([seed, 0xA11])
        names = [d for d in DISTRACTOR_POOL if d != spec.source]
        distractors = [pool[d] for d in rng.choice(names, 2, replace=False)]
        R, el, az = query_pose(spec, mesh, rng, k % n if k >= n else k)
        table = QUERY_TABLES[(oi + k) % len(QUERY_TABLES)]
        if k < n:
            r, T_gt = render_query(mesh, R, el, az, distractors, seed, table)
            yield f"{spec.name}/{k}", RGBDFrame(f"{spec.name}_{k}", r.color, r.depth, DEFAULT_INTRINSICS), T_gt
        elif k == n:  # negative: the distractors alone
            r, _ = render_query(mesh, R, el, az, distractors, seed, table, with_target=False)
            yield f"{spec.name}/empty", RGBDFrame(f"{spec.name}_empty", r.color, r.depth, DEFAULT_INTRINSICS), None
        else:  # negative: a look-alike box of the same size with another print
            r, _ = render_query(mesh, R, el, az, distractors, seed, table, replace_target=lookalike_mesh(spec))
            yield (f"{spec.name}/lookalike", RGBDFrame(f"{spec.name}_lookalike", r.color, r.depth, DEFAULT_INTRINSICS),
                   None)


class Compare:
    """The other tree's estimator (--compare), in a child process (bench/estimate_child.py): `estimate(tpl, frame,
    warm)` -> its JSON line."""

    def __init__(self, tree: str, work: Path):
        import os
        import subprocess

        self.tmp = work / "compare-frames"
        self.tmp.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve().with_name("estimate_child.py"))],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     env=dict(os.environ, PYTHONPATH=tree))

    def estimate(self, tpl: Path, frame: RGBDFrame, warm: bool) -> dict:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        npz = self.tmp / f"{frame.name}.npz"
        K = frame.intrinsics
        np.savez(npz, color=frame.color, depth=frame.depth, K=np.array([K.fx, K.fy, K.cx, K.cy, K.width, K.height]))
        self.proc.stdin.write(f"{tpl} {npz} {int(warm)}\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the compared tree's estimator failed")
        return json.loads(line)

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(60)


def score(rec: dict, T_cam_obj, T_obj_gt: np.ndarray, T_gt, mesh: TexturedMesh) -> dict:
    """`rec` with the pose's errors (add, adds, deg, cm), `wrong` and `within` filled in."""
    diameter = rec["diameter"]
    rec.update(found=T_cam_obj is not None, add=None, adds=None, deg=None, cm=None)
    if T_cam_obj is not None and T_gt is not None:
        T = np.asarray(T_cam_obj) @ T_obj_gt
        deg, m = pose_error(T, T_gt)
        rec.update(add=add(mesh.vertices, T, T_gt), adds=adds(mesh.vertices, T, T_gt), deg=deg, cm=100 * m)
    rec["wrong"] = bool(rec["found"] and (T_gt is None or rec["add"] > 0.1 * diameter))
    rec["within"] = bool(rec["found"] and T_gt is not None and rec["deg"] <= 5.0 and rec["cm"] <= 1.0)
    return rec


def summarise(recs: list[dict]) -> dict:
    """Per split: found %, within 5 deg / 1 cm %, AUC ADD / ADD-S, wrong accepted, median CPU ms."""
    summary = {}
    for split in ("tune", "heldout", "all"):
        rs = [r for r in recs if split == "all" or r["split"] == split]
        pos = [r for r in rs if r["positive"]]
        if not pos:
            continue
        inf = float("inf")
        summary[split] = {
            "scenes": len(pos), "negatives": len(rs) - len(pos),
            "found %": 100.0 * np.mean([r["found"] for r in pos]),
            "within 5deg/1cm %": 100.0 * np.mean([r["within"] for r in pos]),
            "AUC ADD": auc([r["add"] if r["found"] else inf for r in pos]),
            "AUC ADD-S": auc([r["adds"] if r["found"] else inf for r in pos]),
            "wrong accepted": int(sum(r["wrong"] for r in rs)),
            "median cpu ms": float(np.median([r["cpu_ms"] for r in rs])),
        }
    return summary


def run(args: argparse.Namespace) -> dict:
    from gscan.estimate.estimator import Estimator

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    pool = distractor_pool()
    recs: list[dict] = []
    old_recs: list[dict] = []
    compare = Compare(args.compare, work) if args.compare else None
    for oi, spec in enumerate(OBJECTS):
        if args.split != "all" and spec.split != args.split:
            continue
        if args.objects and spec.name not in args.objects.split(","):
            continue
        mesh = build_mesh(spec)
        tpl, T_obj_gt = scan_template(spec, mesh, work, args.scan_frames)
        est = Estimator.from_path(tpl)
        diameter = float(np.linalg.norm(mesh.extent))
        for k, (label, frame, T_gt) in enumerate(scenes_of(spec, oi, mesh, pool, args.scenes)):
            if k == 0:
                est.estimate(frame)  # untimed: the first call
            t0 = time.process_time()
            res = est.estimate(frame)
            cpu = (time.process_time() - t0) * 1e3
            base = {"scene": label, "split": spec.split, "kind": spec.kind, "positive": T_gt is not None,
                    "diameter": diameter}
            rec = score(dict(base, n_matches=res.n_matches, score=res.score, reason=res.reason, cpu_ms=cpu),
                        res.T_cam_obj, T_obj_gt, T_gt, mesh)
            recs.append(rec)
            err = ("not found: " + str(res.reason)) if not res.found else (
                "FOUND (negative scene)" if T_gt is None else f"{rec['deg']:.1f} deg {rec['cm']:.2f} cm")
            print(f"{label:26s} {spec.split:7s} n={res.n_matches:2d} score={res.score:.2f} {cpu:6.0f} ms  {err}",
                  file=sys.stderr, flush=True)
            if compare is not None:
                o = compare.estimate(tpl, frame, warm=k == 0)
                old_recs.append(score(dict(base, n_matches=o["n_matches"], reason=o["reason"], cpu_ms=o["cpu_ms"]),
                                      o["T_cam_obj"], T_obj_gt, T_gt, mesh))
    if compare is not None:
        compare.close()
    summary = summarise(recs)
    out: dict = {"summary": summary, "records": recs}
    if compare is not None:
        out.update(compare_tree=args.compare, compare_summary=summarise(old_recs), compare_records=old_recs)
        for split, v in summary.items():
            v["cpu / compare cpu"] = v["median cpu ms"] / out["compare_summary"][split]["median cpu ms"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", default="all", choices=("all", "tune", "heldout"))
    ap.add_argument("--objects", default="", help="comma-separated object names (default: all of the split)")
    ap.add_argument("--scenes", type=int, default=4, help="positive scenes per object")
    ap.add_argument("--scan-frames", type=int, default=16)
    ap.add_argument("--work", default="/tmp/gscan-bench-recall", help="cache of captures and scanned templates")
    ap.add_argument("--compare", default=None, help="another gscan tree that estimates every scene too")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = run(args)
    print("\n| tree | split | scenes | found % | within 5 deg / 1 cm % | AUC ADD | AUC ADD-S | wrong accepted "
          "(incl. negatives) | median CPU ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    for tree, summary in (("this", out["summary"]), (args.compare, out.get("compare_summary", {}))):
        for split, v in summary.items():
            print(f"| {tree} | {split} | {v['scenes']} + {v['negatives']} neg | {v['found %']:.1f} | "
                  f"{v['within 5deg/1cm %']:.1f} | {v['AUC ADD']:.1f} | {v['AUC ADD-S']:.1f} | {v['wrong accepted']} | "
                  f"{v['median cpu ms']:.0f} |")
    if args.compare:
        print("\nmedian CPU per frame, this tree / " + args.compare + ": "
              + ", ".join(f"{split} {v['cpu / compare cpu']:.2f}" for split, v in out["summary"].items()))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
