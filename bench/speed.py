"""Per-frame CPU and wall time of pose estimation, four ways, on the same rendered frames (640x480, whole image,
no mask), as ratios against one `gscan estimate` command measured in the same run:

- cli: `python -m gscan.cli estimate T --color C --depth D --intrinsics K --json`, one process per frame (CPU of
  the child process, from getrusage);
- warm: one `Estimator` loaded once, `estimate(frame)` per frame (frames already in memory);
- service: `gscan serve T` started once, each frame posted by gscan.client as PNG bytes (wall: request to
  response; CPU: the server process's CPU during the request, from /proc, plus the client's);
- track: `Tracker.step` per frame through the sequence (the previous pose as a prior), and, on the same frames,
  independent warm estimates (the tracking speed-up).

The frames: a template scanned by gscan (gscan.scan.pipeline) from a rendered 16-frame capture of a shared mesh
standing on a newspaper table; a sequence in which that object slides 6 mm and turns 2.3 deg per frame on a
wood table between two other shared meshes, seen by a static camera. The load average (`uptime`) is recorded
before and after: the machine is shared.

    python bench/speed.py                       # 24 frames, 10 CLI calls
    python bench/speed.py --frames 40 --cli 20 --json out.json
    PYTHONPATH=OLD python bench/speed.py --modes cli,warm     # an older gscan (no tracker, no service)
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT.parent / "shared" / "data" / "meshes"
TARGET = "Crayola_Bonus_64_Crayons"
DISTRACTORS = ("Little_Debbie_Cloud_Cakes_10_ct", "Whey_Protein_Chocolate_12_Packets")


def load_average() -> float:
    return float(os.getloadavg()[0])


def stats(xs: list[float]) -> dict[str, float]:
    return {"median": float(np.median(xs)), "p90": float(np.percentile(xs, 90))}


def scanned_template(work: Path) -> Path:
    from gscan.scan.api import scan
    from gscan.synth import load_textured_mesh, render_capture

    cap, tpl = work / "capture", work / "target.gscan"
    if not tpl.exists():
        render_capture(load_textured_mesh(MESHES / TARGET / "model_0.obj"), cap, 16, seed=11)
        scan(cap, tpl)
    return tpl


def render_sequence(n: int, out: Path):
    """The moving-object sequence (RenderedFrames), written as PNG files (capture layout) under `out`."""
    from gscan.geometry.transforms import look_at, make_T, rotvec_to_R, transform_points
    from gscan.synth import (
        DEFAULT_INTRINSICS,
        SynthScene,
        load_textured_mesh,
        place_distractors,
        rest_on_table,
        write_capture,
    )

    target = load_textured_mesh(MESHES / TARGET / "model_0.obj")
    others = [load_textured_mesh(MESHES / d / "model_0.obj") for d in DISTRACTORS]
    T0 = rest_on_table(target, rotvec_to_R([0.0, 0.0, 0.3]))
    scene = SynthScene([(target, T0)] + list(zip(others, place_distractors(target, T0, others,
                                                                          np.random.default_rng(0), gap=0.06))),
                       seed=3, table_kind="wood")
    c = transform_points(T0, target.center[None])[0]
    el, az = 0.8, -1.2
    T_wc = look_at(c + 0.6 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]), c)
    frames = []
    for i in range(n):
        R = rotvec_to_R([0.0, 0.0, np.radians(2.3 * i)])
        T = make_T(R, c - R @ c + np.array([0.006 * i, 0.002 * i, 0.0])) @ T0
        frames.append(scene.render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng([3, i]),
                                   T_world_obj_override=T))
    write_capture(out, frames, DEFAULT_INTRINSICS, write_masks=False)
    return frames


def proc_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(args: argparse.Namespace) -> dict:
    from gscan.estimate.estimator import Estimator
    from gscan.io import open_sequence

    modes = args.modes.split(",")

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    tpl = scanned_template(work)
    tmp = Path(tempfile.mkdtemp(prefix="speed-", dir=work))
    render_sequence(args.frames, tmp / "seq")
    seq = open_sequence(tmp / "seq")
    frames = [seq[n] for n in seq.names]
    files = [(seq.files(n).color, seq.files(n).depth) for n in seq.names]
    K = tmp / "seq" / "cam_K.txt"
    out: dict = {"load_before": load_average(), "frames": len(frames), "template": str(tpl)}
    env = dict(os.environ, PYTHONPATH=str(ROOT))

    # cli: one process per frame
    cpu, wall = [], []
    for c, d in files[: args.cli]:
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "gscan.cli", "estimate", str(tpl), "--color", str(c), "--depth",
                            str(d), "--intrinsics", str(K), "--json"], capture_output=True, env=env, check=False)
        wall.append((time.perf_counter() - t0) * 1e3)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append((r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime) * 1e3)
        if p.returncode != 0:
            raise RuntimeError(p.stderr.decode())
    out["cli"] = {"cpu_ms": stats(cpu), "wall_ms": stats(wall)}

    # warm estimator
    est = Estimator.from_path(tpl)
    cpu, wall, found = [], [], 0
    for f in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        res = est.estimate(f)
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - t0) * 1e3)
        found += res.found
    out["warm"] = {"cpu_ms": stats(cpu), "wall_ms": stats(wall), "found": found}
    independent_cpu = cpu

    if "track" not in modes:
        return _ratios(out)
    from gscan.estimate import Tracker

    # tracking on the same frames
    tracker = Tracker(est)
    cpu, wall, status = [], [], []
    for f in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        step = tracker.step(f)
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - t0) * 1e3)
        status.append(step.status)
    out["track"] = {"cpu_ms": stats(cpu), "wall_ms": stats(wall),
                    "status": {s: status.count(s) for s in sorted(set(status))},
                    "speedup_vs_independent_cpu": float(np.median(independent_cpu) / np.median(cpu))}

    if "service" not in modes:
        return _ratios(out)
    # the service, end to end
    from gscan.client import GscanClient

    proc = subprocess.Popen([sys.executable, "-m", "gscan.cli", "serve", str(tpl), "--port", "0"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
    try:
        url = None
        while url is None:
            line = proc.stderr.readline()
            if not line:
                raise RuntimeError("the service did not start")
            m = re.search(r"at (http://\S+?:\d+)", line)
            url = m.group(1) if m else None
        client = GscanClient(url, timeout=120)
        payload = [(Path(c).read_bytes(), Path(d).read_bytes()) for c, d in files]
        k_text = K.read_text()
        client.estimate(*payload[0], k_text)  # the first request
        cpu, wall = [], []
        for c, d in payload:
            s0, c0, t0 = proc_cpu_s(proc.pid), time.process_time(), time.perf_counter()
            client.estimate(c, d, k_text)
            wall.append((time.perf_counter() - t0) * 1e3)
            cpu.append((proc_cpu_s(proc.pid) - s0) * 1e3 + (time.process_time() - c0) * 1e3)
        out["service"] = {"cpu_ms": stats(cpu), "wall_ms": stats(wall)}
    finally:
        proc.terminate()
        proc.wait(30)
    return _ratios(out)


def _ratios(out: dict) -> dict:
    base = out["cli"]
    for mode in ("warm", "service", "track"):
        if mode in out:
            out[mode]["cli_over_mode"] = {k: base[k]["median"] / out[mode][k]["median"] for k in ("cpu_ms", "wall_ms")}
    out["load_after"] = load_average()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--cli", type=int, default=10, help="frames estimated by the CLI (one process each)")
    ap.add_argument("--work", default="/tmp/gscan-bench-speed", help="cache of the scanned template")
    ap.add_argument("--modes", default="cli,warm,track,service",
                    help="what to measure besides cli and warm (track, service need this version's gscan)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = run(args)
    print(f"load average {out['load_before']:.2f} before, {out['load_after']:.2f} after; {out['frames']} frames "
          f"(640x480, whole image)")
    print("| mode | CPU ms median | CPU ms p90 | wall ms median | wall ms p90 | CLI / mode (CPU, wall) |")
    print("|---|---|---|---|---|---|")
    for mode in [m for m in ("cli", "warm", "service", "track") if m in out]:
        v = out[mode]
        ratio = v.get("cli_over_mode")
        r = f"{ratio['cpu_ms']:.1f}x, {ratio['wall_ms']:.1f}x" if ratio else "1x"
        print(f"| {mode} | {v['cpu_ms']['median']:.0f} | {v['cpu_ms']['p90']:.0f} | {v['wall_ms']['median']:.0f} | "
              f"{v['wall_ms']['p90']:.0f} | {r} |")
    print(f"\nwarm estimates found {out['warm']['found']}/{out['frames']}")
    if "track" in out:
        print(f"tracking statuses {out['track']['status']}, {out['track']['speedup_vs_independent_cpu']:.1f}x less CPU "
              "per frame than independent estimates")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
