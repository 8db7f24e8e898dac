"""Scan time per frame of this checkout against another git ref, as a ratio measured in one run.

The ref is checked out (`git worktree add --detach`) into a temporary folder outside the repository and removed
at the end. Every scan is a child process `python -m gscan.cli scan CAPTURE -o OUT --json` with PYTHONPATH set
to one of the two trees and a working directory outside both (so `-m` imports the tree PYTHONPATH names). For
each capture the two trees alternate (this, ref, ref, this, ...), `--repeats` times each, after one untimed
warm-up scan per tree (numba compiles its kernels into a fresh tree's cache on the first run); medians are
compared. Wall time per frame is the child's wall time over the capture's frame count; CPU is the child's user
+ system time (getrusage). Every scan's poses (each tree's own `gscan poses --json`) are compared with the
capture's ground truth: "wrong" counts frames registered beyond 5 deg or 2 cm (relative poses,
gscan.evaluate.metrics.frame_errors; the most of any repeat). The environment is the same for both (no thread
variable by default: each tree runs as a user would run it; `--one-thread` sets OPENBLAS_NUM_THREADS =
OMP_NUM_THREADS = 1 for both).

Captures: the bundled sample (30 frames, 640x480) and, with `--render N`, a static capture of N views of a
shared mesh rendered by this checkout's gscan.synth (640x480, two rings, newspaper table); or the folders given
with `--capture`. Both trees scan the same files.

    python bench/scan_speed.py --ref 8146a4d
    python bench/scan_speed.py --ref d0c7bd1 --render 36 --repeats 3 --json out.json
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
WRONG_DEG, WRONG_M = 5.0, 0.02  # rendered captures: a frame registered beyond either is at a wrong pose
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "MKL_NUM_THREADS",
               "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS", "NUMBA_NUM_THREADS")


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, check=True, capture_output=True, text=True).stdout.strip()


def scan_once(tree: Path, capture: Path, out: Path, env: dict[str, str], cwd: Path,
              extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """One `gscan scan` of `capture` (with the options `extra`) by the gscan in `tree`: wall s, CPU s, the
    summary's registered / frames and its stage timings."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(capture), "-o", str(out), "--json", *extra],
                       cwd=cwd, env=env | {"PYTHONPATH": str(tree)}, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{tree}: scan of {capture} failed ({p.returncode}): {p.stderr.strip()[-800:]}")
    s = json.loads(p.stdout)
    q = subprocess.run([sys.executable, "-m", "gscan.cli", "poses", str(out), "--json"], cwd=cwd,
                       env=env | {"PYTHONPATH": str(tree)}, capture_output=True, text=True, check=True)
    poses = {n: np.asarray(T, dtype=np.float64) for n, T in json.loads(q.stdout)["frames"].items()}
    out.unlink(missing_ok=True)
    return {"wall_s": wall, "cpu_s": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime),
            "registered": s.get("registered"), "frames": s.get("frames"), "timings_s": s.get("timings_s", {}),
            "wrong": wrong_frames(poses, capture)}


def wrong_frames(T_obj_cam: dict[str, np.ndarray], capture: Path) -> list[str] | None:
    """Registered frames beyond WRONG_DEG or WRONG_M of the capture's ground truth (relative poses,
    gscan.evaluate.metrics.frame_errors); None without ground truth."""
    from gscan.evaluate.metrics import frame_errors
    from gscan.geometry.transforms import inv_T
    from gscan.io import open_sequence

    gt = {n: inv_T(T) for n, T in (open_sequence(capture).gt_T_cam_obj or {}).items()}
    if not gt:
        return None
    names = [n for n in T_obj_cam if n in gt]
    return frame_errors({n: T_obj_cam[n] for n in names}, {n: gt[n] for n in names}).wrong(WRONG_DEG, WRONG_M)


def render(n: int, work: Path, data: Path) -> Path:
    from gscan.synth import load_textured_mesh, render_capture

    cap = work / f"crayola_{n}"
    render_capture(load_textured_mesh(data / "meshes" / "Crayola_Bonus_64_Crayons" / "model_0.obj"), cap, n,
                   mode="static", elevations_deg=(30.0, 55.0), seed=2)
    return cap


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ref", required=True, help="git ref to compare with (a commit, branch or tag)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--capture", type=Path, action="append", default=[], help="capture folder (repeatable)")
    ap.add_argument("--render", type=int, default=0, help="also a rendered static capture of N views")
    ap.add_argument("--data", type=Path,
                    default=Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data"),
                    help="the shared test data (meshes/)")
    ap.add_argument("--one-thread", action="store_true", help="OPENBLAS/OMP_NUM_THREADS=1 for both trees")
    ap.add_argument("--scan-args", default="", help="more options for both trees' `gscan scan` (one string)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    extra = tuple(shlex.split(args.scan_args))

    from gscan.demo import SAMPLES

    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS and k != "PYTHONPATH"}
    if args.one_thread:
        env |= {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    commit = git("rev-parse", args.ref)
    this = git("rev-parse", "HEAD") + (" (with uncommitted changes)" if git("status", "--porcelain") else "")
    work = Path(tempfile.mkdtemp(prefix="gscan-scan-speed-"))
    ref_tree = work / "ref"
    git("worktree", "add", "--detach", str(ref_tree), commit)
    rows: list[dict[str, Any]] = []
    runs: dict[str, Any] = {}
    load = [os.getloadavg()[0]]
    try:
        captures = [p.resolve() for p in args.capture] or [SAMPLES / "capture"]
        if args.render:
            captures.append(render(args.render, work, args.data))
        trees = {"this": ROOT, "ref": ref_tree}
        cwd = work / "cwd"
        cwd.mkdir()
        for cap in captures:
            for tree in trees.values():  # warm-up: numba's cache, the page cache
                scan_once(tree, cap, work / "warm.gscan", env, cwd, extra)
            res: dict[str, list[dict[str, Any]]] = {"this": [], "ref": []}
            for rep in range(args.repeats):
                for name in (("this", "ref") if rep % 2 == 0 else ("ref", "this")):
                    r = scan_once(trees[name], cap, work / f"{name}.gscan", env, cwd, extra)
                    res[name].append(r)
                    print(f"{cap.name} {name}: {r['wall_s']:.2f} s wall, {r['cpu_s']:.2f} s CPU, "
                          f"{r['registered']}/{r['frames']} registered, wrong {r['wrong']}", flush=True)
            runs[str(cap)] = res
            row: dict[str, Any] = {"capture": cap.name, "frames": res["this"][0]["frames"]}
            for name in trees:
                row[f"{name}_registered"] = res[name][0]["registered"]
                wrong = [r["wrong"] for r in res[name]]
                row[f"{name}_wrong"] = None if None in wrong else max(len(w) for w in wrong)
                for k in ("wall_s", "cpu_s"):
                    row[f"{name}_{k}"] = float(np.median([r[k] for r in res[name]]))
                stages = sorted({s for r in res[name] for s in r["timings_s"]})
                row[f"{name}_stages_s"] = {s: float(np.median([r["timings_s"].get(s, 0.0) for r in res[name]]))
                                           for s in stages}
            n = row["frames"] or 1
            row["this_wall_ms_per_frame"] = 1e3 * row["this_wall_s"] / n
            row["ref_wall_ms_per_frame"] = 1e3 * row["ref_wall_s"] / n
            row["wall_ratio"] = row["this_wall_s"] / row["ref_wall_s"]
            row["cpu_ratio"] = row["this_cpu_s"] / row["ref_cpu_s"]
            rows.append(row)
    finally:
        load.append(os.getloadavg()[0])
        subprocess.run(["git", "worktree", "remove", "--force", str(ref_tree)], cwd=ROOT, check=False,
                       capture_output=True)
        shutil.rmtree(work, ignore_errors=True)

    print(f"\nthis: {this}; ref: {args.ref} = {commit}; load average {load[0]:.1f} before, {load[1]:.1f} after; "
          f"medians of {args.repeats}{'; one BLAS/OpenMP thread for both' if args.one_thread else ''}"
          f"{f'; scan options {args.scan_args}' if extra else ''}")
    print(f"| capture | frames | registered (this / {args.ref}) | registered at a wrong pose (this / {args.ref}) | "
          f"this ms/frame | {args.ref} ms/frame | wall ratio | CPU ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['capture']} | {r['frames']} | {r['this_registered']} / {r['ref_registered']} | "
              f"{r['this_wrong']} / {r['ref_wrong']} | "
              f"{r['this_wall_ms_per_frame']:.0f} | {r['ref_wall_ms_per_frame']:.0f} | **{r['wall_ratio']:.2f}** | "
              f"{r['cpu_ratio']:.2f} |")
    for r in rows:
        for side in ("this", "ref"):
            stages = {k: round(v, 2) for k, v in r[f"{side}_stages_s"].items()}
            print(f"{r['capture']} stages (s, median) {side}: {json.dumps(stages)}")
    if args.json:
        args.json.write_text(json.dumps({"this": this, "ref": args.ref, "commit": commit, "load": load,
                                         "one_thread": args.one_thread, "scan_args": list(extra), "rows": rows,
                                         "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
