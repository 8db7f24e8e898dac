"""CPU and wall time of `gscan scan` and `gscan estimate` on the bundled sample with one BLAS / OpenMP thread
(the rule of gscan's processes, gscan.threads) against the libraries' default (one thread per core), as
ratios measured in one run.

Each run is a child process `python -m gscan.cli ...` of this checkout; the two settings alternate, `--repeats`
times each, and the medians are compared. "one thread" is the environment without any thread variable (gscan
applies its rule); "cores" names the count (OPENBLAS_NUM_THREADS = OMP_NUM_THREADS = the CPUs this process may
use), which the rule leaves to the libraries: what every command ran with before the rule. CPU is the child's
user + system time (getrusage). The estimate runs `gscan estimate --json` on each of the sample's held-out
frames against the template the first scan wrote (one process per frame: start-up and template loading
included). `--opencv-one` adds a third setting: one thread also in OpenCV's own pool (OPENCV_FOR_THREADS_NUM).

    python bench/threads.py                     # 3 repeats
    python bench/threads.py --repeats 5 --json out.json
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscan.threads import BLAS_ENV, THREAD_ENV  # noqa: E402


def settings(opencv_one: bool) -> dict[str, dict[str, str]]:
    base = {k: v for k, v in os.environ.items() if k not in BLAS_ENV and k not in THREAD_ENV
            and k != "OPENCV_FOR_THREADS_NUM"}
    base["PYTHONPATH"] = str(ROOT)
    cores = str(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    out = {"one thread": dict(base), "cores": base | {"OPENBLAS_NUM_THREADS": cores, "OMP_NUM_THREADS": cores}}
    if opencv_one:
        out["one thread + OpenCV 1"] = base | {"OPENCV_FOR_THREADS_NUM": "1"}
    return out


def timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float, str]:
    """(CPU s, wall s, stdout) of one child process."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, check=False, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-500:]}")
    return (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), wall, p.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--opencv-one", action="store_true", help="also a setting with one OpenCV thread")
    ap.add_argument("--json", type=Path, help="write the measurements here")
    args = ap.parse_args()

    from gscan.demo import SAMPLES

    modes = settings(args.opencv_one)
    heldout = sorted((SAMPLES / "heldout" / "rgb").iterdir())
    times: dict[str, dict[str, list[tuple[float, float]]]] = {m: {"scan": [], "estimate": []} for m in modes}
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        tpl = Path(tmp) / "sample.gscan"
        for rep in range(args.repeats):
            order = list(modes) if rep % 2 == 0 else list(reversed(modes))
            for m in order:
                out = Path(tmp) / f"{rep}-{len(times[m]['scan'])}.gscan"
                cpu, wall, stdout = timed([sys.executable, "-m", "gscan.cli", "scan", str(SAMPLES / "capture"),
                                           "-o", str(out), "--json"], modes[m])
                reg = json.loads(stdout)["registered"]
                times[m]["scan"].append((cpu, wall))
                if not tpl.exists():
                    out.replace(tpl)
                else:
                    out.unlink()
                print(f"scan     {m:>22}: {cpu:6.2f} s CPU {wall:6.2f} s wall ({reg} registered)", flush=True)
            for m in order:
                cpu_sum = wall_sum = 0.0
                for rgb in heldout:
                    depth = SAMPLES / "heldout" / "depth" / (rgb.stem + ".png")
                    cpu, wall, _ = timed([sys.executable, "-m", "gscan.cli", "estimate", str(tpl), "--color", str(rgb),
                                          "--depth", str(depth), "--intrinsics", str(SAMPLES / "heldout" / "cam_K.txt"),
                                          "--json"], modes[m])
                    cpu_sum += cpu
                    wall_sum += wall
                times[m]["estimate"].append((cpu_sum / len(heldout), wall_sum / len(heldout)))
                print(f"estimate {m:>22}: {cpu_sum / len(heldout):6.2f} s CPU {wall_sum / len(heldout):6.2f} s wall "
                      "per frame", flush=True)
    load.append(os.getloadavg()[0])

    base = "cores"
    rows = []
    for task in ("scan", "estimate"):
        for m in modes:
            cpu = float(np.median([c for c, _ in times[m][task]]))
            wall = float(np.median([w for _, w in times[m][task]]))
            b_cpu = float(np.median([c for c, _ in times[base][task]]))
            b_wall = float(np.median([w for _, w in times[base][task]]))
            rows.append({"task": task, "setting": m, "cpu_s": cpu, "wall_s": wall, "cpu_ratio": cpu / b_cpu,
                         "wall_ratio": wall / b_wall})
    print(f"\nload average {load[0]:.1f} before, {load[1]:.1f} after; medians of {args.repeats}; "
          f"estimate: per held-out frame, one process each")
    print("| command | setting | CPU s | wall s | CPU / cores | wall / cores |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['task']} | {r['setting']} | {r['cpu_s']:.2f} | {r['wall_s']:.2f} | {r['cpu_ratio']:.2f} | "
              f"{r['wall_ratio']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps({"load": load, "repeats": args.repeats, "rows": rows, "runs": times},
                                        indent=1))


if __name__ == "__main__":
    main()
