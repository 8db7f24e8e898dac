"""Pose estimation of objects that look the same under a half turn, with their symmetries ignored and used
(gscan.estimate.symmetric), on the same rendered views in one run.

Objects (gscan.synth.cases), each a CAD template (36 views) whose "symmetries" meta is set from the builder:
- box alike: a box printed alike under a half turn about z, bottom too (the turn holds in shape and texture);
- can twice around: an upright can whose label shows its print twice (the half turn about z in texture; every turn
  about z and the flip in shape only);
- box, bottom differs: the box alike but with its own print on the bottom (the turn in shape only): resting on the
  table its bottom is hidden, so its views are exact ties, which must stay refused.

Views: the object resting on the newspaper table at a random turn, a camera at a random azimuth, 25-65 deg
elevation and 0.35-0.55 m (seeded). Each view is estimated by the estimator with `symmetry.enabled` false
("before": every equivalent pose a rival) and true with `symmetry.weigh_shape_turns` ("after"). A pose is wrong
when its ADD against the nearest of the ground truth's equivalents under the symmetries that hold in texture (none
for the bottom-differs box) exceeds 10 % of the object's diameter.

    python bench/symmetric.py            # 7 objects, 10 views each
    python bench/symmetric.py --quick    # one object of each kind, 4 views each
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscan.estimate.estimator import Estimator  # noqa: E402
from gscan.estimate.params import EstimateParams, SymmetryParams  # noqa: E402
from gscan.estimate.rivals import AMBIGUOUS  # noqa: E402
from gscan.evaluate.metrics import add  # noqa: E402
from gscan.io.camera import RGBDFrame  # noqa: E402
from gscan.scanning.cad import template_from_mesh  # noqa: E402
from gscan.synth import DEFAULT_INTRINSICS, save_textured_mesh, view_on_table  # noqa: E402
from gscan.synth.cases import half_turn_box, half_turn_can  # noqa: E402
from gscan.template.db import TemplateDB  # noqa: E402

# (kind, label, builder, arguments)
OBJECTS = [
    ("box alike", "0.16 x 0.10 x 0.06 m, print 3", half_turn_box, {"size_xyz": (0.16, 0.10, 0.06), "seed": 3}),
    ("can twice around", "r 35 mm, h 120 mm, print 2", half_turn_can, {"radius": 0.035, "height": 0.12, "seed": 2}),
    ("box, bottom differs", "0.16 x 0.10 x 0.06 m, print 3", half_turn_box,
     {"size_xyz": (0.16, 0.10, 0.06), "seed": 3, "bottom_alike": False}),
    ("box alike", "0.20 x 0.08 x 0.05 m, print 7", half_turn_box, {"size_xyz": (0.20, 0.08, 0.05), "seed": 7}),
    ("box alike", "0.12 x 0.09 x 0.07 m, print 11", half_turn_box, {"size_xyz": (0.12, 0.09, 0.07), "seed": 11}),
    ("can twice around", "r 45 mm, h 100 mm, print 9", half_turn_can, {"radius": 0.045, "height": 0.10, "seed": 9}),
    ("box, bottom differs", "0.12 x 0.09 x 0.07 m, print 11", half_turn_box,
     {"size_xyz": (0.12, 0.09, 0.07), "seed": 11, "bottom_alike": False}),
]
QUICK = OBJECTS[:3]
WRONG_ADD = 0.1  # of the diameter


def views(mesh, n: int, seed: int):
    """n views of the mesh resting on the table (module docstring): [(frame, T_cam_obj)]."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        yaw = rng.uniform(0, 2 * np.pi)
        el, az, dist = rng.uniform(25, 65), np.degrees(rng.uniform(0, 2 * np.pi)), rng.uniform(0.35, 0.55)
        r = view_on_table(mesh, yaw, az, el, dist, seed + i, [seed, i])
        out.append((RGBDFrame(f"{i:03d}", r.color, r.depth, DEFAULT_INTRINSICS), r.T_cam_obj))
    return out


def outcome(res, T_gt: np.ndarray, pts: np.ndarray, group: list[np.ndarray], diameter: float) -> str:
    """"found", "wrong", "ambiguous" or "refused" (another reason)."""
    if res.T_cam_obj is None:
        return "ambiguous" if (res.reason or "").startswith(AMBIGUOUS) else "refused"
    err = min(add(pts, res.T_cam_obj, T_gt @ S) for S in group)
    return "wrong" if err > WRONG_ADD * diameter else "found"


def run_object(tmp: Path, i: int, kind: str, builder, kw: dict, n_views: int) -> dict:
    mesh, sym = builder(**kw)
    tpl = tmp / f"obj{i}.gscan"
    template_from_mesh(save_textured_mesh(mesh, tmp / f"obj{i}.obj"), tpl, n_views=36)
    with TemplateDB.open(tpl, writable=True) as db:
        db.set_meta("symmetries", sym.to_json())
    ests = {"before": Estimator.from_path(tpl, EstimateParams(symmetry=SymmetryParams(enabled=False))),
            "after": Estimator.from_path(tpl, EstimateParams(symmetry=SymmetryParams(weigh_shape_turns=True)))}
    tex = sym.in_texture()
    group = [np.eye(4)] + list(tex.discrete)  # (the objects' texture symmetries are discrete)
    pts = mesh.vertices
    diameter = float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=2)))
    counts = {k: {"found": 0, "wrong": 0, "ambiguous": 0, "refused": 0, "marked": 0} for k in ests}
    ms: dict[str, list[float]] = {k: [] for k in ests}
    for frame, T_gt in views(mesh, n_views, 100 + i):
        for k, est in ests.items():
            res = est.estimate(frame)
            counts[k][outcome(res, T_gt, pts, group, diameter)] += 1
            counts[k]["marked"] += res.symmetry is not None
            ms[k].append(res.timings_ms["total"])
    return {"kind": kind, "views": n_views, "holds_in": sym.holds_in, **counts,
            "median_ms": {k: float(np.median(v)) for k, v in ms.items()}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="one object of each kind, 4 views each")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    objects, n_views = (QUICK, 4) if args.quick else (OBJECTS, 10)
    load, t0 = [os.getloadavg()[0]], time.time()
    rows = []
    with tempfile.TemporaryDirectory(prefix="gscan-sym-") as tmp:
        for i, (kind, label, builder, kw) in enumerate(objects):
            r = run_object(Path(tmp), i, kind, builder, kw, n_views) | {"object": label}
            rows.append(r)
            print(f"{kind} ({label}): before {r['before']}, after {r['after']}", flush=True)
    load.append(os.getloadavg()[0])
    print(f"\n{time.time() - t0:.0f} s, load average {load[0]:.1f} before, {load[1]:.1f} after; wrong: ADD to the "
          f"nearest equivalent above {WRONG_ADD:.0%} of the diameter")
    print("| object | kind | views | before: found | ambiguous | other refusals | wrong | after: found | ambiguous | "
          "other refusals | wrong | marked |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows + [total(rows)]:
        b, a = r["before"], r["after"]
        print(f"| {r['object']} | {r['kind']} | {r['views']} | {b['found']} | {b['ambiguous']} | {b['refused']} | "
              f"**{b['wrong']}** | {a['found']} | {a['ambiguous']} | {a['refused']} | **{a['wrong']}** | "
              f"{a['marked']} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    return 1 if any(r["after"]["wrong"] for r in rows) else 0  # (before: the estimator without symmetries)


def total(rows: list[dict]) -> dict:
    """The rows' counts summed."""
    out = {"object": "all", "kind": "", "views": sum(r["views"] for r in rows)}
    for k in ("before", "after"):
        out[k] = {c: sum(r[k][c] for r in rows) for c in rows[0][k]}
    return out


if __name__ == "__main__":
    sys.exit(main())
