"""Benchmark of the scan pipeline (gscan.scanning.pipeline) on rendered captures of the shared meshes, against peers.

1. Accuracy: for every shared mesh (or the first --meshes), a static capture of --views views
   (gscan.synth.render_capture, mode "static", two orbit rings at 30 and 55 degrees elevation,
   ordered ring by ring: the first half of the frames on the 30-degree ring; with --mode turntable the
   object turns 360 degrees in front of one camera at 30 degrees), scanned with the
   rendered masks and again without them (masks/ removed: gscan segments on its own). Reports
   registered frames, frames registered at a wrong pose (beyond 5 deg or 2 cm of the ground truth: the
   median error of a frame's poses relative to the other registered frames, gscan.evaluate.metrics.frame_errors),
   ATE of the camera positions (rigid Umeyama alignment of the scanned T_obj_cam positions onto the
   ground-truth inv(T_cam_obj) ones, gscan.evaluate.metrics.ate; over the registered frames) and seconds per
   frame (wall time of run_scan / frames).
2. Peers on the same captures (bench/peers.py, whole frames): open3d RGB-D odometry chain and
   FPFH + RANSAC + point-to-plane ICP chain; registered / failed frames, wrong frames and ATE. Their depth_max
   is the capture's camera distance plus two object radii (the object and the table around it).
   Both are run again on masked depth (depth outside the rendered mask set to 0; --no-masked-peers skips).
3. End to end: one --e2e-views capture (640x480, three rings at 25/45/65 degrees) scanned in a
   child process (features, registration, pose graph, segmentation, fusion, database): total
   seconds, per-stage seconds (ScanResult.timings_s), peak resident memory of the child
   (ru_maxrss, RUSAGE_CHILDREN) and its accuracy.

Rendered captures are cached under bench/out/captures/ (delete a folder to re-render it).
Raw results go to --json (default bench/out/scan.json).

    python bench/scan.py                  # 21 meshes x 36 views, peers, 100-frame end-to-end run
    python bench/scan.py --meshes 3       # quick end-to-end check of the script
    python bench/scan.py --quick          # 3 meshes, 24 views, 40-frame end-to-end run
    python bench/scan.py --meshes 0       # the end-to-end run alone
    python bench/scan.py --mode turntable --views 24 --e2e-views 0   # turntable captures
    python bench/scan.py --tables bench/out/scan_a.json --merge bench/out/scan_b.json --markdown
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from gscan.evaluate.metrics import ate, frame_errors  # noqa: E402
from gscan.geometry.transforms import inv_T  # noqa: E402
from gscan.io import open_sequence  # noqa: E402
from gscan.scanning.api import scan  # noqa: E402
from gscan.synth import default_distance, load_textured_mesh, render_capture  # noqa: E402
from gscan.template.db import TemplateDB  # noqa: E402

MESHES = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data") / "meshes"
OUT = ROOT / "bench" / "out"
ELEVATIONS = (30.0, 55.0)
E2E_ELEVATIONS = (25.0, 45.0, 65.0)
E2E_MESH = "Crayola_Bonus_64_Crayons"
PEER_DEPTH_RADII = 2.0  # peers' depth_max = camera distance + this x object radius (object + table near it)
TARGET_ATE_M = 0.005
WRONG_DEG, WRONG_M = 5.0, 0.02  # a registered frame beyond either (rendered data) is at a wrong pose


def mesh_names() -> list[str]:
    return sorted(p.name for p in MESHES.iterdir() if (p / "model_0.obj").is_file())


def capture_tag(name: str, views: int, elevations: tuple[float, ...], seed: int, mode: str) -> str:
    return f"{name}_v{views}_e{'-'.join(f'{e:g}' for e in elevations)}_s{seed}" + ("" if mode == "static" else
                                                                                  f"_{mode}")


def capture(name: str, views: int, elevations: tuple[float, ...], seed: int, mode: str = "static"
            ) -> tuple[Path, Path]:
    """(capture folder with masks, copy without masks/), rendered once and cached."""
    tag = capture_tag(name, views, elevations, seed, mode)
    cap, bare = OUT / "captures" / tag, OUT / "captures" / f"{tag}_nomask"
    if not (cap / ".done").exists():
        shutil.rmtree(cap, ignore_errors=True)
        t = time.perf_counter()
        mesh = load_textured_mesh(MESHES / name / "model_0.obj")
        render_capture(mesh, cap, views, mode=mode, elevations_deg=elevations, seed=seed)
        (cap / ".done").write_text("ok\n")
        print(f"  rendered {name}: {views} views in {time.perf_counter() - t:.0f} s", flush=True)
    if not (bare / ".done").exists():
        shutil.rmtree(bare, ignore_errors=True)
        shutil.copytree(cap, bare, ignore=shutil.ignore_patterns("masks", ".done"))
        (bare / ".done").write_text("ok\n")
    return cap, bare


def gt_T_world_cam(cap: Path) -> dict[str, np.ndarray]:
    """Ground-truth camera poses in the object frame: name -> inv(T_cam_obj) [4 x 4]."""
    return {n: inv_T(T) for n, T in open_sequence(cap).gt_T_cam_obj.items()}


def score(est: dict[str, np.ndarray | None], gt: dict[str, np.ndarray]) -> dict:
    """Registered count, the frames registered at a wrong pose (beyond WRONG_DEG / WRONG_M, relative poses) and
    ATE (m) of the registered frames' positions against the ground truth."""
    names = [n for n in gt if est.get(n) is not None]
    out = {"frames": len(gt), "registered": len(names), "failed": sorted(set(gt) - set(names)),
           "wrong": frame_errors({n: np.asarray(est[n]) for n in names}, {n: gt[n] for n in names}).wrong(
               WRONG_DEG, WRONG_M)}
    if names:
        a = ate([np.asarray(est[n]) for n in names], [gt[n] for n in names])
        out.update(ate_rmse=a.rmse, ate_median=a.median, ate_max=a.max,
                   worst=[names[k] for k in np.argsort(-a.errors)[:3]])
    else:
        out.update(ate_rmse=float("nan"), ate_median=float("nan"), ate_max=float("nan"), worst=[])
    return out


def scan_once(cap: Path, gt: dict[str, np.ndarray], db_path: Path) -> dict:
    t = time.perf_counter()
    res = scan(cap, db_path, force=True)
    secs = time.perf_counter() - t
    with TemplateDB.open(db_path) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    out = score(poses, gt)
    out.update(seconds=secs, s_per_frame=secs / max(1, res.frames), mode=res.mode,
               edges_accepted=res.edges_accepted, edges_rejected=res.edges_rejected,
               timings_s=res.timings_s, mesh_vertices=res.mesh_vertices)
    db_path.unlink(missing_ok=True)
    return out


def peer_depth_max(name: str) -> float:
    """Working range given to the peers (m): the rig's camera distance plus two object radii."""
    mesh = load_textured_mesh(MESHES / name / "model_0.obj")
    return default_distance(mesh) + PEER_DEPTH_RADII * mesh.radius


def run_peers(cap: Path, gt: dict[str, np.ndarray], depth_max: float, masked: bool) -> dict:
    """Both peers on whole frames (keys odometry, fpfh) or, masked, on the object's depth alone
    (depth outside the rendered mask set to 0; keys odometry_masked, fpfh_masked)."""
    from peers import fpfh_ransac_icp_chain, rgbd_odometry_chain

    seq = open_sequence(cap)
    frames = [seq[n] for n in seq.names]
    for f in frames:
        if masked:
            f.depth = np.where(f.mask, f.depth, 0.0).astype(np.float32)
        f.mask = None
    out = {}
    for key, fn in (("odometry", rgbd_odometry_chain), ("fpfh", fpfh_ransac_icp_chain)):
        r = fn(frames, depth_max)
        s = score(r.T_world_cam, gt)
        s.update(seconds=r.seconds, s_per_frame=r.seconds / len(frames), notes=r.notes, depth_max=depth_max)
        out[key + ("_masked" if masked else "")] = s
    return out


def _mm(x: float) -> str:
    return "  -  " if not np.isfinite(x) else f"{1000 * x:6.2f}"


def _wrong(rs: list[dict]) -> str:
    """Frames registered at a wrong pose over rows `rs` ("-" when a row was scored before they were counted)."""
    return "-" if any("wrong" not in r for r in rs) else str(sum(len(r["wrong"]) for r in rs))


def wait_for_capture(name: str, views: int, seed: int, mode: str, timeout_s: float = 3600.0) -> None:
    """Block until another process has rendered this capture (a split run renders each once)."""
    tag = capture_tag(name, views, ELEVATIONS, seed, mode)
    t = time.perf_counter()
    while not (OUT / "captures" / f"{tag}_nomask" / ".done").exists():
        if time.perf_counter() - t > timeout_s:
            raise TimeoutError(f"capture {tag} not rendered after {timeout_s:.0f} s")
        time.sleep(5.0)


def accuracy(names: list[str], views: int, what: set[str], result: dict, json_path: Path,
             wait: bool = False, mode: str = "static") -> dict:
    """Per-mesh rows of the methods in `what` ("scan", "peers", "peers_masked"); the raw results
    so far are rewritten to json_path after every mesh."""
    rows = result.setdefault("accuracy", {})
    everything = mesh_names()
    for k, name in enumerate(names):
        print(f"[{k + 1}/{len(names)}] {name}", flush=True)
        seed = everything.index(name)  # index among all meshes: the same capture in a split run
        if wait:
            wait_for_capture(name, views, seed, mode)
        cap, bare = capture(name, views, ELEVATIONS, seed=seed, mode=mode)
        gt = gt_T_world_cam(cap)
        row = {}
        if "scan" in what:
            db = OUT / f"bench_scan_{name}.gscan"  # per mesh: split runs never share a database
            row["masks"] = scan_once(cap, gt, db)
            row["nomask"] = scan_once(bare, gt, db)
        if "peers" in what:
            row.update(run_peers(cap, gt, peer_depth_max(name), masked=False))
        if "peers_masked" in what:
            row.update(run_peers(cap, gt, peer_depth_max(name), masked=True))
        rows[name] = row
        line = "  ".join(f"{m}: {r['registered']}/{r['frames']} wrong {len(r['wrong'])} "
                         f"ATE {_mm(r['ate_rmse']).strip()} mm "
                         f"({r['s_per_frame']:.2f} s/f)" for m, r in row.items() if isinstance(r, dict))
        print("   " + line, flush=True)
        write_json(result, json_path)
    return rows


def print_accuracy(rows: dict, views: int) -> None:
    order = ("masks", "nomask", "odometry", "fpfh", "odometry_masked", "fpfh_masked")
    methods = [m for m in order if any(m in r for r in rows.values())]
    label = {"masks": "gscan masks", "nomask": "gscan no masks", "odometry": "o3d odometry",
             "fpfh": "o3d FPFH+ICP", "odometry_masked": "o3d odometry masked",
             "fpfh_masked": "o3d FPFH+ICP masked"}
    print(f"\nATE RMSE (mm) (registered frames of {views}), per mesh")
    print(f"{'mesh':40s}" + "".join(f"{label[m]:>27s}" for m in methods) + "   (w: frames at a wrong pose)")
    for name, r in sorted(rows.items()):
        cells = [(f"{_mm(r[m]['ate_rmse'])} ({r[m]['registered']:2d}/{r[m]['frames']}, w {_wrong([r[m]])})"
                  if m in r else "") for m in methods]
        print(f"{name[:40]:40s}" + "".join(c.rjust(27) for c in cells))
    print("\nsummary")
    print(f"{'method':20s} {'meshes':>6s} {'median ATE mm':>14s} {'mean ATE mm':>12s} {'max ATE mm':>11s} "
          f"{'all frames reg.':>16s} {'frames reg.':>12s} {'wrong':>6s} {'ATE<=5mm & all reg.':>20s} "
          f"{'s/frame median':>15s}")
    for m in methods:
        rs = [r[m] for r in rows.values() if m in r]
        a = np.array([x["ate_rmse"] for x in rs])
        full = sum(x["registered"] == x["frames"] for x in rs)
        ok = sum(x["registered"] == x["frames"] and x["ate_rmse"] <= TARGET_ATE_M for x in rs)
        reg = sum(x["registered"] for x in rs)
        tot = sum(x["frames"] for x in rs)
        print(f"{label[m]:20s} {len(rs):6d} {_mm(np.nanmedian(a)):>14s} {_mm(np.nanmean(a)):>12s} "
              f"{_mm(np.nanmax(a)):>11s} {full:>13d}/{len(rs):<2d} {reg:>7d}/{tot:<4d} {_wrong(rs):>6s} "
              f"{ok:>17d}/{len(rs):<2d} "
              f"{np.median([x['s_per_frame'] for x in rs]):>15.2f}")


def markdown_accuracy(rows: dict) -> str:
    """The per-mesh and summary tables as Markdown (for BENCHMARKS.md)."""
    order = ("masks", "nomask", "odometry", "fpfh", "odometry_masked", "fpfh_masked")
    methods = [m for m in order if any(m in r for r in rows.values())]
    label = {"masks": "gscan, masks", "nomask": "gscan, no masks", "odometry": "o3d odometry",
             "fpfh": "o3d FPFH+RANSAC+ICP", "odometry_masked": "o3d odometry, masked depth",
             "fpfh_masked": "o3d FPFH+RANSAC+ICP, masked depth"}
    out = ["| mesh | " + " | ".join(label[m] for m in methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for name, r in sorted(rows.items()):
        cells = [(f"{1000 * r[m]['ate_rmse']:.2f} ({r[m]['registered']}/{r[m]['frames']}, {_wrong([r[m]])} wrong)"
                  if m in r else "") for m in methods]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    out += ["", "| method | meshes | median ATE (mm) | mean ATE (mm) | max ATE (mm) | meshes with every frame "
            "registered | frames registered | registered at a wrong pose | meshes ATE <= 5 mm and all registered | "
            "s/frame (median) |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for m in methods:
        rs = [r[m] for r in rows.values() if m in r]
        a = 1000 * np.array([x["ate_rmse"] for x in rs])
        ok = sum(x["registered"] == x["frames"] and x["ate_rmse"] <= TARGET_ATE_M for x in rs)
        out.append(f"| {label[m]} | {len(rs)} | {np.nanmedian(a):.2f} | {np.nanmean(a):.2f} | {np.nanmax(a):.2f} | "
                   f"{sum(x['registered'] == x['frames'] for x in rs)}/{len(rs)} | "
                   f"{sum(x['registered'] for x in rs)}/{sum(x['frames'] for x in rs)} | {_wrong(rs)} | "
                   f"{ok}/{len(rs)} | "
                   f"{np.median([x['s_per_frame'] for x in rs]):.2f} |")
    return "\n".join(out)


def e2e(views: int) -> dict:
    """Scan one `views`-frame capture in a child process; its timings, accuracy and peak memory."""
    cap, _ = capture(E2E_MESH, views, E2E_ELEVATIONS, seed=100)
    res_json = OUT / f"e2e_{views}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child-scan", str(cap), str(OUT / "e2e.gscan"),
           str(res_json)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # Linux: KiB, max over waited children
    child = json.loads(res_json.read_text())
    gt = gt_T_world_cam(cap)
    out = score({n: np.asarray(T) for n, T in child["poses"].items()}, gt)
    out.update(views=views, mesh=E2E_MESH, run_scan_s=child["seconds"], child_wall_s=wall,
               timings_s=child["timings_s"], peak_rss_mib=peak_kib / 1024.0,
               peak_rss_note="" if before < peak_kib else "an earlier child had a larger peak",
               self_maxrss_mib=child["maxrss_kib"] / 1024.0, edges_accepted=child["edges_accepted"],
               edges_rejected=child["edges_rejected"], keyframes=child["keyframes"],
               mesh_vertices=child["mesh_vertices"])
    (OUT / "e2e.gscan").unlink(missing_ok=True)
    return out


def print_e2e(r: dict) -> None:
    print(f"\nend to end: {r['views']} frames 640x480 of {r['mesh']} (3 rings), child process")
    print(f"  run_scan {r['run_scan_s']:.1f} s ({r['run_scan_s'] / r['views']:.2f} s/frame), child wall "
          f"{r['child_wall_s']:.1f} s (interpreter start and imports included), peak RSS {r['peak_rss_mib']:.0f} MiB")
    print("  stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in r["timings_s"].items()))
    print(f"  registered {r['registered']}/{r['frames']}, at a wrong pose {_wrong([r])}, "
          f"ATE RMSE {_mm(r['ate_rmse']).strip()} mm, "
          f"edges {r['edges_accepted']} accepted / {r['edges_rejected']} rejected, {r['keyframes']} keyframes")


def child_scan(cap: str, db: str, out: str) -> None:
    t = time.perf_counter()
    res = scan(Path(cap), Path(db), force=True)
    secs = time.perf_counter() - t
    with TemplateDB.open(db) as d:
        poses = d.poses()["frames"]
    Path(out).write_text(json.dumps({
        "seconds": secs, "timings_s": res.timings_s, "poses": poses, "edges_accepted": res.edges_accepted,
        "edges_rejected": res.edges_rejected, "keyframes": res.keyframes, "mesh_vertices": res.mesh_vertices,
        "maxrss_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))


def write_json(result: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", type=int, default=None, help="first N shared meshes (default all)")
    ap.add_argument("--offset", type=int, default=0, help="skip the first K meshes (to split a run)")
    ap.add_argument("--names", default=None, help="comma-separated mesh names (instead of --offset/--meshes)")
    ap.add_argument("--views", type=int, default=36, help="views per accuracy capture (two rings)")
    ap.add_argument("--mode", choices=("static", "turntable"), default="static",
                    help="accuracy captures: cameras on two rings around the object, or the object turning in "
                         "front of one camera (30 deg elevation; no peers: they register whole frames)")
    ap.add_argument("--e2e-views", type=int, default=100, help="frames of the end-to-end run (0 = skip)")
    ap.add_argument("--no-peers", action="store_true", help="skip the open3d peers")
    ap.add_argument("--no-scan", action="store_true", help="skip the gscan scans (peers only)")
    ap.add_argument("--no-masked-peers", action="store_true", help="skip the peers on masked depth")
    ap.add_argument("--wait-captures", action="store_true",
                    help="wait for the captures to be rendered by another process of a split run")
    ap.add_argument("--quick", action="store_true", help="3 meshes, 24 views, 40-frame end-to-end run")
    ap.add_argument("--json", type=Path, default=OUT / "scan.json", help="raw results")
    ap.add_argument("--tables", type=Path, default=None, help="only print the tables of an earlier (partial) JSON")
    ap.add_argument("--markdown", action="store_true", help="with --tables: Markdown tables")
    ap.add_argument("--merge", type=Path, nargs="*", help="with --tables: add the rows of these JSONs")
    ap.add_argument("--child-scan", nargs=3, metavar=("CAPTURE", "DB", "JSON"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if a.child_scan:
        child_scan(*a.child_scan)
        return 0
    if a.tables:
        old = json.loads(a.tables.read_text())
        for extra in a.merge or []:  # further JSONs of a split run: rows merged method by method
            more = json.loads(extra.read_text())
            for name, row in more.get("accuracy", {}).items():
                old.setdefault("accuracy", {}).setdefault(name, {}).update(row)
            if "e2e" in more:
                old["e2e"] = more["e2e"]
        if old.get("accuracy") and a.markdown:
            print(markdown_accuracy(old["accuracy"]))
        elif old.get("accuracy"):
            print_accuracy(old["accuracy"], old["views"])
        if "e2e" in old:
            print_e2e(old["e2e"])
        return 0
    if a.quick:
        a.meshes, a.views, a.e2e_views = a.meshes or 3, 24, 40
    OUT.mkdir(parents=True, exist_ok=True)
    names = a.names.split(",") if a.names else mesh_names()[a.offset:][: a.meshes]
    unknown = sorted(set(names) - set(mesh_names()))
    if unknown:
        ap.error(f"unknown meshes: {', '.join(unknown)}")
    t0 = time.perf_counter()
    result: dict = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "argv": sys.argv[1:],
                    "views": a.views, "elevations_deg": ELEVATIONS, "mode": a.mode}
    if a.e2e_views > 0:  # first, so that RUSAGE_CHILDREN holds this child alone
        result["e2e"] = e2e(a.e2e_views)
        print_e2e(result["e2e"])
        write_json(result, a.json)
    what = {w for w, off in (("scan", a.no_scan), ("peers", a.no_peers or a.mode == "turntable"),
                             ("peers_masked", a.no_masked_peers or a.mode == "turntable")) if not off}
    if names:  # --meshes 0: the end-to-end run alone
        accuracy(names, a.views, what, result, a.json, wait=a.wait_captures, mode=a.mode)
        print_accuracy(result["accuracy"], a.views)
    if "e2e" in result:
        print_e2e(result["e2e"])
    result["total_s"] = time.perf_counter() - t0
    write_json(result, a.json)
    print(f"\nraw results: {a.json}  (total {result['total_s'] / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
