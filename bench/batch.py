"""Benchmark of `gscan batch` (gscan.batch.run_batch): many captures on Ray against one after another.

8 rendered captures (the first --captures shared meshes, `gscan.synth.render_capture`, static, --views views on
two rings at 30 and 55 degrees, --width x 3/4 pixels) are scanned twice in this one run:
1. one after another in this process (`gscan.scan()`, as a script looping over `gscan scan` would, with the
   scan's own two threads);
2. by `run_batch` on a local Ray runtime of --workers CPUs (its start and shutdown included), one task per
   capture, each scan in a child process with one thread per pool.
Reported: the wall times and their ratio, the seconds of each capture in each mode, the peak resident memory of
each batch task's scan process (ru_maxrss of that child, from wait4) and of this process after the sequential
scans, the Ray runtime's start-up (measured alone), the bytes each capture reads and writes (capture folder,
template), whether the batch's templates equal the sequential ones (poses to 1e-9), and the frames registered and
registered at a wrong pose (beyond 5 deg or 2 cm of the rendered ground truth, relative poses: the batch report's
ground-truth check, gscan.batch.facts, applied to the sequential templates too). The load average
(`uptime`) is recorded before and after: the machine is shared.

    python bench/batch.py                       # 8 captures x 16 views, 320 x 240, 2 workers
    python bench/batch.py --views 24 --width 640
Rendered captures are cached under bench/out/batch/captures/; raw results go to --json (bench/out/batch.json).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscan.batch.runtime import ray_runtime  # noqa: E402
from gscan.batch.scan import run_batch  # noqa: E402
from gscan.scan.api import scan  # noqa: E402
from gscan.synth import DEFAULT_INTRINSICS, load_textured_mesh, render_capture  # noqa: E402
from gscan.template.db import TemplateDB  # noqa: E402

MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"
OUT = ROOT / "bench" / "out" / "batch"


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} {five:.2f} {fifteen:.2f}"


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def render(n: int, views: int, width: int) -> Path:
    root = OUT / "captures" / f"{n}x{views}x{width}"
    intr = DEFAULT_INTRINSICS.scaled(width / DEFAULT_INTRINSICS.width)
    meshes = sorted(p for p in MESHES.iterdir() if (p / "model_0.obj").is_file())[:n]
    if len(meshes) < n:
        sys.exit(f"only {len(meshes)} meshes under {MESHES}")
    for k, m in enumerate(meshes):
        if not (root / m.name / "cam_K.txt").is_file():
            render_capture(load_textured_mesh(m / "model_0.obj"), root / m.name, views, mode="static",
                           elevations_deg=(30.0, 55.0), intr=intr, seed=k)
    return root


def poses(path: Path) -> dict[str, np.ndarray | None]:
    with TemplateDB.open(path) as db:
        return {v.name: v.T_obj_cam for v in db.views(load_images=False)}


def same(a: Path, b: Path) -> bool:
    pa, pb = poses(a), poses(b)
    if sorted(pa) != sorted(pb):
        return False
    for n, T in pa.items():
        U = pb[n]
        if (T is None) != (U is None) or (T is not None and np.max(np.abs(T - U)) > 1e-9):
            return False
    return True


def wrong_frames(capture: Path, template: Path) -> list[str] | None:
    """Frames of `template` registered beyond 5 deg / 2 cm of `capture`'s ground truth (None: no ground truth)."""
    from gscan.batch.facts import ground_truth_check, template_facts

    check = ground_truth_check(capture, template_facts(template))
    return None if check is None else check.wrong_frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, default=8)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--width", type=int, default=320, help="image width (height 3/4 of it)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "out" / "batch.json")
    args = ap.parse_args()

    caps = render(args.captures, args.views, args.width)
    names = sorted(p.name for p in caps.iterdir() if p.is_dir())
    seq_out, batch_out = OUT / "sequential", OUT / "batch"
    for d in (seq_out, batch_out):
        shutil.rmtree(d, ignore_errors=True)
    load_before = load()

    t0 = time.perf_counter()
    with ray_runtime(None, args.workers):
        pass
    ray_start_s = time.perf_counter() - t0

    seq_s: dict[str, float] = {}
    t0 = time.perf_counter()
    for n in names:
        t1 = time.perf_counter()
        scan(caps / n, seq_out / f"{n}.gscan")
        seq_s[n] = time.perf_counter() - t1
    sequential_s = time.perf_counter() - t0
    seq_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    load_mid = load()
    t0 = time.perf_counter()
    report = run_batch(caps, batch_out, workers=args.workers)
    batch_s = time.perf_counter() - t0
    load_after = load()

    rows = {r.name: r for r in report.rows}
    failed = [r.name for r in report.rows if r.status != "scanned"]
    identical = all(same(seq_out / f"{n}.gscan", batch_out / f"{n}.gscan") for n in names if n not in failed)
    peaks = [r.peak_rss_bytes / 2**20 for r in report.rows if r.peak_rss_bytes]
    task_s = [rows[n].seconds for n in names]
    cap_bytes = [folder_bytes(caps / n) for n in names]
    tpl_bytes = [(batch_out / f"{n}.gscan").stat().st_size for n in names if (batch_out / f"{n}.gscan").is_file()]
    out = {
        "captures": len(names), "views": args.views, "size": [args.width, args.width * 3 // 4],
        "workers": args.workers, "cpus": os.cpu_count(), "load_before": load_before, "load_mid": load_mid,
        "load_after": load_after, "sequential_s": sequential_s, "batch_s": batch_s,
        "ratio": sequential_s / batch_s, "ray_start_s": ray_start_s,
        "per_capture_sequential_s": seq_s, "per_capture_task_s": {n: rows[n].seconds for n in names},
        "task_peak_rss_mb": {n: (rows[n].peak_rss_bytes or 0) / 2**20 for n in names},
        "sequential_process_peak_rss_mb": seq_peak / 2**20, "failed": failed, "identical_poses": identical,
        "capture_mb_mean": float(np.mean(cap_bytes)) / 2**20, "template_mb_mean": float(np.mean(tpl_bytes)) / 2**20,
        "registered": {n: f"{rows[n].registered}/{rows[n].frames}" for n in names},
        "wrong_batch": {n: (rows[n].ground_truth or {}).get("wrong_frames") for n in names},
        "wrong_sequential": {n: wrong_frames(caps / n, seq_out / f"{n}.gscan") for n in names},
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=1))

    print(f"{len(names)} captures x {args.views} views at {args.width}x{args.width * 3 // 4}, {args.workers} workers, "
          f"{os.cpu_count()} CPUs; load (1/5/15 min) before {load_before}, between {load_mid}, after {load_after}")
    print("\n| mode | wall s | per capture s (median, min-max) | peak memory MiB |")
    print("|---|---|---|---|")
    s = list(seq_s.values())
    print(f"| one after another (`gscan.scan()` in one process) | {sequential_s:.1f} | {np.median(s):.1f} "
          f"({min(s):.1f}-{max(s):.1f}) | {seq_peak / 2**20:.0f} (the process) |")
    print(f"| `run_batch`, local Ray, {args.workers} workers | {batch_s:.1f} | {np.median(task_s):.1f} "
          f"({min(task_s):.1f}-{max(task_s):.1f}) | {np.median(peaks):.0f} median, {max(peaks):.0f} max (per task) |")
    print(f"\nratio sequential / batch: {sequential_s / batch_s:.2f}; Ray runtime start + shutdown alone: "
          f"{ray_start_s:.1f} s; templates identical to the sequential ones (poses 1e-9): {identical}; "
          f"failed: {failed or 'none'}")
    print(f"per capture: {np.mean(cap_bytes) / 2**20:.1f} MiB read (capture), {np.mean(tpl_bytes) / 2**20:.1f} MiB "
          "written (template)")

    def n_wrong(w: dict[str, list[str] | None]) -> str:
        return "-" if any(v is None for v in w.values()) else str(sum(len(v or []) for v in w.values()))

    reg = sum(rows[n].registered or 0 for n in names)
    print(f"frames registered {reg}/{sum(rows[n].frames or 0 for n in names)}; registered at a wrong pose (5 deg / "
          f"2 cm): {n_wrong(out['wrong_batch'])} batch, {n_wrong(out['wrong_sequential'])} one after another")


if __name__ == "__main__":
    main()
