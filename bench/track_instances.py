"""Tracking every instance (`gscan track --all`, gscan.estimate.track_instances.InstanceTracker): CPU per frame
against the number of instances, as a ratio to the single-instance `Tracker` on one copy in the same run, and the
identities kept.

Each object gets a 16-view CAD template (gscan.scanning.cad.template_from_mesh of a shared mesh). For each count N
of copies, a rendered sequence (gscan.synth.piles.render_row_sequence: N copies upright in a row on a wood table,
3-4 cm apart, a static camera 50 deg above the table; the last copy slides 1 cm and turns 3 deg in every frame from
the fourth on) is tracked by `InstanceTracker` and by the single `Tracker` (which follows one of the copies).
Ratios: to the single `Tracker` on the one-copy sequence, and to the single `Tracker` on the same sequence (the
neighbours in the crop ICP and the keypoints work on cost every tracked object alike). CPU: the
process CPU time of each `step`, the least of `--rounds` runs of the same sequence (a fresh tracker each, the
trackers alternating): the first frame (the search that finds every instance) apart, then the mean of the others
(the instances held by their priors; every third frame checks keypoints). Identities: every pose within 5 deg /
1 cm of one copy, each identity on the same copy in every frame, all N found in the first frame.

    OPENBLAS_NUM_THREADS=1 python bench/track_instances.py
    python bench/track_instances.py --counts 1 2 3 --frames 10 --rounds 3 --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gscan.estimate import Estimator, Tracker
from gscan.estimate.track_instances import InstanceTracker
from gscan.geometry.transforms import pose_error
from gscan.io.camera import RGBDFrame
from gscan.synth import load_textured_mesh
from gscan.synth.piles import render_row_sequence

MESHES = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"
OBJECTS = ["Frozen_Scrabble_Jr", "Crayola_Bonus_64_Crayons"]


def timed_steps(tracker: Tracker | InstanceTracker, frames: list[RGBDFrame]) -> tuple[list, list[float]]:
    """The steps and the process CPU (ms) of each."""
    steps, cpu = [], []
    for f in frames:
        c0 = time.process_time()
        steps.append(tracker.step(f))
        cpu.append(1e3 * (time.process_time() - c0))
    return steps, cpu


def identities_ok(steps: list, truths: np.ndarray) -> tuple[bool, str]:
    """Every pose within 5 deg / 1 cm of one copy, each identity on one copy throughout, every copy found in the
    first frame (truths [F x N x 4 x 4])."""
    copy_of: dict[int, int] = {}
    for f, s in enumerate(steps):
        for i in s.instances:
            if i.result.T_cam_obj is None:
                continue
            near = [j for j in range(truths.shape[1])
                    if all(np.array(pose_error(i.result.T_cam_obj, truths[f, j])) <= (5.0, 0.01))]
            if not near:
                return False, f"frame {f}: identity {i.id} at no copy"
            if copy_of.setdefault(i.id, near[0]) != near[0]:
                return False, f"frame {f}: identity {i.id} swapped"
    if len(copy_of) != truths.shape[1] or len(steps[0].instances) != truths.shape[1]:
        return False, f"{len(copy_of)} identities for {truths.shape[1]} copies"
    return True, ""


def run_object(name: str, counts: list[int], n_frames: int, rounds: int, root: Path) -> dict:
    from gscan.scanning.cad import template_from_mesh

    tpl = root / f"{name}.gscan"
    template_from_mesh(MESHES / name / "model_0.obj", tpl, n_views=16)
    mesh = load_textured_mesh(MESHES / name / "model_0.obj")
    rows = []
    single_ms = None
    for n in counts:
        rs = render_row_sequence(mesh, n, n_frames, seed=20 + n, moving=n - 1, moves=range(3, n_frames),
                                 distance=0.8)
        frames = [RGBDFrame(f"{i:06d}", f.color, f.depth, f.intrinsics) for i, f in enumerate(rs.frames)]
        est = Estimator.from_path(tpl)
        est.estimate(frames[0])  # untimed: compiled kernels loaded
        cpu1, cpu = np.full(n_frames, np.inf), np.full(n_frames, np.inf)
        for _ in range(rounds):
            cpu1 = np.minimum(cpu1, timed_steps(Tracker(est), frames)[1])
            steps, c = timed_steps(InstanceTracker(est), frames)
            cpu = np.minimum(cpu, c)
        if n == 1:
            single_ms = float(cpu1[1:].mean())
        ok, why = identities_ok(steps, rs.T_cam_objs)
        rows.append({"n": n, "first_ms": float(cpu[0]), "mean_ms": float(cpu[1:].mean()),
                     "single_same_scene_ms": float(cpu1[1:].mean()),
                     "tracked": sum(i.status == "tracked" for s in steps for i in s.instances),
                     "identities_ok": ok, "why": why})
        print(f"{name[:24]:24s} n={n}: first {cpu[0]:.0f} ms, then {rows[-1]['mean_ms']:.0f} ms a frame, "
              f"identities {'ok' if ok else why}", file=sys.stderr)
    assert single_ms is not None, "the counts must include 1 (the single tracker's reference)"
    for r in rows:
        r["ratio"] = r["mean_ms"] / single_ms
        r["ratio_same_scene"] = r["mean_ms"] / r["single_same_scene_ms"]
    return {"object": name, "single_mean_ms": single_ms, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", nargs="+", default=OBJECTS)
    ap.add_argument("--counts", nargs="+", type=int, default=[1, 2, 3])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=3, help="runs of each sequence (the least CPU per frame kept)")
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        report = [run_object(name, sorted(set(args.counts) | {1}), args.frames, args.rounds, Path(tmp))
                  for name in args.objects]
    counts = [r["n"] for r in report[0]["rows"]]
    print("| object | single Tracker, 1 copy, CPU ms | "
          + " | ".join(f"{n} instance{'s' if n > 1 else ''}: x single on 1 copy / x single in the scene (first "
                       "frame ms)" for n in counts) + " |")
    print("|---|---|" + "---|" * len(report[0]["rows"]))
    for o in report:
        cells = " | ".join(f"{r['ratio']:.2f} / {r['ratio_same_scene']:.2f} ({r['first_ms']:.0f})"
                           + ("" if r["identities_ok"] else " !") for r in o["rows"])
        print(f"| {o['object']} | {o['single_mean_ms']:.0f} | {cells} |")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
