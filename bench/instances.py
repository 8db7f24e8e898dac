"""Every instance in one frame (`Estimator.estimate_all`): recall, precision, duplicates and wrong poses on rendered
piles, and the CPU per frame against the number of instances.

Each object gets a 36-view CAD template (gscan.scanning.cad.template_from_mesh of a shared mesh). Its piles
(gscan.synth.piles.render_pile) hold 2-5 copies side by side, touching or nearly, some lying on a side, seen
from 35-70 deg elevation and 0.6 m, and one copy of a distractor (another shared mesh, no template); each
object also has a negative scene (the distractor alone in a pile of other shared meshes). Objects are split
into a tuning set (the settings of `instances` were chosen on it) and a held-out set (run once).

Scored per split: an instance with at least 30 % of its silhouette in sight is found when a returned pose lies
within 5 deg / 1 cm of its ground truth (up to the template's symmetries that hold in shape and texture); a
returned pose near no instance is wrong (also in a negative), one near an instance already matched is a
duplicate. Recall: found / instances; precision: returned
poses that find an instance / returned.

BOP: each object's piles written as a BOP test split (`gscan.synth.piles.write_bop_piles`: the copies object 1, the
distractor object 2, test targets of the copies with at least 10 % in sight) and scored through `gscan eval`'s
`evaluate` (estimate_all up to each image's inst_count, the BOP toolkit's matching): BOP19's AR and its three
recalls, pooled over a split's objects (weighted by their instances scored, as one dataset's recall pools its
targets).

CPU: the process CPU time of `estimate_all` on each pile, as a ratio to the single `estimate` on the same frame
(timed right before it, same estimator: one call finds one instance); the median ratio per number of
instances in the pile. Every estimator estimates a first frame untimed (compiled kernels loaded).

    python bench/instances.py                     # both splits
    python bench/instances.py --split tune --json out.json
    python bench/instances.py --retries 1         # a refused search tried again
    python bench/instances.py --cpu-only          # the piles' CPU ratios and scores only: no negatives, no BOP
    python bench/instances.py --cpu-only --counts 1   # the same on piles of one copy
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from gscan.estimate.estimator import EstimateParams, Estimator
from gscan.evaluate.bop19 import evaluate
from gscan.io.camera import RGBDFrame
from gscan.synth import load_textured_mesh
from gscan.synth.piles import render_pile, write_bop_piles

MESHES = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"
SPLITS = {
    "tune": ["Crayola_Bonus_64_Crayons", "Little_Debbie_Cloud_Cakes_10_ct", "Frozen_Scrabble_Jr"],
    "held_out": ["Vans_Cereal_Honey_Nut_Crunch_11_oz_box", "Mattel_SKIP_BO_Card_Game",
                 "Crunch_Girl_Scouts_Candy_Bars_Peanut_Butter_Creme_78_oz_box"],
}
DISTRACTOR = "Whey_Protein_Chocolate_12_Packets"
NEGATIVE = ["Apples_to_Apples_Kids_Edition", "Clue_Board_Game_Classic_Edition"]
COUNTS = (2, 3, 4, 5)
MIN_VISIBLE = 0.3  # instances with less of their silhouette in sight are not counted (found or not)
BOP_METRICS = ("AR", "AR VSD", "AR MSSD", "AR MSPD")


def frame_of(pile) -> RGBDFrame:
    f = pile.frame
    return RGBDFrame("pile", f.color, f.depth, f.intrinsics)


def score(est: Estimator, results, truths: list[np.ndarray], visible: np.ndarray, deg: float = 5.0,
          dist: float = 0.01) -> dict:
    """found / wrong / duplicates of the returned poses against the instances' T_cam_obj [4 x 4] each; the
    instances to find are those with at least `MIN_VISIBLE` of their silhouette in sight (visible [K]), a pose of
    a less visible one is right but not counted as found."""
    matched: set[int] = set()
    wrong = dup = 0
    for r in results:
        errs = [est.verifier.apart(r.T_cam_obj, T) for T in truths]
        hit = [i for i, (d, m) in enumerate(errs) if d <= deg and m <= dist]
        if not hit:
            wrong += 1
        elif hit[0] in matched:
            dup += 1
        else:
            matched.add(hit[0])
    targets = {i for i in range(len(truths)) if visible[i] >= MIN_VISIBLE}
    return {"instances": len(targets), "found": len(matched & targets), "returned": len(results), "wrong": wrong,
            "duplicates": dup}


def run_object(name: str, seeds: int, root: Path, params: EstimateParams, cpu_only: bool = False,
               counts: tuple[int, ...] = COUNTS) -> dict:
    from gscan.scanning.cad import template_from_mesh

    tpl = root / f"{name}.gscan"
    template_from_mesh(MESHES / name / "model_0.obj", tpl, n_views=36)
    mesh = load_textured_mesh(MESHES / name / "model_0.obj")
    distractor = load_textured_mesh(MESHES / DISTRACTOR / "model_0.obj")
    est = Estimator.from_path(tpl, params)
    est.estimate(frame_of(render_pile([mesh], 999)))  # untimed: compiled kernels loaded
    rows = []
    piles = []
    for n in counts:
        for s in range(seeds):
            seed = 1000 * n + s
            pile = render_pile([mesh] * n + [distractor], seed)
            piles.append(pile)
            frame = frame_of(pile)
            c0 = time.process_time()
            est.estimate(frame)
            c1 = time.process_time()
            out = est.estimate_all(frame)
            c2 = time.process_time()
            row = score(est, out.results, list(pile.T_cam_objs[:n]), pile.visible[:n])
            row.update(n=n, seed=seed, cpu_single_ms=1e3 * (c1 - c0), cpu_all_ms=1e3 * (c2 - c1),
                       reason=out.reason)
            rows.append(row)
            print(f"{name[:24]:24s} n={n} seed={seed}: found {row['found']}/{row['instances']}, wrong {row['wrong']}, "
                  f"dup {row['duplicates']}, cpu all/single {row['cpu_all_ms']:.0f}/{row['cpu_single_ms']:.0f} ms",
                  file=sys.stderr)
    if cpu_only:
        return {"object": name, "rows": rows, "bop": None}
    negs = [load_textured_mesh(MESHES / m / "model_0.obj") for m in NEGATIVE] + [distractor]
    out = est.estimate_all(frame_of(render_pile(negs, 77)))
    rows.append({"n": 0, "seed": 77, "instances": 0, "found": 0, "returned": len(out.results),
                 "wrong": len(out.results), "duplicates": 0, "reason": out.reason})
    scene = write_bop_piles(piles, root / f"{name}_bop", [[1] * (len(p.meshes) - 1) + [2] for p in piles])
    rep = evaluate(tpl, scene.parent, root / f"{name}_bop.csv", params=params)
    bop = {"instances": len(rep.rows), "found": rep.n_found, **{k: rep.metrics[k] for k in BOP_METRICS}}
    print(f"{name[:24]:24s} BOP: AR {bop['AR']:.1f} over {bop['instances']} instances", file=sys.stderr)
    return {"object": name, "rows": rows, "bop": bop}


def summary(objects: list[dict]) -> dict:
    rows = [r for o in objects for r in o["rows"]]
    inst = sum(r["instances"] for r in rows)
    found = sum(r["found"] for r in rows)
    returned = sum(r["returned"] for r in rows)
    # a split's recalls pool its objects' instances
    weights = [o["bop"]["instances"] for o in objects if o["bop"] is not None]
    ratios = {n: float(np.median([r["cpu_all_ms"] / r["cpu_single_ms"] for r in rows if r["n"] == n]))
              for n in sorted({r["n"] for r in rows if r["n"] > 0})}
    return {"piles": sum(r["n"] > 0 for r in rows), "negatives": sum(r["n"] == 0 for r in rows), "instances": inst,
            "recall": found / max(1, inst), "precision": (returned - sum(r["wrong"] + r["duplicates"] for r in rows))
            / max(1, returned), "wrong": sum(r["wrong"] for r in rows),
            "duplicates": sum(r["duplicates"] for r in rows), "cpu_ratio_by_n": ratios,
            "median_cpu_single_ms": float(np.median([r["cpu_single_ms"] for r in rows if r["n"] > 0])),
            "bop": {k: float(np.average([o["bop"][k] for o in objects], weights=weights)) for k in BOP_METRICS}
            | {"instances": sum(weights)} if weights else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=["tune", "held_out", "both"], default="both")
    ap.add_argument("--seeds", type=int, default=2, help="piles per object and number of instances")
    ap.add_argument("--retries", type=int, default=None, help="estimate.instances.retries (default: the setting's)")
    ap.add_argument("--cpu-only", action="store_true", help="the piles only (CPU ratios, recall): no negatives, no BOP")
    ap.add_argument("--counts", type=int, nargs="+", default=list(COUNTS),
                    help="copies per pile (with --cpu-only, 1: the cost of estimate_all where there is one)")
    ap.add_argument("--json", type=Path, default=None, help="write the rows and the summary here")
    args = ap.parse_args()
    splits = list(SPLITS) if args.split == "both" else [args.split]
    params = EstimateParams()
    if args.retries is not None:
        params = replace(params, instances=replace(params.instances, retries=args.retries))
    report = {}
    with tempfile.TemporaryDirectory() as tmp:
        for split in splits:
            objects = [run_object(name, args.seeds, Path(tmp), params, args.cpu_only, tuple(args.counts))
                       for name in SPLITS[split]]
            report[split] = {"summary": summary(objects), "objects": objects}
    counts = " / ".join(str(n) for n in args.counts)
    print("| split | piles + negatives | instances | recall % | precision % | duplicates | wrong | "
          f"CPU ratio to one estimate, {counts} instances | BOP instances | BOP AR (VSD / MSSD / MSPD) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for split, rep in report.items():
        s = rep["summary"]
        ratios = " / ".join(f"{s['cpu_ratio_by_n'][n]:.2f}" for n in args.counts if n in s["cpu_ratio_by_n"])
        b = s["bop"]
        bop = "- | -" if b is None else \
            f"{b['instances']} | {b['AR']:.1f} ({b['AR VSD']:.1f} / {b['AR MSSD']:.1f} / {b['AR MSPD']:.1f})"
        print(f"| {split} | {s['piles']} + {s['negatives']} | {s['instances']} | {100 * s['recall']:.1f} | "
              f"{100 * s['precision']:.1f} | {s['duplicates']} | {s['wrong']} | {ratios} | {bop} |")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
