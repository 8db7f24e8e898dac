"""Per-frame CPU and wall time of pose estimation, four ways, on the same rendered frames (640x480, whole image,
no mask), as ratios against one `gscan estimate` command measured in the same run:

- cli: `python -m gscan.cli estimate T --color C --depth D --intrinsics K --json`, one process per frame (CPU of
  the child process, from getrusage);
- warm: one `Estimator` loaded once, `estimate(frame)` per frame (frames already in memory);
- service: `gscan serve T` started once, each frame posted by gscan.client as PNG bytes (wall: request to
  response; CPU: the server process's CPU during the request, from /proc, plus the client's);
- track: `Tracker.step` per frame through the sequence (the previous pose as a prior), and, on the same frames,
  independent warm estimates (the tracking speed-up).

With --compare DIR, another gscan tree (DIR holds its `gscan` package: a checkout of an older commit) is
measured in the same run: its CLI call after this tree's on every CLI frame, and its warm estimator in a child
process whose passes alternate with this tree's (--rounds passes each), so that both see the same load; the
ratio of the two warm CPU medians is printed.

Wrong results accepted: a returned pose whose ADD exceeds 10 % of the object's diameter (bench/estimate.py's
and bench/recall.py's rule), the template's frame mapped to the mesh's by the scan's ground truth
(gscan.evaluate.bop19.template_to_gt, from the capture the template was scanned from, never from these frames).

The frames: a template scanned by gscan (gscan.scanning.pipeline) from a rendered 16-frame capture of a shared mesh
standing on a newspaper table; a sequence in which that object slides 6 mm and turns 2.3 deg per frame on a
wood table between two other shared meshes, seen by a static camera. The load average (`uptime`) is recorded
before and after: the machine is shared. The meshes are read from ../shared/data beside the repository, or the
folder GSCAN_TEST_DATA names.

    python bench/speed.py                       # 24 frames, 10 CLI calls
    python bench/speed.py --frames 40 --cli 20 --json out.json
    git archive <commit> | tar -x -C /tmp/old; python bench/speed.py --compare /tmp/old --rounds 3
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
MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"  # as tests/conftest.py
TARGET = "Crayola_Bonus_64_Crayons"
DISTRACTORS = ("Little_Debbie_Cloud_Cakes_10_ct", "Whey_Protein_Chocolate_12_Packets")


def load_average() -> float:
    return float(os.getloadavg()[0])


def stats(xs: list[float]) -> dict[str, float]:
    return {"median": float(np.median(xs)), "p90": float(np.percentile(xs, 90))}


def scanned_template(work: Path) -> Path:
    from gscan.scanning.api import scan
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
    d_poses = place_distractors(target, T0, others, np.random.default_rng(0), gap=0.06)
    scene = SynthScene([(target, T0)] + list(zip(others, d_poses, strict=True)), seed=3, table_kind="wood")
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


def warm_pass(est, frames) -> dict:
    """One pass of warm estimates: per-frame CPU and wall ms, and the poses (None when not found)."""
    cpu, wall, poses = [], [], []
    for f in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        res = est.estimate(f)
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - t0) * 1e3)
        poses.append(None if res.T_cam_obj is None else np.asarray(res.T_cam_obj).tolist())
    return {"cpu": cpu, "wall": wall, "poses": poses}


def warm_child(seq_dir: str, tpl: str, rounds: int) -> None:
    """--warm-child: `warm_pass` of the gscan on sys.path, one JSON line per pass on stdout, each after a line
    on stdin (the parent interleaves its own passes)."""
    from gscan.estimate.estimator import Estimator
    from gscan.io import open_sequence

    seq = open_sequence(Path(seq_dir))
    frames = [seq[n] for n in seq.names]
    est = Estimator.from_path(tpl)
    est.estimate(frames[0])
    for _ in range(rounds):
        if not sys.stdin.readline():
            return
        print(json.dumps(warm_pass(est, frames)), flush=True)


class Truth:
    """Ground truth of the sequence, in the scanned template's frame: `wrong(T)` for a returned pose."""

    def __init__(self, work: Path, tpl: Path, seq) -> None:
        from gscan.evaluate.bop19 import template_to_gt
        from gscan.io import open_sequence
        from gscan.synth import load_textured_mesh

        mesh = load_textured_mesh(MESHES / TARGET / "model_0.obj")
        self.points = np.asarray(mesh.vertices, dtype=np.float64)
        self.diameter = float(np.linalg.norm(mesh.extent))
        gt = open_sequence(work / "capture").gt_T_cam_obj
        assert gt is not None, "the rendered capture has ground truth"
        self.T_obj_gt = template_to_gt(tpl, gt)
        self.gt = [seq.gt_T_cam_obj[n] for n in seq.names]

    def add(self, i: int, T_cam_obj) -> float:
        from gscan.evaluate.metrics import add

        return add(self.points, np.asarray(T_cam_obj, dtype=np.float64) @ self.T_obj_gt, self.gt[i])

    def count(self, poses: list) -> dict:
        """found, wrong (ADD > 10 % of the diameter) and the largest ADD (mm) of the returned poses."""
        adds = [self.add(i, T) for i, T in enumerate(poses) if T is not None]
        return {"found": len(adds), "wrong": int(sum(a > 0.1 * self.diameter for a in adds)),
                "max_add_mm": 1e3 * max(adds, default=0.0)}


def run(args: argparse.Namespace) -> dict:
    import gscan
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
    truth = Truth(work, tpl, seq)
    out: dict = {"load_before": load_average(), "frames": len(frames), "template": str(tpl),
                 "gscan": str(Path(gscan.__file__).parent)}
    env = dict(os.environ, PYTHONPATH=str(Path(gscan.__file__).resolve().parents[1]))  # the gscan measured here

    # cli: one process per frame (with --compare, the other tree's command on the same frame after each)
    trees = {"cli": env} | ({"cli_compare": dict(os.environ, PYTHONPATH=args.compare)} if args.compare else {})
    runs: dict[str, dict[str, list]] = {k: {"cpu": [], "wall": [], "poses": []} for k in trees}
    for c, d in files[: args.cli]:
        for key, tree_env in trees.items():
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            p = subprocess.run([sys.executable, "-m", "gscan.cli", "estimate", str(tpl), "--color", str(c), "--depth",
                                str(d), "--intrinsics", str(K), "--json"], capture_output=True, env=tree_env,
                               check=False)
            runs[key]["wall"].append((time.perf_counter() - t0) * 1e3)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            runs[key]["cpu"].append((r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime) * 1e3)
            if p.returncode != 0:
                raise RuntimeError(p.stderr.decode())
            runs[key]["poses"].append(json.loads(p.stdout)["T_cam_obj"])
    for key, r in runs.items():
        out[key] = {"cpu_ms": stats(r["cpu"]), "wall_ms": stats(r["wall"]), **truth.count(r["poses"])}
    if args.compare:
        out["cli_compare"]["tree"] = args.compare

    # warm estimator (and, with --compare, another tree's, interleaved pass by pass)
    child = None
    if args.compare:
        child = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--warm-child", str(tmp / "seq"),
                                  str(tpl), "--rounds", str(args.rounds)], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=args.compare))
    est = Estimator.from_path(tpl)
    est.estimate(frames[0])
    passes, old_passes = [], []
    for _ in range(args.rounds):
        if child is not None:
            assert child.stdin is not None and child.stdout is not None
            child.stdin.write("\n")
            child.stdin.flush()
            line = child.stdout.readline()
            if not line:
                raise RuntimeError(f"the warm estimator of {args.compare} failed")
            old_passes.append(json.loads(line))
        passes.append(warm_pass(est, frames))
    if child is not None:
        assert child.stdin is not None
        child.stdin.close()
        child.wait(60)
        old = {k: [x for q in old_passes for x in q[k]] for k in ("cpu", "wall")}
        out["warm_compare"] = {"cpu_ms": stats(old["cpu"]), "wall_ms": stats(old["wall"]), "tree": args.compare,
                               **truth.count(old_passes[0]["poses"])}
    cpu = [x for q in passes for x in q["cpu"]]
    out["warm"] = {"cpu_ms": stats(cpu), "wall_ms": stats([x for q in passes for x in q["wall"]]),
                   **truth.count(passes[0]["poses"])}
    independent_cpu = cpu

    if "track" in modes:
        from gscan.estimate import Tracker

        tracker = Tracker(est)
        cpu, wall, status, poses = [], [], [], []
        for f in frames:
            t0, c0 = time.perf_counter(), time.process_time()
            step = tracker.step(f)
            cpu.append((time.process_time() - c0) * 1e3)
            wall.append((time.perf_counter() - t0) * 1e3)
            status.append(step.status)
            poses.append(step.result.T_cam_obj)
        out["track"] = {"cpu_ms": stats(cpu), "wall_ms": stats(wall),
                        "status": {s: status.count(s) for s in sorted(set(status))},
                        "speedup_vs_independent_cpu": float(np.median(independent_cpu) / np.median(cpu)),
                        **truth.count(poses)}

    if "service" in modes:
        out["service"] = measure_service(tpl, files, K, env, truth)
    return _ratios(out)


def measure_service(tpl: Path, files: list, K: Path, env: dict, truth: Truth) -> dict:
    """The service, end to end: `gscan serve` started once, every frame posted by gscan.client."""
    from gscan.client import GscanClient

    proc = subprocess.Popen([sys.executable, "-m", "gscan.cli", "serve", str(tpl), "--port", "0"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
    try:
        url = None
        assert proc.stderr is not None
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
        cpu, wall, poses = [], [], []
        for c, d in payload:
            s0, c0, t0 = proc_cpu_s(proc.pid), time.process_time(), time.perf_counter()
            r = client.estimate(c, d, k_text)
            wall.append((time.perf_counter() - t0) * 1e3)
            cpu.append((proc_cpu_s(proc.pid) - s0) * 1e3 + (time.process_time() - c0) * 1e3)
            poses.append(next(iter(r.results.values())).T_cam_obj)
        return {"cpu_ms": stats(cpu), "wall_ms": stats(wall), **truth.count(poses)}
    finally:
        proc.terminate()
        proc.wait(30)


def _ratios(out: dict) -> dict:
    base = out["cli"]
    for mode in ("cli_compare", "warm", "warm_compare", "service", "track"):
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
    ap.add_argument("--rounds", type=int, default=1, help="passes of warm estimates over the sequence")
    ap.add_argument("--compare", default=None, help="another gscan tree whose warm estimator is measured too")
    ap.add_argument("--warm-child", nargs=2, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if args.warm_child:  # the gscan of PYTHONPATH (--compare)
        warm_child(args.warm_child[0], args.warm_child[1], args.rounds)
        return
    sys.path.insert(0, str(ROOT))  # this tree's gscan, not an installed one
    out = run(args)
    print(f"load average {out['load_before']:.2f} before, {out['load_after']:.2f} after; {out['frames']} frames "
          f"(640x480, whole image); gscan from {out['gscan']}")
    print("| mode | CPU ms median | CPU ms p90 | wall ms median | wall ms p90 | CLI / mode (CPU, wall) | found "
          "| wrong |")
    print("|---|---|---|---|---|---|---|---|")
    for mode in [m for m in ("cli", "cli_compare", "warm", "warm_compare", "service", "track") if m in out]:
        v = out[mode]
        ratio = v.get("cli_over_mode")
        r = f"{ratio['cpu_ms']:.1f}x, {ratio['wall_ms']:.1f}x" if ratio else "1x"
        name = f"{mode.split('_')[0]} ({v['tree']})" if "tree" in v else mode
        n = args.cli if mode.startswith("cli") else out["frames"]
        print(f"| {name} | {v['cpu_ms']['median']:.0f} | {v['cpu_ms']['p90']:.0f} | {v['wall_ms']['median']:.0f} | "
              f"{v['wall_ms']['p90']:.0f} | {r} | {v['found']}/{n} | {v['wrong']} |")
    print("\nwrong: ADD above 10 % of the diameter; largest ADD of a returned pose (mm): "
          + ", ".join(f"{m} {out[m]['max_add_mm']:.1f}" for m in ("cli", "cli_compare", "warm", "warm_compare",
                                                                   "service", "track") if m in out))
    if "warm_compare" in out:
        print(f"warm CPU median, this tree / {args.compare}: "
              f"{out['warm']['cpu_ms']['median'] / out['warm_compare']['cpu_ms']['median']:.2f}")
    if "track" in out:
        print(f"tracking statuses {out['track']['status']}, {out['track']['speedup_vs_independent_cpu']:.1f}x less CPU "
              "per frame than independent estimates")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
