"""Scans of rendered captures made to resemble what scanners get wrong on real data (gscan.synth.cases), gscan at
its defaults against the SIFT + ratio + RANSAC + ICP odometry chain (bench/peers.py) on the same frames, in one
run: registered frames, frames registered at a wrong pose (beyond 5 deg or 2 cm of the ground truth relative to
the other registered frames, gscan.evaluate.metrics.frame_errors) and ATE.

Two splits:
- development: the captures tests/test_scan_hard.py scans (the Whey box 1.5-2.5 m away on newspaper and wood,
  a glossy can with a curved label static and on a turntable, two rings of 20-degree steps joined by a 25-degree
  jump, depth shifted 4-5 px against colour, a colour camera of 0.9 times the given focal length); the pipeline
  was developed against these;
- held out: the same kinds of capture of other shared meshes, other seeds and distances, never looked at while
  developing (`HELD_OUT`): what the development split's figures are worth.

The peer reads each capture as given (its depth_max: the capture's distance plus a metre). Captures are rendered
into a temporary folder (640x480) and removed.

    python bench/hard.py                  # both splits
    python bench/hard.py --split held-out --json out.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"
WRONG_DEG, WRONG_M = 5.0, 0.02

# (name, mesh, builder arguments): builders are gscan.synth.cases' functions, called as builder(mesh, folder, **kw)
DEVELOPMENT = [
    ("far 1.5 m, newspaper", "Whey_Protein_Chocolate_12_Packets", "far_capture", {"distance": 1.5}),
    ("far 2.0 m, newspaper", "Whey_Protein_Chocolate_12_Packets", "far_capture", {"distance": 2.0}),
    ("far 2.5 m, newspaper", "Whey_Protein_Chocolate_12_Packets", "far_capture", {"distance": 2.5}),
    ("far 1.5 m, wood", "Whey_Protein_Chocolate_12_Packets", "far_capture", {"distance": 1.5, "table_kind": "wood"}),
    ("far 2.0 m, wood", "Whey_Protein_Chocolate_12_Packets", "far_capture", {"distance": 2.0, "table_kind": "wood"}),
    ("glossy can, turntable", None, "glossy_can_capture", {"n_views": 24, "mode": "turntable",
                                                           "table_kind": "plain"}),
    ("glossy can, static", None, "glossy_can_capture", {"n_views": 16, "mode": "static", "table_kind": "plain"}),
    ("two rings, 25 deg jump", "Whey_Protein_Chocolate_12_Packets", "ring_jump_capture", {"table_kind": "plain"}),
    ("depth shifted (5, 0) px", "Whey_Protein_Chocolate_12_Packets", "shifted_depth_capture",
     {"shift_px": (5, 0), "table_kind": "plain"}),
    ("depth shifted (-4, 3) px", "Whey_Protein_Chocolate_12_Packets", "shifted_depth_capture",
     {"shift_px": (-4, 3), "table_kind": "newspaper"}),
    ("colour camera 0.9x", "Whey_Protein_Chocolate_12_Packets", "two_camera_capture", {"colour_scale": 0.9}),
]
HELD_OUT = [
    ("far 1.5 m, wood", "Nestle_Carnation_Cinnamon_Coffeecake_Kit_1913OZ", "far_capture",
     {"distance": 1.5, "table_kind": "wood", "seed": 5}),
    ("far 1.8 m, wood", "Vans_Cereal_Honey_Nut_Crunch_11_oz_box", "far_capture",
     {"distance": 1.8, "table_kind": "wood", "seed": 6}),
    ("far 2.2 m, newspaper", "Clue_Board_Game_Classic_Edition", "far_capture", {"distance": 2.2, "seed": 7}),
    ("far 1.6 m, newspaper, 12 views", "Little_Debbie_Cloud_Cakes_10_ct", "far_capture",
     {"distance": 1.6, "n_views": 12, "seed": 8}),
    ("glossy can, static, another label", None, "glossy_can_capture",
     {"n_views": 16, "mode": "static", "table_kind": "newspaper", "seed": 9}),
    ("two rings, 25 deg jump", "Crayola_Bonus_64_Crayons", "ring_jump_capture", {"table_kind": "wood", "seed": 10}),
    ("depth shifted (0, 5) px", "Frozen_Scrabble_Jr", "shifted_depth_capture",
     {"shift_px": (0, 5), "table_kind": "wood", "seed": 11}),
    ("colour camera 1.1x", "Nestle_Raisinets_Milk_Chocolate_35_oz_992_g", "two_camera_capture",
     {"colour_scale": 1.1, "seed": 12}),
]


def build(folder: Path, mesh_name: str | None, builder: str, kw: dict):
    """The capture (gscan.synth.cases.Case) written into `folder`."""
    from gscan.synth import cases, load_textured_mesh

    fn: Callable = getattr(cases, builder)
    if mesh_name is None:  # the glossy can is built by the case itself
        return fn(folder, **kw)
    return fn(load_textured_mesh(MESHES / mesh_name / "model_0.obj"), folder, **kw)


def score(poses: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> dict:
    from gscan.evaluate.metrics import ate, frame_errors

    names = [n for n in gt if poses.get(n) is not None]
    out: dict = {"frames": len(gt), "registered": len(names), "wrong": [], "ate_mm": float("nan")}
    if len(names) >= 2:
        mine, truth = {n: np.asarray(poses[n]) for n in names}, {n: gt[n] for n in names}
        out["wrong"] = frame_errors(mine, truth).wrong(WRONG_DEG, WRONG_M)
        out["ate_mm"] = 1e3 * ate([mine[n] for n in names], [truth[n] for n in names]).rmse
    return out


def run_case(work: Path, name: str, mesh_name: str | None, builder: str, kw: dict) -> dict:
    from peers import sift_ransac_icp_chain

    from gscan.geometry.transforms import inv_T
    from gscan.io import open_sequence
    from gscan.scanning.api import scan
    from gscan.template.db import TemplateDB

    case = build(work / "capture", mesh_name, builder, kw)
    seq = open_sequence(case.path)
    gt = {n: inv_T(T) for n, T in seq.gt_T_cam_obj.items() if n in case.object_frames}
    t = time.perf_counter()
    scan(case.path, work / "scan.gscan", force=True)
    secs = time.perf_counter() - t
    with TemplateDB.open(work / "scan.gscan") as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    frames = [seq[n] for n in seq.names]
    depth_max = float(max(np.median(f.depth[f.depth > 0]) for f in frames)) + 1.0
    peer = sift_ransac_icp_chain(frames, depth_max)
    return {"case": name, "mesh": mesh_name or "glossy can", "gscan": score(poses, gt) | {"seconds": secs},
            "peer": score({n: T for n, T in peer.T_world_cam.items() if T is not None}, gt)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=("development", "held-out", "both"), default="both")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    splits = {"development": DEVELOPMENT, "held-out": HELD_OUT}
    chosen = list(splits) if args.split == "both" else [args.split]
    rows = []
    load = [os.getloadavg()[0]]
    for split in chosen:
        for name, mesh_name, builder, kw in splits[split]:
            with tempfile.TemporaryDirectory(prefix="gscan-hard-") as tmp:
                r = run_case(Path(tmp), name, mesh_name, builder, kw) | {"split": split}
            rows.append(r)
            g, p = r["gscan"], r["peer"]
            print(f"{split} | {name} | {r['mesh']}: gscan {g['registered']}/{g['frames']} wrong {len(g['wrong'])} "
                  f"ATE {g['ate_mm']:.1f} mm; peer {p['registered']}/{p['frames']} wrong {len(p['wrong'])} "
                  f"ATE {p['ate_mm']:.1f} mm", flush=True)
    load.append(os.getloadavg()[0])
    print(f"\nload average {load[0]:.1f} before, {load[1]:.1f} after; wrong: beyond {WRONG_DEG:g} deg or "
          f"{1e3 * WRONG_M:g} mm of the ground truth (relative poses)")
    print("| split | capture | mesh | gscan registered | gscan registered at a wrong pose | gscan ATE mm | "
          "chain registered | chain registered at a wrong pose | chain ATE mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        g, p = r["gscan"], r["peer"]
        print(f"| {r['split']} | {r['case']} | {r['mesh']} | {g['registered']} / {g['frames']} | "
              f"**{len(g['wrong'])}** | {g['ate_mm']:.1f} | {p['registered']} / {p['frames']} | {len(p['wrong'])} | "
              f"{p['ate_mm']:.1f} |")
    for split in chosen:
        got = [r for r in rows if r["split"] == split]
        print(f"{split}: gscan {sum(r['gscan']['registered'] for r in got)} / {sum(r['gscan']['frames'] for r in got)}"
              f" registered, {sum(len(r['gscan']['wrong']) for r in got)} wrong; chain "
              f"{sum(r['peer']['registered'] for r in got)} registered, {sum(len(r['peer']['wrong']) for r in got)} "
              "wrong")
    if args.json:
        args.json.write_text(json.dumps({"load": load, "rows": rows}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
