"""Recordings as input: RealSense .bag, rosbag2 (.db3 file, bag folder) and .mcap, written here from views
rendered around a shared mesh (12 views, 320x240) with the ordinary libraries (rosbags' writers, the mcap
writer) in the layouts librealsense's recorder and realsense2_camera use.

- every kind reads the same frames, names, intrinsics and depth scale as the rendered capture folder;
- pyrealsense2's own playback opens the .bag and returns the frames gscan reads, pixel for pixel;
- a scan of each recording gives the same poses as a scan of the folder;
- unaligned depth (a depth camera 5 cm off, turned 2 degrees, other intrinsics) is reprojected within a
  millimetre of the truth, identically from every kind, and its scan is as accurate as the aligned capture's;
- image_transport's CompressedImage topics (PNG colour, compressedDepth, JPEG, 32FC1 inverse depth) and
  messages compressed alone with zstd (librealsense 2.58's .db3) read as the raw ones;
- pairing, streaming (bounded buffering, random access), and bad input through the real CLI.

RealSense recordings written by pyrealsense2's own recorder are tested in test_realsense_sdk.
"""
from __future__ import annotations

import json
import struct
import subprocess
import sys
import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest
from _recordings import K_COLOR, K_DEPTH, PERIOD_NS, T0_NS, T_depth_offset, playback, render_views, same_rs_intrinsics
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.errors import InputError
from gscan.evaluate.metrics import ate_rmse
from gscan.geometry.transforms import inv_T
from gscan.io import associate, open_sequence
from gscan.io.align import align_depth_reference, align_depth_to_color
from gscan.io.camera import DepthCamera, Intrinsics
from gscan.io.recordings.pairing import pair_frames, pair_tolerance
from gscan.scanning.options import ScanOptions
from gscan.scanning.pipeline import run_scan
from gscan.synth.recordings import RecordingFrame, write_mcap, write_realsense_bag, write_rosbag2
from gscan.template.db import TemplateDB

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def views(meshes_dir):
    """12 views; depth from the colour camera and from a depth camera at T_depth_offset()."""
    return render_views(meshes_dir, 12, T_color_depth=T_depth_offset())


@pytest.fixture(scope="module")
def recs(views, tmp_path_factory):
    """The rendered capture as a folder and as recordings of every kind."""
    root = tmp_path_factory.mktemp("recordings")
    out = {"folder": views.write_folder(root / "capture")}
    out["bag"] = write_realsense_bag(root / "d435.bag", views.frames(), K_COLOR)
    out["db3"] = write_rosbag2(root / "ros2_db3", views.frames(), K_COLOR, topics=("color", "aligned"))
    out["rosbag2"] = out["db3"].parent
    out["mcap"] = write_mcap(root / "ros2.mcap", views.frames(), K_COLOR, topics=("color", "aligned"))
    # unaligned: depth from the depth camera, extrinsics from the stream tf, /tf_static, realsense2_camera's message
    T = T_depth_offset()
    cam = DepthCamera(K_DEPTH, T)
    out["bag_unaligned"] = write_realsense_bag(root / "d435_unaligned.bag", views.frames(unaligned=True), K_COLOR, cam)
    out["mcap_unaligned"] = write_mcap(root / "unaligned.mcap", views.frames(unaligned=True), K_COLOR, cam)
    out["db3_unaligned"] = write_rosbag2(root / "unaligned_db3", views.frames(unaligned=True), K_COLOR, cam,
                                         extrinsics="realsense")
    return out


def _poses(db_path: Path) -> dict[str, np.ndarray]:
    with TemplateDB.open(db_path) as db:
        return {k: np.asarray(v) for k, v in db.poses()["frames"].items()}


@pytest.fixture(scope="module")
def folder_scan(recs, tmp_path_factory):
    out = tmp_path_factory.mktemp("scan") / "folder.gscan"
    res = run_scan(recs["folder"], out, ScanOptions())
    assert res.registered == 12
    return out


# ----------------------------------------------------------------------------------------- reading


@pytest.mark.parametrize("kind", ["bag", "db3", "rosbag2", "mcap"])
def test_recording_reads_the_capture_frames(recs, kind):
    folder = open_sequence(recs["folder"])
    with open_sequence(recs[kind]) as seq:
        assert seq.format == kind and not seq.aligned and seq.problems == {} and seq.damage == []
        assert seq.names == folder.names == [f"{i:06d}" for i in range(12)]
        assert seq.intrinsics == folder.intrinsics == K_COLOR
        assert seq.depth_scale == 0.001
        for name in seq.names:
            a, b = folder[name], seq[name]
            assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth), name
        assert seq.timestamps["000003"] == pytest.approx((T0_NS + 3 * PERIOD_NS) * 1e-9, abs=1e-9)
        assert seq.pair_tolerance_s == pytest.approx(0.5 * PERIOD_NS * 1e-9, rel=1e-4)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_compressed_image_topics_read_the_capture_frames(views, recs, storage, tmp_path):
    """image_transport's CompressedImage topics (colour .../image_raw/compressed as PNG, depth .../compressedDepth),
    as `ros2 bag record` stores a camera driver's compressed topics: the capture's frames, pixel for pixel, with
    the CameraInfo of the raw topic they were compressed from."""
    path = write_rosbag2(tmp_path / "compressed", views.frames(), K_COLOR, topics=("color", "aligned"),
                         storage=storage, transport="compressed")
    folder = open_sequence(recs["folder"])
    with open_sequence(path) as seq:
        assert seq.setup.compressed == {seq.setup.color_topic, seq.setup.depth_topic}
        assert seq.setup.color_topic.endswith("color/image_raw/compressed")
        assert seq.names == folder.names and seq.problems == {} and seq.intrinsics == K_COLOR
        for name in seq.names:
            a, b = folder[name], seq[name]
            assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth), name


@pytest.mark.parametrize("kind", ["bag", "bag_unaligned"])
def test_pyrealsense2_playback_returns_the_frames_gscan_reads(recs, kind):
    frames, info = playback(recs[kind])
    with open_sequence(recs[kind]) as seq:
        # librealsense's playback can, on a loaded machine, leave the first frameset unpaired and skip it: the
        # frames it delivers are then the last 11, each compared with gscan's below
        assert len(seq) == 12 and len(frames) in (11, 12), len(frames)
        skipped = len(seq) - len(frames)
        assert info["scale"] == pytest.approx(seq.depth_scale, rel=1e-6)
        assert same_rs_intrinsics(info["color"], seq.setup.color_intrinsics)
        assert same_rs_intrinsics(info["depth"], seq.setup.depth_camera.intrinsics)
        np.testing.assert_allclose(info["T_color_depth"], seq.setup.depth_camera.T_color_depth, atol=1e-6)
        for name, (color, raw) in zip(seq.names[skipped:], frames, strict=True):
            c, d = seq.raw(name)
            assert np.array_equal(color, c), name
            assert np.array_equal(raw.astype(np.float32) * np.float32(seq.depth_scale), d), name
            if kind == "bag":  # registered: the frame is the recording's depth as it is
                assert np.array_equal(seq[name].depth, d)


def test_depth_units_come_from_the_frames_when_the_option_is_missing(views, tmp_path):
    bag = write_realsense_bag(tmp_path / "no_option.bag", views.frames()[:2], K_COLOR, depth_units_option=False)
    with open_sequence(bag) as seq:
        assert seq.depth_scale == 0.001  # librealsense's per-frame depth units (Image header version "1")
        assert np.array_equal(seq[0].depth, open_sequence(bag)[0].depth)


@pytest.mark.parametrize("kind", ["bag_unaligned", "mcap_unaligned", "db3_unaligned"])
def test_unaligned_depth_is_reprojected_identically_by_every_kind(recs, kind):
    with open_sequence(recs["bag_unaligned"]) as ref, open_sequence(recs[kind]) as seq:
        assert seq.aligned and seq.setup.depth_camera.intrinsics == K_DEPTH
        np.testing.assert_allclose(seq.setup.depth_camera.T_color_depth, T_depth_offset(), atol=1e-9)
        for name in ("000000", "000007"):
            assert np.array_equal(seq[name].color, ref[name].color)
            assert np.array_equal(seq[name].depth, ref[name].depth)


def test_a_recording_refuses_an_outside_depth_calibration(recs):
    """A recording carries its own depth camera: --depth-intrinsics (for folders) is refused, naming it."""
    with pytest.raises(InputError, match="carries its own depth calibration") as e:
        open_sequence(recs["bag_unaligned"], depth_camera=DepthCamera(K_DEPTH))
    assert e.value.path == recs["bag_unaligned"]


# --------------------------------------------------------------------------------------- alignment


def test_alignment_puts_depth_where_the_colour_camera_sees_it(meshes_dir):
    """Noise-free depth from the offset depth camera, reprojected: within a millimetre of the colour camera's own
    depth at the median (the footprint splat is piecewise constant over a pixel), a few mm at the 90th percentile."""
    v = render_views(meshes_dir, 2, of_ring=12, T_color_depth=T_depth_offset(), clean=True)
    for d_depth, d_color in zip(v.offset_depths, v.depths, strict=True):
        a = align_depth_to_color(d_depth, DepthCamera(K_DEPTH, T_depth_offset()), K_COLOR)
        both = (a > 0) & (d_color > 0)
        err = np.abs(a - d_color)[both]
        assert both.mean() > 0.85  # the rest: outside the depth camera's view, or hidden from it
        assert np.median(err) < 0.001 and np.percentile(err, 90) < 0.003, (np.median(err), np.percentile(err, 90))
        # a misplaced reprojection (extrinsics inverted) is off by centimetres
        bad = align_depth_to_color(d_depth, DepthCamera(K_DEPTH, inv_T(T_depth_offset())), K_COLOR)
        both = (bad > 0) & (d_color > 0)
        assert np.median(np.abs(bad - d_color)[both]) > 0.003


def test_alignment_with_identical_cameras_is_the_identity():
    rng = np.random.default_rng(0)
    d = rng.uniform(0.3, 2.0, (30, 40)).astype(np.float32)
    d[rng.random(d.shape) < 0.2] = 0
    K = Intrinsics(50.0, 52.0, 19.5, 14.5, 40, 30)
    assert np.array_equal(align_depth_to_color(d, DepthCamera(K), K), d)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), tx=st.floats(-0.1, 0.1), ty=st.floats(-0.05, 0.05), tz=st.floats(-0.05, 0.05),
       ang=st.floats(-8.0, 8.0), scale=st.sampled_from([0.5, 1.0, 1.7]))
def test_alignment_kernel_matches_its_reference(seed, tx, ty, tz, ang, scale):
    rng = np.random.default_rng(seed)
    Kd = Intrinsics(40.0, 41.0, 15.2, 11.7, 32, 24)
    Kc = Intrinsics(40.0 * scale, 40.5 * scale, 16.0 * scale, 12.0 * scale, round(32 * scale), round(24 * scale))
    d = rng.uniform(0.2, 1.5, (24, 32)).astype(np.float32)
    d[rng.random(d.shape) < 0.15] = 0
    a = np.radians(ang)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [tx, ty, tz]
    fast = align_depth_to_color(d, DepthCamera(Kd, T), Kc)
    ref = align_depth_reference(d, DepthCamera(Kd, T), Kc)
    assert np.array_equal(fast, ref)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.7, 1.4), dc=st.floats(-3.0, 3.0))
def test_alignment_kernel_between_cameras_of_one_centre_matches_its_reference(seed, scale, dc):
    """T_color_depth = I (the colour camera's check, a colour camera of another focal length at the depth camera's
    centre) takes the kernel's shorter branch: the reference's values to the bit."""
    rng = np.random.default_rng(seed)
    Kd = Intrinsics(40.0, 41.0, 15.2, 11.7, 32, 24)
    Kc = Intrinsics(40.0 * scale, 41.0 * scale, 15.2 + dc, 11.7 - dc, 32, 24)
    d = rng.uniform(0.2, 1.5, (24, 32)).astype(np.float32)
    d[rng.random(d.shape) < 0.15] = 0
    assert np.array_equal(align_depth_to_color(d, DepthCamera(Kd), Kc), align_depth_reference(d, DepthCamera(Kd), Kc))


# ----------------------------------------------------------------------------------------- pairing


@settings(max_examples=60, deadline=None)
@given(c=st.lists(st.integers(0, 2_000_000_000), min_size=0, max_size=25),
       d=st.lists(st.integers(0, 2_000_000_000), min_size=0, max_size=25),
       tol_ms=st.floats(1.0, 100.0))
def test_pairing_is_tum_association(c, d, tol_ms):
    """pair_frames (O(N log N)) gives TUM associate.py's greedy closest-first one-to-one pairs."""
    got = pair_frames(np.array(c, dtype=np.int64), np.array(d, dtype=np.int64), tol_ms / 1000.0)
    want = associate(np.array(c, dtype=np.float64) * 1e-9, np.array(d, dtype=np.float64) * 1e-9, tol_ms / 1000.0)
    # ties broken the same way except where float seconds cannot tell nanoseconds apart: compare the distances
    assert len(got) == len(want)
    assert sorted(abs(c[i] - d[j]) for i, j in got.items()) == pytest.approx(
        sorted(abs(c[i] - d[j]) for i, j in want.items()), abs=2)
    assert len(set(got.values())) == len(got)
    assert all(abs(c[i] - d[j]) <= round(tol_ms * 1e6) for i, j in got.items())


def test_pair_tolerance_is_half_the_faster_frame_period():
    c = np.arange(10) * 33_333_333
    d = np.arange(30) * 11_111_111
    assert pair_tolerance(c, d) == pytest.approx(0.5 * 0.011111111)
    assert pair_tolerance(c[:1], d[:1]) == pytest.approx(0.5 / 30)


def test_unpaired_colour_frames_are_reported_and_left_out(views, tmp_path):
    frames = views.frames()[:6]
    for f in (frames[1], frames[4]):
        f.depth = None
    frames[2].depth_t_ns = frames[2].t_ns + 20_000_000  # 20 ms late: beyond half a frame period (16.7 ms)
    rec = write_rosbag2(tmp_path / "gaps", frames, K_COLOR, topics=("color", "aligned"))
    with open_sequence(rec) as seq:
        assert seq.names == ["000000", "000003", "000005"]
        assert sorted(seq.problems) == ["000001", "000002", "000004"]
        assert all("no depth frame on /camera/camera/aligned_depth_to_color/image_raw within 16.7 ms" in r
                   for r in seq.problems.values())
        assert np.array_equal(seq["000003"].color, views.colors[3])


def _damage_mcap_record(path: Path, topic: str, k: int) -> None:
    """Make the k-th message record of `topic` in an uncompressed MCAP declare 2^40 bytes: the reader loses the
    records after it in its chunk, as a damaged file does."""
    import struct

    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    channel = next(c.id for c in summary.channels.values() if c.topic == topic)
    data = bytearray(path.read_bytes())
    i, seen = 0, 0
    while True:  # a message record: opcode 0x05, u64 length, u16 channel id, ...
        i = data.index(b"\x05", i)
        length, ch = struct.unpack_from("<QH", data, i + 1)
        if ch == channel and 22 < length < len(data) - i:
            if seen == k:
                break
            seen += 1
            i += 9 + length
            continue
        i += 1
    struct.pack_into("<Q", data, i + 1, 2**40)
    path.write_bytes(bytes(data))


def test_damaged_records_are_reported_as_damage(views, tmp_path):
    """An MCAP whose colour record declares 2^40 bytes loses the records after it in its chunk: the damage is
    reported (topic, messages listed and read, where), in the scan's summary and --json, and a colour frame whose
    depth was lost is said to be lost to the damage, not "no depth frame within 16.7 ms"."""
    rec = write_mcap(tmp_path / "damaged.mcap", views.frames(), K_COLOR, topics=("color", "aligned"),
                     compressed=False)
    _damage_mcap_record(rec, "/camera/camera/color/image_raw", 4)
    with open_sequence(rec) as seq:
        assert seq.damage and all("damaged records:" in d and "could not be read" in d for d in seq.damage)
        assert any("/camera/camera/aligned_depth_to_color/image_raw" in d for d in seq.damage), seq.damage
        lost = [n for n, why in seq.problems.items() if "among the recording's damaged records" in why]
        assert lost and not any("within 16.7 ms" in why for why in seq.problems.values()), seq.problems
    proc = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(rec), "-o", str(tmp_path / "d.gscan"),
                           "--json"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads(proc.stdout)
    assert res["damage"] == seq.damage
    assert all(res["unregistered_reasons"][n] == seq.problems[n] for n in lost)
    assert "damaged recording:" in proc.stderr or "damaged records" in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "gscan.cli", "track", str(tmp_path / "d.gscan"), str(rec), "--json"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    tracked = json.loads(proc.stdout)
    assert tracked["damage"] == seq.damage and set(lost) <= set(tracked["unreadable"]), tracked["unreadable"]


def test_a_rosbag2_folder_of_a_damaged_mcap_reports_its_damage_and_reads_the_rest(tmp_path):
    """A rosbag2 folder (metadata.yaml + one MCAP) whose 5th colour record declares 2^40 bytes is read as the bare MCAP
    is: the records lost are reported as damage and the frames before them read, not the whole folder refused."""
    frames = _tiny(12)
    rec = write_rosbag2(tmp_path / "folder", frames, K_TINY, storage="mcap", topics=("color", "aligned"))
    _damage_mcap_record(rec, "/camera/camera/color/image_raw", 4)
    with open_sequence(rec.parent) as seq:
        assert seq.format == "rosbag2" and len(seq.damage) == 2, seq.damage
        assert all(line.startswith(f"{rec.parent}: damaged records: ") and "could not be read" in line
                   for line in seq.damage), seq.damage
        assert seq.names[:4] == ["000000", "000001", "000002", "000003"]
        for i, name in enumerate(seq.names):
            assert np.array_equal(seq[name].color, frames[i].color), name


# --------------------------------------------------------------------------------------- streaming


def test_frames_stream_through_the_file_and_random_access_restarts(views, tmp_path):
    """In-order reading keeps at most one message of a later frame; any order gives the same frames; reading a
    recording allocates a few frames' worth of memory, not the recording's."""
    frames = [RecordingFrame(f.color, f.depth, T0_NS + i * PERIOD_NS)
              for i, f in enumerate(views.frames() * 8)]  # 96 frames, ~22 MB
    bag = write_realsense_bag(tmp_path / "long.bag", frames, K_COLOR)
    size = bag.stat().st_size
    with open_sequence(bag) as seq:
        assert len(seq) == 96
        tracemalloc.start()
        try:
            in_order = []
            for k, f in enumerate(seq.iter_frames(skip_bad=False)):
                assert len(seq._buffer) <= 1
                if k % 19 == 0:
                    in_order.append((f.name, f.depth.copy()))
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert peak < 0.25 * size, (peak, size)
        for name, depth in reversed(in_order):
            assert np.array_equal(seq[name].depth, depth)


# ------------------------------------------------------------------------------------------- scans


@pytest.mark.parametrize("kind", ["bag", "db3", "mcap"])
def test_scan_of_a_recording_gives_the_folder_scan_poses(recs, folder_scan, tmp_path, kind):
    out = tmp_path / f"{kind}.gscan"
    res = run_scan(recs[kind], out, ScanOptions())
    assert res.registered == 12 and res.problems == {}
    ref, got = _poses(folder_scan), _poses(out)
    assert sorted(got) == sorted(ref)
    for name in ref:
        np.testing.assert_array_equal(got[name], ref[name])


def test_scan_cli_on_a_bag_with_unpaired_frames(views, tmp_path):
    """Through the CLI: frames without depth are skipped by name, the others registered; exit 0."""
    frames = views.frames()
    frames[5].depth = None
    frames[9].depth = None
    bag = write_realsense_bag(tmp_path / "gaps.bag", frames, K_COLOR)
    out = tmp_path / "gaps.gscan"
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(bag), "-o", str(out), "--json"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300, check=False)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["frames"] == 12 and res["registered"] == 10
    assert sorted(res["skipped"]) == ["000005", "000009"]
    assert "no depth frame" in res["skipped"]["000005"]
    assert sorted(_poses(out)) == [f"{i:06d}" for i in range(12) if i not in (5, 9)]


def test_unaligned_recording_scans_as_accurately_as_the_aligned_capture(recs, views, folder_scan, tmp_path):
    """Bound: the unaligned scan's ATE is within max(2 x, +1 mm) of the aligned capture's (measured: 1.2 vs
    0.5 mm), and under the 5 mm of the static-capture scan tests."""
    out = tmp_path / "unaligned.gscan"
    res = run_scan(recs["bag_unaligned"], out, ScanOptions())
    assert res.registered == 12

    def ate(path: Path) -> float:
        poses = _poses(path)
        names = sorted(poses)
        return ate_rmse([poses[n] for n in names], [inv_T(views.T_cam_obj[int(n)]) for n in names])

    aligned, unaligned = ate(folder_scan), ate(out)
    assert unaligned <= max(2.0 * aligned, aligned + 0.001) and unaligned < 0.005, (aligned, unaligned)


def _cli_json(*args: str | Path) -> dict:
    r = subprocess.run([sys.executable, "-m", "gscan.cli", *map(str, args), "--json"], capture_output=True,
                       text=True, cwd=ROOT, timeout=300, check=False)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_eval_of_a_recording_scores_the_frames_of_the_folder(recs, folder_scan, tmp_path):
    """`gscan eval` on a rosbag2 folder (a recording carries no ground truth) estimates every frame, as on the
    capture folder it was written from: the same estimated poses, bit for bit."""
    rec = _cli_json("eval", folder_scan, recs["rosbag2"], "-o", tmp_path / "rec.csv")
    ref = _cli_json("eval", folder_scan, recs["folder"], "-o", tmp_path / "folder.csv")
    assert rec["n_images"] == ref["n_images"] == 12 and rec["n_found"] == ref["n_found"] > 0
    assert [r["T_cam_obj"] for r in rec["rows"]] == [r["T_cam_obj"] for r in ref["rows"]]


def test_resume_refuses_a_recording_that_changed(views, tmp_path):
    """A scan of a recording resumed after the recording changed (here its folder gained a file) is refused with
    one line naming the database, and the database is left as it was."""
    bag = write_rosbag2(tmp_path / "four", views.frames()[:4], K_COLOR).parent
    out = tmp_path / "four.gscan"
    res = _cli_json("scan", bag, "-o", out)
    assert res["registered"] >= 2
    (bag / "notes.txt").write_text("calibrated again\n")
    before = out.read_bytes()
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(bag), "-o", str(out), "--resume"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300, check=False)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {out}") and "frame 000000 changed" in lines[0], lines
    assert out.read_bytes() == before


# --------------------------------------------------------------------------------------- bad input


def _tiny(n: int = 3, **kw) -> list[RecordingFrame]:
    rng = np.random.default_rng(1)
    return [RecordingFrame(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), np.full((48, 64), 500, np.uint16),
                           T0_NS + i * PERIOD_NS, **kw) for i in range(n)]


K_TINY = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _truncate(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


BAD = {
    "bag-without-depth": (lambda p: write_realsense_bag(p / "x.bag", _tiny(), K_TINY, streams=("Color",)),
                          "no depth stream"),
    "bag-without-colour": (lambda p: write_realsense_bag(p / "x.bag", _tiny(), K_TINY, streams=("Depth",)),
                           "no colour stream"),
    "bag-without-camera-info": (lambda p: write_realsense_bag(p / "x.bag", _tiny(), K_TINY, camera_info=False),
                                "no CameraInfo for /device_0/sensor_1/Color_0/image/data"),
    "bag-truncated": (lambda p: _truncate(write_realsense_bag(p / "x.bag", _tiny(), K_TINY)), "truncated"),
    "bag-never-pairs": (lambda p: write_realsense_bag(p / "x.bag", [RecordingFrame(f.color, f.depth, f.t_ns,
                                                                                   f.t_ns + 400_000_000)
                                                                    for f in _tiny()], K_TINY),
                        "timestamps never pair"),
    "bag-empty": (lambda p: _write(p / "x.bag", b""), "file is empty"),
    "bag-not-a-bag": (lambda p: _write(p / "x.bag", b"not a bag at all" * 8), "cannot open"),
    "db3-without-depth": (lambda p: write_rosbag2(p / "x", _tiny(), K_TINY, topics=("color",)),
                          "no depth image topic"),
    "db3-truncated": (lambda p: _truncate(write_rosbag2(p / "x", _tiny(), K_TINY, topics=("color", "aligned"))),
                      "x.db3"),
    "db3-no-extrinsics": (lambda p: write_rosbag2(p / "x", _tiny(), K_TINY, DepthCamera(K_TINY),
                                                         extrinsics="none"),
                          "no transform between them"),
    "mcap-without-colour": (lambda p: write_mcap(p / "x.mcap", _tiny(), K_TINY, topics=("depth",)),
                            "no colour image topic"),
    "mcap-bayer-colour": (lambda p: write_mcap(p / "x.mcap", _tiny(), K_TINY, color_encoding="bayer_rggb8"),
                          "/camera/camera/color/image_raw (bayer_rggb8: an encoding gscan does not read)"),
    "db3-bayer-colour": (lambda p: write_rosbag2(p / "x", _tiny(), K_TINY, color_encoding="bayer_rggb8"),
                         "colour encodings read: rgb8, bgr8"),
    "mcap-truncated": (lambda p: _truncate(write_mcap(p / "x.mcap", _tiny(), K_TINY, topics=("color", "aligned"))),
                       "truncated or corrupt MCAP"),
    "mcap-never-pairs": (lambda p: write_mcap(p / "x.mcap", _tiny(depth_t_ns=T0_NS + 5 * 10**9), K_TINY,
                                              topics=("color", "aligned")), "timestamps never pair"),
    "wrong-depth-topic": (lambda p: write_mcap(p / "x.mcap", _tiny(), K_TINY, topics=("color", "aligned")),
                          "--depth-topic /camera/depth: no such sensor_msgs/Image topic"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_recording_exits_2_with_one_line(tmp_path, case):
    make, needle = BAD[case]
    rec = make(tmp_path)
    out = tmp_path / "out.gscan"
    cmd = [sys.executable, "-m", "gscan.cli", "scan", str(rec), "-o", str(out)]
    if case == "wrong-depth-topic":
        cmd += ["--depth-topic", "/camera/depth"]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=120, check=False)
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in r.stderr, r.stderr
    assert str(rec) in lines[0] and needle in lines[0], lines[0]
    assert not out.exists()


def test_topic_options_on_a_folder_are_refused(recs, tmp_path):
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(recs["folder"]), "-o", str(tmp_path / "o.gscan"),
                        "--color-topic", "/camera/color/image_raw"], capture_output=True, text=True, cwd=ROOT,
                       timeout=120, check=False)
    assert r.returncode == 2 and "apply to recordings" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_recording_frames_above_the_pixel_limit_are_refused_from_their_header(recs, monkeypatch, tmp_path):
    """The pixel limit every image file is held to (GSCAN_MAX_IMAGE_PIXELS) holds for a recording's image messages,
    checked on their headers: a recording whose images are all over it is bad input (exit 2, one line naming the
    file and the limit), and nothing is written."""
    monkeypatch.setenv("GSCAN_MAX_IMAGE_PIXELS", str(320 * 240 - 1))
    with pytest.raises(InputError, match="above the limit of 76799 pixels"):
        open_sequence(recs["mcap"])
    out = tmp_path / "t.gscan"
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(recs["bag"]), "-o", str(out)],
                       capture_output=True, text=True, cwd=ROOT, timeout=120, check=False)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and str(recs["bag"]) in lines[0], r.stderr
    assert "above the limit of 76799 pixels" in lines[0] and not out.exists()


def _compressed_msg(fmt: str, data: bytes, wire: str = "cdr") -> bytes:
    """A CompressedImage serialised as ROS 2 (CDR) or ROS 1 writes it, its header stamped 1.5 s in frame "cam"."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if wire == "ros1" else Stores.ROS2_HUMBLE)
    T = ts.types
    stamp = T["builtin_interfaces/msg/Time"](sec=1, nanosec=500_000_000)
    H = T["std_msgs/msg/Header"]
    hdr = H(seq=7, stamp=stamp, frame_id="cam") if wire == "ros1" else H(stamp=stamp, frame_id="cam")
    msg = T["sensor_msgs/msg/CompressedImage"](header=hdr, format=fmt, data=np.frombuffer(data, np.uint8))
    if wire == "ros1":
        return bytes(ts.serialize_ros1(msg, "sensor_msgs/msg/CompressedImage"))
    return bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))


def test_compressed_depth_of_float_depth_is_its_quantised_inverse_depth():
    """compressed_depth_image_transport's 32FC1 coding (inverse depth quantised to 16 bits, depthQuantA = 100,
    depthQuantB = 1 - 100 / 10 m, 0 = invalid) decodes to metres within its quantisation step, holes kept."""
    from gscan.io.recordings.messages import depth_raw, parse_image

    rng = np.random.default_rng(3)
    z = rng.uniform(0.3, 3.0, (48, 64)).astype(np.float32)
    z[5:9, 10:20] = 0.0
    a, b = 100.0, 1.0 - 100.0 / 10.0
    inv = np.where(z > 0, np.rint(a / np.where(z > 0, z, 1.0) + b), 0).astype(np.uint16)
    ok, png = cv2.imencode(".png", inv)
    assert ok
    msg = parse_image("cdr", True, _compressed_msg("32FC1; compressedDepth png",
                                                   struct.pack("<iff", 0, a, b) + png.tobytes()))
    assert (msg.width, msg.height, msg.encoding, msg.stamp_ns, msg.frame_id) == (64, 48, "32FC1", 1_500_000_000, "cam")
    got = depth_raw(msg)
    assert got.dtype == np.float32 and np.all(got[5:9, 10:20] == 0)
    # half a quantisation step of the inverse depth either way: at most 0.5 z^2 / (a - 0.5 z) metres
    bound = 0.5 * z ** 2 / (a - 0.5 * z)
    assert np.all(np.abs(got - z)[z > 0] <= bound[z > 0] + 1e-6)


@pytest.mark.parametrize("wire", ["ros1", "cdr"])
def test_jpeg_colour_reads_as_opencv_decodes_it(wire):
    """A bare "jpeg" CompressedImage (old drivers, image_transport's bgr8) of a ROS 1 bag or a rosbag2: its size
    from the JPEG frame header without decoding, its pixels as OpenCV decodes the file, RGB."""
    from gscan.io.recordings.messages import color_pixels, parse_image

    rgb = np.random.default_rng(4).integers(0, 256, (40, 56, 3), dtype=np.uint8)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    msg = parse_image(wire, True, _compressed_msg("jpeg", jpg.tobytes(), wire))
    assert (msg.width, msg.height, msg.compression) == (56, 40, "image")
    assert (msg.stamp_ns, msg.frame_id, msg.encoding) == (1_500_000_000, "cam", "bgr8")
    want = cv2.cvtColor(cv2.imdecode(jpg, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(color_pixels(msg), want)


def test_messages_compressed_alone_with_zstd_read_as_the_plain_ones(recs, tmp_path):
    """librealsense 2.58 compresses every message of its .db3 alone with zstd and writes no metadata.yaml that
    says so: such a file reads as the plain one; a message whose zstd frame is cut short spoils its frame only
    (reported by name), not the recording."""
    import sqlite3

    import zstandard

    db3 = tmp_path / "zstd.db3"
    db3.write_bytes(recs["db3"].read_bytes())
    with sqlite3.connect(db3) as con:
        rows = con.execute("SELECT id, data FROM messages").fetchall()
        con.executemany("UPDATE messages SET data = ? WHERE id = ?",
                        [(zstandard.ZstdCompressor().compress(data), i) for i, data in rows])
    with open_sequence(recs["db3"]) as ref, open_sequence(db3) as seq:
        assert seq.names == ref.names and seq.problems == {} and seq.intrinsics == ref.intrinsics
        for name in ("000000", "000005", "000011"):
            assert np.array_equal(seq[name].color, ref[name].color) and np.array_equal(seq[name].depth, ref[name].depth)
    with sqlite3.connect(db3) as con:
        mid, data = con.execute("SELECT m.id, m.data FROM messages m JOIN topics t ON m.topic_id = t.id WHERE "
                                "t.name LIKE '%/color/image_raw' ORDER BY m.timestamp LIMIT 1 OFFSET 4").fetchone()
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (data[: len(data) // 2], mid))
    with open_sequence(db3) as seq:
        assert "000004" not in seq.names and len(seq) == 11
        assert "zstd data does not decompress" in seq.problems["000004"]
