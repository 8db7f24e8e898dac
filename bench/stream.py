"""Benchmark of long recordings in bounded memory (frame selection, frames streamed from disk) and of the template
database's write pattern, each against the code before it, run from the same command.

1. Long recordings. A rendered hand-held-like recording (`gscan.synth`, 640x480, RealSense-like depth noise, no
   masks): a camera circling a shared mesh on its table at 30 frames a second, `--step` degrees of azimuth a
   frame (0.15: a turn in 80 s), its elevation swinging 32-48 degrees, standing still for 2 s (60 frames) twice
   (frames 600-659 and 1400-1459). Rendered once, frame by frame, into bench/out/captures/; the runs scan its first
   200, 1000 and 2000 frames (folders of links). Each scan runs in a child process with the code of one revision:
   "before" is --before (8146a4d: every frame kept in memory), "after" is --after (HEAD), each exported with
   `git archive` into a temporary folder outside the repository. Reported: peak resident memory of the child
   (ru_maxrss), wall
   time, frames kept / registered, ATE of the registered frames against the rendered poses, and frames read per
   second (the load stage: frames read, selected and stored, over its seconds). A "before" run whose memory
   (`BEFORE_GB`: 0.8 GB + 4.9 MB a frame) or time (extrapolated linearly from its 200-frame run) would pass
   --max-gb / --max-minutes is not run and says so.
2. Database writes. A short capture (--db-views views, 640x480, one ring) scanned --repeats times by --before and by
   --db-rev (the write pattern alone: WAL, a commit per stage, each view written once), alternating, in child
   processes after a warm-up round; medians of the scan's time, of the stages that write (features, register,
   database) and of the time spent inside the database's write calls (image encoding included), the commits a
   scan makes, and the ratios after / before.

    python bench/stream.py                          # both, 200 / 1000 / 2000 frames
    python bench/stream.py --lengths 200 --no-db    # a quick check of part 1
    python bench/stream.py --no-long --repeats 5    # part 2 alone
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

OUT = ROOT / "bench" / "out"
MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"  # as the tests
MESH = "Crayola_Bonus_64_Crayons"
PAUSES = ((600, 60), (1400, 60))  # (first frame, frames) the camera stands still
BEFORE_GB = (0.8, 4.9e-3)  # issue 23: peak RSS of the scan before streaming, GB + GB per 640x480 frame

CHILD = r"""
import json, resource, sys, time
from gscan.scanning.api import scan
from gscan.template.db import TemplateDB
# the time the scan spends in the database's write calls (encoding included), and its commits
spent, depth, commits = [0.0], [0], [0]
def timed(f):
    def wrapper(*a, **k):
        depth[0] += 1
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            depth[0] -= 1
            if depth[0] == 0:
                spent[0] += time.perf_counter() - t
    return wrapper
for m in ("add_view", "add_edge", "add_features", "set_meta", "set_mesh", "set_cloud", "update_pose", "update_view",
          "remove_view", "_execute"):
    if hasattr(TemplateDB, m):
        setattr(TemplateDB, m, timed(getattr(TemplateDB, m)))
connect = TemplateDB._connect
def traced(*a, **k):
    c = connect(*a, **k)
    c.set_trace_callback(lambda sql: commits.__setitem__(0, commits[0] + sql.startswith("COMMIT")))
    return c
TemplateDB._connect = staticmethod(traced)
t = time.perf_counter()
r = scan(sys.argv[1], sys.argv[2], force=True)
print(json.dumps({"seconds": time.perf_counter() - t, "frames": r.frames, "registered": r.registered,
                  "timings_s": r.timings_s, "selection": getattr(r, "selection", None) or {},
                  "db_write_s": spent[0], "commits": commits[0],
                  "maxrss_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
"""


# ------------------------------------------------------------------------------------------ captures
def orbit_angles(n: int, step: float) -> list[tuple[float, float]]:
    """(elevation, azimuth) in degrees of the recording's n frames (module docstring)."""
    still = {i for first, count in PAUSES for i in range(first, first + count)}
    out, az = [], 0.0
    for i in range(n):
        if i > 0 and i not in still:
            az += step
        out.append((40.0 + 8.0 * np.sin(2 * np.pi * az / 300.0), az))
    return out


def long_capture(n: int, step: float) -> Path:
    """The recording's folder (capture layout), rendered once frame by frame (cached; `.done` marks it whole)."""
    import cv2

    from gscan.synth import default_distance, load_textured_mesh
    from gscan.synth.capture import orbit_poses, rest_on_table
    from gscan.synth.render import DEFAULT_INTRINSICS, SynthScene

    cap = OUT / "captures" / f"stream_{MESH}_{n}_step{step:g}"
    if (cap / ".done").exists():
        return cap
    shutil.rmtree(cap, ignore_errors=True)
    for d in ("rgb", "depth", "annotated_poses"):
        (cap / d).mkdir(parents=True)
    mesh = load_textured_mesh(MESHES / MESH / "model_0.obj")
    T_world_obj = rest_on_table(mesh)
    scene = SynthScene([(mesh, T_world_obj)], seed=7)
    centre = T_world_obj[:3, :3] @ mesh.center + T_world_obj[:3, 3]
    intr = DEFAULT_INTRINSICS
    dist = default_distance(mesh, intr)
    np.savetxt(cap / "cam_K.txt", intr.K, fmt="%.10g")
    t = time.perf_counter()
    for i, (el, az) in enumerate(orbit_angles(n, step)):
        T_wc = orbit_poses(centre, dist, [el], 1, azimuth0_deg=az)[0]
        r = scene.render(T_wc, intr, rng=np.random.default_rng([7, i]))
        name = f"{i:06d}"
        cv2.imwrite(str(cap / "rgb" / f"{name}.png"), cv2.cvtColor(r.color, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(cap / "depth" / f"{name}.png"),
                    np.clip(np.rint(r.depth.astype(np.float64) * 1000.0), 0, 65535).astype(np.uint16))
        np.savetxt(cap / "annotated_poses" / f"{name}.txt", r.T_cam_obj, fmt="%.10g")
        if i % 100 == 99:
            print(f"  rendered {i + 1} / {n} frames ({time.perf_counter() - t:.0f} s)", flush=True)
    (cap / ".done").write_text("ok\n")
    return cap


def prefix(cap: Path, n: int) -> Path:
    """A capture folder of the first n frames of `cap` (links)."""
    out = cap.parent / f"{cap.name}_first{n}"
    if (out / ".done").exists():
        return out
    shutil.rmtree(out, ignore_errors=True)
    for d in ("rgb", "depth", "annotated_poses"):
        (out / d).mkdir(parents=True)
        for p in sorted((cap / d).iterdir())[:n]:
            (out / d / p.name).symlink_to(p)
    (out / "cam_K.txt").symlink_to(cap / "cam_K.txt")
    (out / ".done").write_text("ok\n")
    return out


def short_capture(views: int) -> Path:
    from gscan.synth import load_textured_mesh, render_capture

    cap = OUT / "captures" / f"stream_db_{MESH}_v{views}"
    if not (cap / ".done").exists():
        shutil.rmtree(cap, ignore_errors=True)
        render_capture(load_textured_mesh(MESHES / MESH / "model_0.obj"), cap, views, mode="static",
                       elevations_deg=(40.0,), seed=3, write_masks=False)
        (cap / ".done").write_text("ok\n")
    return cap


# ------------------------------------------------------------------------------------------ runs
def export(rev: str, where: Path) -> Path:
    """The tree of revision `rev` exported into `where` (outside the repository)."""
    where.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(where)], input=archive, check=True)
    return where


def run(tree: Path, cap: Path, db: Path) -> dict:
    """One scan of `cap` by the code in `tree`, in a child process."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    p = subprocess.run([sys.executable, "-c", CHILD, str(cap), str(db)], cwd=tree, env=env, capture_output=True,
                       text=True, check=False)
    if p.returncode != 0:
        raise RuntimeError(f"scan by {tree} failed: {p.stderr[-2000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["ate_mm"] = ate_mm(cap, db)
    db.unlink(missing_ok=True)
    return out


def ate_mm(cap: Path, db: Path) -> float:
    from gscan.evaluate.metrics import ate
    from gscan.geometry.transforms import inv_T
    from gscan.io import open_sequence
    from gscan.template.db import TemplateDB

    with TemplateDB.open(db) as t:
        poses = t.poses()["frames"]
    gt = open_sequence(cap).gt_T_cam_obj
    names = [n for n in poses if n in gt]
    return 1000.0 * ate([np.asarray(poses[n]) for n in names], [inv_T(gt[n]) for n in names]).rmse


def long_runs(args: argparse.Namespace, before: Path, after: Path) -> list[dict]:
    cap = long_capture(max(args.lengths), args.step)
    warm = short_capture(4)
    for tree in (before, after):  # numba compiles into each tree's cache on its first scan: not timed
        with tempfile.TemporaryDirectory(dir=OUT) as d:
            run(tree, warm, Path(d) / "t.gscan")
    rows = []
    t200 = None
    for n in args.lengths:
        c = prefix(cap, n)
        for label, tree in (("before", before), ("after", after)):
            row = {"frames": n, "code": label}
            est_gb = BEFORE_GB[0] + BEFORE_GB[1] * n
            est_min = None if t200 is None else t200 * n / 200 / 60
            if label == "before" and (est_gb > args.max_gb or (est_min is not None and est_min > args.max_minutes)):
                row["skipped"] = (f"not run: about {est_gb:.1f} GB" + (f" and {est_min:.0f} min" if est_min else "")
                                  + f" expected (limits {args.max_gb:g} GB, {args.max_minutes:g} min)")
                print(f"  {n} frames, {label}: {row['skipped']}", flush=True)
                rows.append(row)
                continue
            with tempfile.TemporaryDirectory(dir=OUT) as d:
                r = run(tree, c, Path(d) / "t.gscan")
            if label == "before" and n == 200:
                t200 = r["seconds"]
            row.update(r)
            load = r["timings_s"].get("load", float("nan"))
            row["read_fps"] = n / load if load > 0 else float("nan")
            print(f"  {n} frames, {label}: {r['maxrss_kib'] / 2**20:.2f} GB peak, {r['seconds']:.0f} s, "
                  f"kept {r['selection'].get('kept', n)}, registered {r['registered']}, ATE {r['ate_mm']:.2f} mm, "
                  f"read {row['read_fps']:.0f} frames/s", flush=True)
            rows.append(row)
    return rows


def db_runs(args: argparse.Namespace, before: Path, db_tree: Path) -> dict:
    cap = short_capture(args.db_views)
    got: dict[str, list[dict]] = {"before": [], "after": []}
    for k in range(args.repeats + 1):  # the first round warms numba's caches and the page cache: not counted
        for label, tree in (("before", before), ("after", db_tree)):
            with tempfile.TemporaryDirectory(dir=OUT) as d:
                r = run(tree, cap, Path(d) / "t.gscan")
            print(f"  database round {k}, {label}: {r['seconds']:.1f} s", flush=True)
            if k:
                got[label].append(r)
    out: dict = {}
    for label, rs in got.items():
        stages = {s: statistics.median(r["timings_s"].get(s, 0.0) for r in rs)
                  for s in ("features", "register", "database")}
        out[label] = {"seconds": statistics.median(r["seconds"] for r in rs), "stages": stages,
                      "db_write_s": statistics.median(r["db_write_s"] for r in rs), "commits": rs[0]["commits"],
                      "all": [r["seconds"] for r in rs]}
    out["ratio"] = out["after"]["seconds"] / out["before"]["seconds"]
    out["write_ratio"] = out["after"]["db_write_s"] / out["before"]["db_write_s"]
    print(f"  database writes: scan {out['before']['seconds']:.1f} s before, {out['after']['seconds']:.1f} s after "
          f"(ratio {out['ratio']:.2f}); writing {out['before']['db_write_s']:.2f} s, "
          f"{out['after']['db_write_s']:.2f} s "
          f"(ratio {out['write_ratio']:.2f}); commits {out['before']['commits']}, {out['after']['commits']}",
          flush=True)
    return out


def markdown(result: dict) -> str:
    lines = []
    if result.get("long"):
        lines += ["| frames | code | peak RSS GB | seconds | frames kept | registered | ATE mm | frames read / s |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in result["long"]:
            if "skipped" in r:
                lines.append(f"| {r['frames']} | {r['code']} | {r['skipped']} | | | | | |")
                continue
            lines.append(f"| {r['frames']} | {r['code']} | {r['maxrss_kib'] / 2**20:.2f} | {r['seconds']:.0f} | "
                         f"{r['selection'].get('kept', r['frames'])} | {r['registered']} | {r['ate_mm']:.2f} | "
                         f"{r['read_fps']:.0f} |")
    if result.get("db"):
        d = result["db"]
        head = "| code | scan s (median) | features s | register s | database s | in database writes s | commits |"
        lines += ["", head, "|---|---|---|---|---|---|---|"]
        for label in ("before", "after"):
            s = d[label]["stages"]
            lines.append(f"| {label} | {d[label]['seconds']:.1f} | {s['features']:.1f} | {s['register']:.1f} | "
                         f"{s['database']:.1f} | {d[label]['db_write_s']:.2f} | {d[label]['commits']} |")
        lines.append(f"\nratio after / before: scan {d['ratio']:.2f}, database writes {d['write_ratio']:.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lengths", type=lambda s: [int(x) for x in s.split(",")], default=[200, 1000, 2000])
    ap.add_argument("--step", type=float, default=0.15, help="degrees of azimuth a frame")
    ap.add_argument("--before", default="8146a4d", help="the revision before streaming and the write pattern")
    ap.add_argument("--after", default="HEAD", help="the revision with streaming")
    ap.add_argument("--db-rev", default="edd720d", help="the revision with the write pattern alone")
    ap.add_argument("--db-views", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-gb", type=float, default=8.0)
    ap.add_argument("--max-minutes", type=float, default=15.0)
    ap.add_argument("--no-long", action="store_true")
    ap.add_argument("--no-db", action="store_true")
    ap.add_argument("--json", type=Path, default=OUT / "stream.json")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    result: dict = {"args": {k: v for k, v in vars(args).items() if k != "json"}}
    with tempfile.TemporaryDirectory(prefix="gscan-bench-") as tmp:
        before = export(args.before, Path(tmp) / "before")
        if not args.no_db:
            result["db"] = db_runs(args, before, export(args.db_rev, Path(tmp) / "db"))
        if not args.no_long:
            result["long"] = long_runs(args, before, export(args.after, Path(tmp) / "after"))
    args.json.write_text(json.dumps(result, indent=1, default=str))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
