"""Benchmark of `gscan batch` (gscan.batch.run_batch): many captures on Ray against one after another.

8 rendered captures (the first --captures shared meshes, `gscan.synth.render_capture`, static, --views views on
two rings at 30 and 55 degrees, --width x 3/4 pixels) are scanned --repeats times in each of two modes, the
modes alternating (batch, one after another, batch, one after another, ...) because the machine is shared:
1. batch: `run_batch` on a local Ray runtime of --workers CPUs (its start and shutdown included), one task per
   capture, each scan in a child process of its own with one thread per pool;
2. one after another: `gscan.scan()` on each capture in this process, as a script looping over the captures
   would, with the scan's own threads.
An untimed scan of the first capture comes first (numba's on-disk cache is filled, this process's imports are
loaded), so neither mode pays a first compilation.
Reported per pair: both wall times, their ratio (one after another / batch), and the load average (`uptime`)
before and after each timed part; then the median ratio and its spread, the seconds of each capture in each
mode (and the CPU seconds of each one after another), the wall and CPU seconds a task's process spends before
its scan (interpreter and imports; measured alone, 3 times), the peak resident memory of each batch task's scan
process (ru_maxrss of that child, from wait4) and of this process, the Ray runtime's start-up and shutdown
(measured alone), the bytes each capture reads and writes (capture folder, template), and whether every template
equals the first sequential pass's (poses to 1e-9).

    python bench/batch.py --repeats 4      # 8 captures x 16 views, 320 x 240, 2 workers, 4 pairs
    python bench/batch.py --views 24 --width 640
The meshes are read from $GSCAN_TEST_DATA/meshes (default: ../shared/data beside the repository). Rendered
captures are cached under bench/out/batch/captures/; raw results go to --json (bench/out/batch.json).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscan.batch.jobs import child_env  # noqa: E402
from gscan.batch.runtime import ray_runtime  # noqa: E402
from gscan.batch.scan import run_batch  # noqa: E402
from gscan.scanning.api import scan  # noqa: E402
from gscan.synth import DEFAULT_INTRINSICS, load_textured_mesh, render_capture  # noqa: E402
from gscan.template.db import TemplateDB  # noqa: E402

MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"
OUT = ROOT / "bench" / "out" / "batch"
T = TypeVar("T")


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


def timed(fn: Callable[[], T]) -> tuple[T, float, str, str]:
    """(fn's result, its wall seconds, the load average before, after)."""
    before = load()
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0, before, load()


def sequential(caps: Path, names: list[str], out: Path) -> tuple[dict[str, float], dict[str, float]]:
    """Scan every capture one after another in this process: (wall seconds, CPU seconds) per capture."""
    seconds: dict[str, float] = {}
    cpu: dict[str, float] = {}
    for n in names:
        t0, c0 = time.perf_counter(), time.process_time()
        scan(caps / n, out / f"{n}.gscan")
        seconds[n], cpu[n] = time.perf_counter() - t0, time.process_time() - c0
    return seconds, cpu


def task_start(repeats: int = 3) -> tuple[float, float]:
    """(wall, CPU) seconds, medians, of what a batch task's process does before its scan: the interpreter and
    the scan's imports with one thread per pool (`gscan.batch.child`), in the environment the task gets."""
    walls, cpus = [], []
    code = "from gscan.batch.child import _limit_threads; _limit_threads()"
    for _ in range(repeats):
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", code], env=child_env(), cwd=ROOT, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        _, status, usage = os.wait4(proc.pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            sys.exit("the task start-up probe failed")
        walls.append(time.perf_counter() - t0)
        cpus.append(usage.ru_utime + usage.ru_stime)
    return float(np.median(walls)), float(np.median(cpus))


def start_ray(workers: int) -> None:
    """Start a local Ray runtime as `run_batch` does and shut it down."""
    with ray_runtime(None, workers):
        pass


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 2**20


def spread(xs: list[float]) -> str:
    return f"{np.median(xs):.1f} ({min(xs):.1f}-{max(xs):.1f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, default=8)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--width", type=int, default=320, help="image width (height 3/4 of it)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2, help="pairs (batch, one after another), at least 1")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "out" / "batch.json")
    args = ap.parse_args()
    if args.repeats < 1:
        sys.exit("--repeats must be at least 1")

    caps = render(args.captures, args.views, args.width)
    names = sorted(p.name for p in caps.iterdir() if p.is_dir())
    shutil.rmtree(OUT / "runs", ignore_errors=True)
    scan(caps / names[0], OUT / "runs" / "warmup.gscan")  # untimed: numba's cache and this process's imports
    rss_before_ray = rss_mb()
    _, ray_start_s, *ray_load = timed(partial(start_ray, args.workers))
    rss_after_ray = rss_mb()
    start_wall, start_cpu = task_start()

    pairs: list[dict[str, Any]] = []
    first_seq = OUT / "runs" / "sequential0"
    task_s: dict[str, list[float]] = {n: [] for n in names}
    seq_s: dict[str, list[float]] = {n: [] for n in names}
    seq_cpu: dict[str, list[float]] = {n: [] for n in names}
    task_peak: dict[str, list[float]] = {n: [] for n in names}
    failed: set[str] = set()
    identical = True
    for r in range(args.repeats):
        b_out, s_out = OUT / "runs" / f"batch{r}", OUT / "runs" / f"sequential{r}"
        report, b_s, b_before, b_after = timed(partial(run_batch, caps, b_out, workers=args.workers))
        (seconds, cpu), s_s, s_before, s_after = timed(partial(sequential, caps, names, s_out))
        rows = {row.name: row for row in report.rows}
        for n in names:
            if rows[n].status != "scanned":
                failed.add(n)
                continue
            task_s[n].append(rows[n].seconds)
            seq_s[n].append(seconds[n])
            seq_cpu[n].append(cpu[n])
            task_peak[n].append((rows[n].peak_rss_bytes or 0) / 2**20)
            identical &= same(first_seq / f"{n}.gscan", b_out / f"{n}.gscan")
            identical &= same(first_seq / f"{n}.gscan", s_out / f"{n}.gscan")
        pairs.append({"batch_s": b_s, "sequential_s": s_s, "ratio": s_s / b_s, "load_before_batch": b_before,
                      "load_after_batch": b_after, "load_before_sequential": s_before,
                      "load_after_sequential": s_after})
    seq_peak = rss_mb()

    ratios = [p["ratio"] for p in pairs]
    all_task = [t for n in names for t in task_s[n]]
    all_seq = [t for n in names for t in seq_s[n]]
    all_cpu = [t for n in names for t in seq_cpu[n]]
    peaks = [m for n in names for m in task_peak[n]]
    overhead = [a - b for n in names for a, b in zip(task_s[n], seq_s[n], strict=True)]
    cap_bytes = [folder_bytes(caps / n) for n in names]
    tpl_bytes = [(first_seq / f"{n}.gscan").stat().st_size for n in names if (first_seq / f"{n}.gscan").is_file()]
    out = {
        "captures": len(names), "views": args.views, "size": [args.width, args.width * 3 // 4],
        "workers": args.workers, "cpus": os.cpu_count(), "repeats": args.repeats, "pairs": pairs,
        "ratio_median": float(np.median(ratios)), "ratio_min": min(ratios), "ratio_max": max(ratios),
        "ray_start_shutdown_s": ray_start_s, "ray_start_load": ray_load,
        "per_capture_sequential_s": seq_s, "per_capture_sequential_cpu_s": seq_cpu, "per_capture_task_s": task_s,
        "task_peak_rss_mb": task_peak, "task_start_wall_s": start_wall, "task_start_cpu_s": start_cpu,
        "process_peak_rss_mb": {"after_warmup_scan": rss_before_ray, "after_ray_start": rss_after_ray,
                                "after_all": seq_peak},
        "failed": sorted(failed), "identical_poses": identical,
        "capture_mb_mean": float(np.mean(cap_bytes)) / 2**20, "template_mb_mean": float(np.mean(tpl_bytes)) / 2**20,
        "registered": {n: f"{rows[n].registered}/{rows[n].frames}" for n in names},
        "wrong_batch": {n: (rows[n].ground_truth or {}).get("wrong_frames") for n in names},
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=1))

    print(f"{len(names)} captures x {args.views} views at {args.width}x{args.width * 3 // 4}, {args.workers} workers, "
          f"{os.cpu_count()} CPUs, {args.repeats} pairs (batch first in each)")
    print("\n| pair | batch s | load before / after | one after another s | load before / after | ratio |")
    print("|---|---|---|---|---|---|")
    for k, p in enumerate(pairs, 1):
        print(f"| {k} | {p['batch_s']:.1f} | {p['load_before_batch']} / {p['load_after_batch']} | "
              f"{p['sequential_s']:.1f} | {p['load_before_sequential']} / {p['load_after_sequential']} | "
              f"{p['ratio']:.2f} |")
    print(f"\nratio one after another / batch: median {np.median(ratios):.2f}, spread {min(ratios):.2f}-"
          f"{max(ratios):.2f} over {len(ratios)} pairs")
    print(f"per capture s, median (min-max) over captures and pairs: one after another {spread(all_seq)} wall, "
          f"{spread(all_cpu)} CPU; batch task {spread(all_task)} wall (task minus the same capture one after another: "
          f"{spread(overhead)})")
    print(f"a task's process before its scan (interpreter, imports, thread limits): {start_wall:.1f} s wall, "
          f"{start_cpu:.1f} s CPU (median of 3)")
    print(f"peak memory per batch task (its scan process) MiB: median {np.median(peaks):.0f}, max {max(peaks):.0f}; "
          f"this process: {rss_before_ray:.0f} after the warm-up scan, {rss_after_ray:.0f} after a Ray start, "
          f"{seq_peak:.0f} at the end")
    print(f"Ray runtime start + shutdown alone: {ray_start_s:.1f} s (load {ray_load[0]} / {ray_load[1]}); "
          f"templates identical to the first pass one after another (poses 1e-9): {identical}; failed: "
          f"{sorted(failed) or 'none'}")
    print(f"per capture: {np.mean(cap_bytes) / 2**20:.1f} MiB read (capture), {np.mean(tpl_bytes) / 2**20:.1f} MiB "
          "written (template)")

    def n_wrong(w: dict[str, list[str] | None]) -> str:
        return "-" if any(v is None for v in w.values()) else str(sum(len(v or []) for v in w.values()))

    reg = sum(rows[n].registered or 0 for n in names)
    print(f"frames registered {reg}/{sum(rows[n].frames or 0 for n in names)}; registered at a wrong pose (5 deg / "
          f"2 cm): {n_wrong(out['wrong_batch'])} batch, {n_wrong(out['wrong_sequential'])} one after another")


if __name__ == "__main__":
    main()
