"""Benchmark of reading recordings (gscan.io.recordings): frames per second of each kind, and alignment's cost.

A few views of a shared mesh are rendered at --size (colour camera, its own depth, and the depth of a
second camera 5 cm off and turned 2 degrees with other intrinsics), repeated with new timestamps to
--frames frames at 30 fps and written as:

  folder        the capture layout (PNG), read by gscan.io.sequence: the baseline
  bag           RealSense .bag (librealsense layout, depth registered to colour), uncompressed
  bag-lz4       the same with LZ4 chunk compression (the recorder's compression option)
  db3           rosbag2 sqlite3 (realsense2_camera topics, aligned_depth_to_color)
  mcap          bare MCAP, the mcap writer's default zstd chunks
  bag-unaligned RealSense .bag with the depth camera's depth: read with reprojection into the colour camera

For each: the open time (one pass over the headers, pairing) and the frames per second of reading every frame in
order (RGB + metres in the colour camera), as a ratio to the folder's rate measured in the same process; the
peak of Python allocations while streaming (tracemalloc) against the file's size; the fastest of --passes
reads (the benchmark machines are shared). Alignment: the time of
`align_depth_to_color` on one frame (best of --repeat), in ms and as a ratio to reading one registered bag
frame. For reference, pyrealsense2's playback of the same .bag (non-real-time, frames only) and rs.align. Accuracy:
noise-free depth of the offset depth camera reprojected by gscan and by rs.align, against the colour camera's own
noise-free depth (median and 90th percentile of the error over 4 views).

    python bench/recordings.py                      # 300 frames at 640x480
    python bench/recordings.py --frames 60 --size 320x240
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscan.geometry.transforms import transform_points  # noqa: E402
from gscan.io import open_sequence  # noqa: E402
from gscan.io.align import align_depth_to_color  # noqa: E402
from gscan.io.camera import DepthCamera, Intrinsics  # noqa: E402
from gscan.synth import (  # noqa: E402
    SynthScene,
    default_distance,
    load_textured_mesh,
    orbit_poses,
    rest_on_table,
    write_capture,
)
from gscan.synth.recordings import (  # noqa: E402
    RecordingFrame,
    depth_to_raw,
    write_mcap,
    write_realsense_bag,
    write_rosbag2,
)

MESHES = ROOT.parent / "shared" / "data" / "meshes"
MESH = "Crayola_Bonus_64_Crayons"
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333


def T_offset() -> np.ndarray:
    a = np.radians(2.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    T[:3, 3] = [0.05, 0.015, 0.0]
    return T


def render(n_views: int, w: int, h: int) -> tuple[Intrinsics, Intrinsics, list, list, list, list]:
    f = 615.0 * w / 640.0
    Kc = Intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
    Kd = Intrinsics(0.94 * f, 0.95 * f, w / 2 + 3.0, h / 2 - 2.0, w, h)
    mesh = load_textured_mesh(MESHES / MESH / "model_0.obj")
    T_wo = rest_on_table(mesh)
    scene = SynthScene([(mesh, T_wo)], seed=0)
    center = transform_points(T_wo, mesh.center[None])[0]
    colors, depths, offset, rendered = [], [], [], []
    for i, T_wc in enumerate(orbit_poses(center, default_distance(mesh, Kc), [40.0], n_views)):
        fr = scene.render(T_wc, Kc, rng=np.random.default_rng([0, i]))
        rendered.append(fr)
        colors.append(fr.color)
        depths.append(depth_to_raw(fr.depth))
        offset.append(depth_to_raw(scene.render(T_wc @ T_offset(), Kd, rng=np.random.default_rng([0, i, 1])).depth))
    return Kc, Kd, colors, depths, offset, rendered


def frames(colors: list, depths: list, n: int):
    for i in range(n):
        yield RecordingFrame(colors[i % len(colors)], depths[i % len(depths)], T0_NS + i * PERIOD_NS)


def read_all(path: Path, passes: int) -> dict:
    """Open and read every frame `passes` times: the fastest pass (the machine is shared), the peak allocations."""
    t_open = t_read = float("inf")
    for _ in range(passes):
        t0 = time.perf_counter()
        seq = open_sequence(path)
        t_open = min(t_open, time.perf_counter() - t0)
        tracemalloc.start()
        t0 = time.perf_counter()
        n = 0
        for _ in seq.iter_frames(skip_bad=False):
            n += 1
        t_read = min(t_read, time.perf_counter() - t0)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        if hasattr(seq, "close"):
            seq.close()
    size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size
    return {"frames": n, "open_s": t_open, "read_s": t_read, "fps": n / t_read, "ms_per_frame": 1000 * t_read / n,
            "peak_alloc_mb": peak / 2**20, "size_mb": size / 2**20}


def rs_playback(bag: Path, align: bool) -> dict:
    import pyrealsense2 as rs

    cfg = rs.config()
    cfg.enable_device_from_file(str(bag), repeat_playback=False)
    pipe = rs.pipeline()
    cfg.resolve(rs.pipeline_wrapper(pipe)).get_device().as_playback().set_real_time(False)
    pipe.start(cfg)
    al = rs.align(rs.stream.color)
    n, t_align = 0, 0.0
    t0 = t_last = time.perf_counter()
    while True:
        ok, fs = pipe.try_wait_for_frames(1000)
        if not ok:
            break
        t_last = time.perf_counter()
        if align:
            ta = time.perf_counter()
            fs = al.process(fs)
            np.asanyarray(fs.get_depth_frame().get_data())
            t_align += time.perf_counter() - ta
        np.asanyarray(fs.get_color_frame().get_data())
        n += 1
    dt = t_last - t0  # to the last frame (the wait after it times out)
    pipe.stop()
    return {"frames": n, "fps": n / dt, "align_ms": 1000 * t_align / max(n, 1)}


def alignment_accuracy(n_views: int, w: int, h: int, tmp: Path) -> dict:
    """Depth error (mm, median and 90th percentile over pixels valid in both) of gscan's reprojection and of
    rs.align, against the colour camera's own noise-free depth, for noise-free depth from the depth camera
    offset by T_offset() (5 cm, 2 deg about y) and by its translation alone."""
    import pyrealsense2 as rs

    f = 615.0 * w / 640.0
    Kc = Intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
    Kd = Intrinsics(0.94 * f, 0.95 * f, w / 2 + 3.0, h / 2 - 2.0, w, h)
    mesh = load_textured_mesh(MESHES / MESH / "model_0.obj")
    T_wo = rest_on_table(mesh)
    scene = SynthScene([(mesh, T_wo)], seed=0)
    center = transform_points(T_wo, mesh.center[None])[0]
    cams = orbit_poses(center, default_distance(mesh, Kc), [40.0], n_views)
    out = {}
    for label, T in (("5 cm + 2 deg", T_offset()), ("5 cm", np.block([[np.eye(3), T_offset()[:3, 3:]],
                                                                       [np.zeros((1, 3)), np.ones((1, 1))]]))):
        truth, fr = [], []
        for i, T_wc in enumerate(cams):
            c = scene.render(T_wc, Kc, noise=False)
            d = scene.render(T_wc @ T, Kd, noise=False)
            truth.append(c.depth_clean)
            fr.append(RecordingFrame(c.color, depth_to_raw(d.depth_clean), T0_NS + i * PERIOD_NS))
        bag = write_realsense_bag(tmp / f"acc{len(out)}.bag", fr, Kc, DepthCamera(Kd, T))
        seq = open_sequence(bag)
        cfg = rs.config()
        cfg.enable_device_from_file(str(bag), repeat_playback=False)
        pipe = rs.pipeline()
        cfg.resolve(rs.pipeline_wrapper(pipe)).get_device().as_playback().set_real_time(False)
        pipe.start(cfg)
        al = rs.align(rs.stream.color)
        errs: dict[str, list] = {"gscan": [], "rs.align": []}
        for k in range(len(cams)):
            ok, fs = pipe.try_wait_for_frames(2000)
            assert ok, "pyrealsense2 returned fewer frames than the bag holds"
            ra = np.asanyarray(al.process(fs).get_depth_frame().get_data()).astype(np.float32) * np.float32(0.001)
            for name, a in (("gscan", seq[k].depth), ("rs.align", ra)):
                both = (a > 0) & (truth[k] > 0)
                errs[name].append(np.abs(a - truth[k])[both])
        pipe.stop()
        seq.close()
        out[label] = {name: {"median_mm": 1000 * float(np.median(np.concatenate(e))),
                             "p90_mm": 1000 * float(np.percentile(np.concatenate(e), 90))} for name, e in errs.items()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--repeat", type=int, default=20, help="alignment timings (the best is reported)")
    ap.add_argument("--passes", type=int, default=3, help="reads of each recording (the fastest is reported)")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "out" / "recordings.json")
    a = ap.parse_args()
    w, h = (int(x) for x in a.size.split("x"))
    Kc, Kd, colors, depths, offset, rendered = render(a.views, w, h)
    tmp = Path(tempfile.mkdtemp(prefix="gscan-bench-rec-"))
    try:
        paths = {}
        reps = [rendered[i % len(rendered)] for i in range(a.frames)]
        paths["folder"] = write_capture(tmp / "folder", reps, Kc, write_masks=False)
        paths["bag"] = write_realsense_bag(tmp / "d435.bag", frames(colors, depths, a.frames), Kc)
        paths["bag-lz4"] = write_realsense_bag(tmp / "d435_lz4.bag", frames(colors, depths, a.frames), Kc,
                                               compress=True)
        paths["db3"] = write_rosbag2(tmp / "ros2", frames(colors, depths, a.frames), Kc, topics=("color", "aligned"))
        paths["mcap"] = write_mcap(tmp / "ros2.mcap", frames(colors, depths, a.frames), Kc, topics=("color", "aligned"))
        paths["bag-unaligned"] = write_realsense_bag(tmp / "unaligned.bag", frames(colors, offset, a.frames), Kc,
                                                     DepthCamera(Kd, T_offset()))
        open_sequence(paths["bag-unaligned"])[0]  # numba's compiled kernel loaded before timing
        res = {k: read_all(p, a.passes) for k, p in paths.items()}
        base = res["folder"]["fps"]
        for r in res.values():
            r["x_folder"] = r["fps"] / base
        d = open_sequence(paths["bag-unaligned"]).raw(0)[1]
        times = []
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            align_depth_to_color(d, DepthCamera(Kd, T_offset()), Kc)
            times.append(time.perf_counter() - t0)
        align_ms = 1000 * min(times)
        res["align"] = {"ms": align_ms, "x_bag_frame": align_ms / res["bag"]["ms_per_frame"]}
        res["pyrealsense2"] = {"bag": rs_playback(paths["bag"], False),
                               "bag-unaligned+rs.align": rs_playback(paths["bag-unaligned"], True)}
        res["accuracy"] = alignment_accuracy(4, w, h, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res["setup"] = {"frames": a.frames, "size": a.size, "views": a.views}
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(res, indent=1) + "\n")
    print(f"{a.frames} frames {a.size}; folder (PNG) baseline {base:.1f} fps")
    print("| kind | open (s) | read (frames/s) | x folder | ms / frame | peak alloc (MB) | file (MB) |")
    print("|---|---|---|---|---|---|---|")
    for k, r in res.items():
        if "fps" in r and "open_s" in r:
            print(f"| {k} | {r['open_s']:.2f} | {r['fps']:.1f} | {r['x_folder']:.2f} | {r['ms_per_frame']:.1f} | "
                  f"{r['peak_alloc_mb']:.1f} | {r['size_mb']:.0f} |")
    al = res["align"]
    print(f"align_depth_to_color: {al['ms']:.2f} ms a frame (best of {a.repeat}), {al['x_bag_frame']:.2f} x reading "
          f"one registered .bag frame")
    p = res["pyrealsense2"]
    print(f"pyrealsense2 playback (non-real-time): {p['bag']['fps']:.1f} frames/s; rs.align "
          f"{p['bag-unaligned+rs.align']['align_ms']:.2f} ms a frame")
    print("aligned depth against the colour camera's own (noise-free), mm median / p90:")
    for label, r in res["accuracy"].items():
        print(f"  depth camera {label}: gscan {r['gscan']['median_mm']:.2f} / {r['gscan']['p90_mm']:.2f}, "
              f"rs.align {r['rs.align']['median_mm']:.2f} / {r['rs.align']['p90_mm']:.2f}")


if __name__ == "__main__":
    main()
