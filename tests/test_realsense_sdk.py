"""RealSense recordings written by pyrealsense2's own recorder (a software device fed rendered views), in the
layout of each SDK version at hand: the installed one (2.58 and later write rosbag2 `.db3`, colour as PNG or zstd
and depth as compressedDepth PNG from 2.59), and any other listed in GSCAN_TEST_PYREALSENSE2 (folders, separated
by the path separator, each holding another pyrealsense2, e.g. `pip install --no-deps --target DIR
pyrealsense2==2.58.4.10922` for 2.58's zstd-compressed messages, or 2.57.7 for the `.bag`).

- every layout reads the frames fed, the intrinsics, depth scale, extrinsics and camera timestamps;
- pyrealsense2's own playback of the installed SDK's `.db3` returns the frames gscan reads;
- colour formats the SDK stores otherwise (BGR8, RGBA8 as PNG; YUYV zstd-compressed) read as fed;
- a frame whose image does not decode is reported by name; a `.db3` without intrinsics exits 2 naming it;
- a row missing from the `.db3` is reported as damage, its frame as lost to it;
- `gscan scan`, `track` and `capture --from` of a `.db3` give what they give for a folder of the same frames.
"""
from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from _recordings import K_COLOR, K_DEPTH, T_depth_offset, playback, render_views, same_rs_intrinsics

from gscan.errors import InputError
from gscan.io import open_sequence
from gscan.template.db import TemplateDB

ROOT = Path(__file__).resolve().parents[1]
RECORDER = Path(__file__).with_name("_rs_record.py")
T0_MS = 1_000.0  # the first frame's camera timestamp
PERIOD_MS = 1000.0 / 30.0
EXTRA_SDKS = [p for p in os.environ.get("GSCAN_TEST_PYREALSENSE2", "").split(os.pathsep) if p]


def _sdk_id(path: str | None) -> str:
    if path is None:
        return "installed"
    infos = sorted(Path(path).glob("pyrealsense2-*.dist-info"))
    return infos[0].name.removesuffix(".dist-info").split("-")[1] if infos else Path(path).name


SDKS = [pytest.param(None, id="installed")] + [pytest.param(p, id=_sdk_id(p)) for p in EXTRA_SDKS]
if not EXTRA_SDKS:
    SDKS.append(pytest.param("", id="other", marks=pytest.mark.skip(
        reason="no other pyrealsense2 version: GSCAN_TEST_PYREALSENSE2 lists none (pip install --no-deps "
               "--target DIR pyrealsense2==2.58.4.10922 or ==2.57.7.10387)")))


def record(views, out: Path, sdk: str | None = None, unaligned: bool = False, color_format: str = "rgb8",
           n: int | None = None, **extra: float) -> tuple[Path, str]:
    """A recording of the views written by pyrealsense2's recorder (the SDK at `sdk`, or the installed one), as
    OUT.db3 or, when that SDK writes ROS 1 bags, OUT.bag; and the SDK's version. Aligned: depth from the colour
    camera, identity extrinsics; unaligned: from the depth camera at T_depth_offset() with K_DEPTH. extra: the
    recorder's optional settings (tests/_rs_record.py)."""
    frames = views.frames(unaligned=unaligned)[:n]
    K_d, T = (K_DEPTH, T_depth_offset()) if unaligned else (K_COLOR, np.eye(4))
    data = out.with_suffix(".npz")
    np.savez(data, colors=np.stack([f.color for f in frames]), depths=np.stack([f.depth for f in frames]),
             K_color=K_COLOR.K, K_depth=K_d.K, T_color_depth=T, depth_units=0.001, period_ms=PERIOD_MS,
             t0_ms=T0_MS, color_format=color_format, **extra)
    env = dict(os.environ)
    if sdk:
        env["PYTHONPATH"] = os.pathsep.join([sdk, env.get("PYTHONPATH", "")])
    ask = "import importlib.metadata as m; print(m.version('pyrealsense2'))"
    version = subprocess.run([sys.executable, "-c", ask], env=env, capture_output=True, text=True,
                             check=True).stdout.strip()
    major, minor = (int(v) for v in version.split(".")[:2])
    path = out.with_suffix(".db3" if (major, minor) >= (2, 58) else ".bag")
    r = subprocess.run([sys.executable, str(RECORDER), str(data), str(path)], env=env, capture_output=True,
                       text=True, timeout=120, check=False)
    assert r.returncode == 0 and path.is_file(), r.stderr
    return path, version


@pytest.fixture(scope="module")
def views(meshes_dir):
    return render_views(meshes_dir, 12, T_color_depth=T_depth_offset())


@pytest.fixture(scope="module")
def folder(views, tmp_path_factory):
    return views.write_folder(tmp_path_factory.mktemp("sdk") / "capture")


@pytest.fixture(scope="module")
def db3(views, tmp_path_factory):
    """The views recorded by the installed SDK (aligned)."""
    path, version = record(views, tmp_path_factory.mktemp("sdk") / "d435")
    assert path.suffix == ".db3", version
    return path


def _timestamps_ok(seq, n: int) -> None:
    for i, name in enumerate(seq.names[:n]):
        assert seq.timestamps[name] == pytest.approx((T0_MS + i * PERIOD_MS) * 1e-3, abs=1e-6), name


@pytest.mark.parametrize("sdk", SDKS)
def test_sdk_recording_reads_the_frames_fed(views, folder, sdk, tmp_path):
    path, version = record(views, tmp_path / "rec", sdk)
    ref = open_sequence(folder)
    with open_sequence(path) as seq:
        assert seq.kind == ("RealSense rosbag2" if path.suffix == ".db3" else "RealSense bag"), version
        assert seq.names == ref.names and seq.problems == {} and seq.damage == [] and not seq.aligned
        assert seq.intrinsics == K_COLOR and seq.depth_scale == 0.001
        _timestamps_ok(seq, 12)
        for name in seq.names:
            a, b = ref[name], seq[name]
            assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth), (version, name)


@pytest.mark.parametrize("sdk", SDKS)
def test_sdk_unaligned_recording_gives_its_depth_camera(views, sdk, tmp_path):
    """The depth camera's intrinsics and T_color_depth as registered with the SDK (the .db3 keeps the extrinsics as
    text with 6 decimals: within 1e-6); with the installed SDK, also as its own playback reports them, with the
    same frames, pixel for pixel."""
    path, version = record(views, tmp_path / "unaligned", sdk, unaligned=True, n=4)
    with open_sequence(path) as seq:
        assert seq.aligned and len(seq) == 4, version
        assert seq.setup.depth_camera.intrinsics == K_DEPTH
        np.testing.assert_allclose(seq.setup.depth_camera.T_color_depth, T_depth_offset(), atol=1e-6)
        _timestamps_ok(seq, 4)
        fed = views.frames(unaligned=True)
        for i, name in enumerate(seq.names):
            c, d = seq.raw(name)
            assert np.array_equal(c, fed[i].color) and np.array_equal(d, fed[i].depth * np.float32(0.001)), name
        if sdk is None:
            frames, info = playback(path)
            assert info["scale"] == pytest.approx(seq.depth_scale, rel=1e-6)
            assert same_rs_intrinsics(info["color"], seq.intrinsics)
            assert same_rs_intrinsics(info["depth"], seq.setup.depth_camera.intrinsics)
            np.testing.assert_allclose(info["T_color_depth"], seq.setup.depth_camera.T_color_depth, atol=1e-6)
            # the playback's syncer may hand a frame out in more than one frameset, and on a busy machine drop the
            # first: every frame it returns (by frame number) is the one gscan reads
            color = {cn: c for (c, _), (cn, _) in zip(frames, info["numbers"], strict=True)}
            depth = {dn: d for (_, d), (_, dn) in zip(frames, info["numbers"], strict=True)}
            assert color and depth and set(color) | set(depth) <= set(range(4)), info["numbers"]
            for i, name in enumerate(seq.names):
                c, d = seq.raw(name)
                assert i not in color or np.array_equal(color[i], c), name
                assert i not in depth or np.array_equal(depth[i].astype(np.float32) * np.float32(0.001), d), name


def test_timestamps_of_two_clocks_pair_by_recording_time(views, tmp_path):
    """Colour timestamps on another clock (system time, 5 s off) than depth's (hardware clock) never pair by
    value: the frames are paired by the times they were recorded at (fed 0.1 s apart), every frame as fed."""
    path, _ = record(views, tmp_path / "clocks", n=4, color_clock_ms=5000.0, pause_s=0.1)
    with open_sequence(path) as seq:
        assert len(seq) == 4 and seq.problems == {}
        assert seq.timestamps["000000"] < 1.0  # the recording time, not the camera's 1 s or 6 s
        for i, name in enumerate(seq.names):
            assert np.array_equal(seq[name].color, views.colors[i]), name
            assert np.array_equal(seq[name].depth, views.frames()[i].depth * np.float32(0.001)), name


@pytest.mark.parametrize("fmt", ["bgr8", "rgba8", "yuyv"])
def test_sdk_colour_formats_read_as_fed(views, fmt, tmp_path):
    """BGR8 and RGBA8 are stored as PNG (lossless: the RGB fed comes back), YUYV as zstd-compressed raw pixels
    (read as OpenCV converts the YUYV fed)."""
    path, _ = record(views, tmp_path / fmt, color_format=fmt, n=2)
    with open_sequence(path) as seq:
        assert len(seq) == 2
        for i, name in enumerate(seq.names):
            rgb = views.colors[i]
            want = cv2.cvtColor(cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_YUYV), cv2.COLOR_YUV2RGB_YUYV) \
                if fmt == "yuyv" else rgb
            assert np.array_equal(seq[name].color, want), name


def test_a_frame_whose_image_does_not_decode_is_reported_and_left_out(views, tmp_path):
    """The second colour frame's PNG spoilt in the SDK's .db3 (its header, and so its size, kept): the recording
    opens, and reading that frame raises naming it, recorded in `problems`; the other frames read as fed."""
    path, _ = record(views, tmp_path / "spoilt", n=3)
    with sqlite3.connect(path) as con:
        (tid,) = con.execute("SELECT id FROM topics WHERE name LIKE '%Color_0/image/data/compressed'").fetchone()
        mid, data = con.execute("SELECT id, data FROM messages WHERE topic_id = ? ORDER BY timestamp LIMIT 1 "
                                "OFFSET 1", (tid,)).fetchone()
        keep = bytes(data).index(b"\x89PNG") + 33  # the PNG signature and its IHDR chunk
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (data[:keep] + b"\0" * (len(data) - keep), mid))
    with open_sequence(path) as seq:
        assert seq.names == ["000000", "000001", "000002"]
        with pytest.raises(InputError, match="frame 000001: compressed image does not decode") as e:
            seq["000001"]
        assert e.value.path == path and "000001" in seq.problems
        assert np.array_equal(seq["000002"].color, views.colors[2])


def test_a_row_missing_from_an_sdk_db3_is_reported_as_damage(views, tmp_path):
    """The SDK's .db3 (no metadata stored; log times as the recorder's thread wrote them) with the 4th depth image's
    row deleted: the gap in its message ids is reported, put on the depth topic by the depth stream's period and no
    other (or said not to be told, where the log times do not show it), and frame 000003 is said to have lost its
    depth to it; the other frames read as fed."""
    path, _ = record(views, tmp_path / "gap", n=8)
    with sqlite3.connect(path) as con:
        (tid,) = con.execute("SELECT id FROM topics WHERE name LIKE '%Depth_0/image/data%'").fetchone()
        (mid,) = con.execute("SELECT id FROM messages WHERE topic_id = ? ORDER BY id LIMIT 1 OFFSET 3",
                             (tid,)).fetchone()
        con.execute("DELETE FROM messages WHERE id = ?", (mid,))
    with open_sequence(path) as seq:
        assert len(seq.damage) == 1, seq.damage
        depth = seq.setup.depth_topic
        assert seq.damage[0].startswith(f"{path}: damaged records: message id {mid} of {path.name}: missing from its "
                                        "messages table"), seq.damage
        # the topic is inferred from the streams' periods in the log times the recorder's thread wrote; on a busy
        # machine they may not tell, and the report must then say so rather than guess
        told = f"by the image streams' periods, 1 on {depth})" in seq.damage[0]
        assert seq.damage[0].count(" on /") == int(told), seq.damage
        assert told or "(on topics the file does not tell)" in seq.damage[0], seq.damage
        assert list(seq.problems) == ["000003"] and "among the recording's damaged records" in seq.problems["000003"]
        assert seq.names == ["000000", "000001", "000002", "000004", "000005", "000006", "000007"]
        for name in seq.names:
            assert np.array_equal(seq[name].color, views.colors[int(name)]), name


def test_an_sdk_db3_without_intrinsics_exits_2_naming_it(views, tmp_path):
    """The SDK's .db3 with the colour stream's CameraInfo and camera_info text removed: `gscan scan` exits 2 with one
    line naming the file and the topics looked for, and writes nothing."""
    path, _ = record(views, tmp_path / "no_intrinsics", n=2)
    with sqlite3.connect(path) as con:
        ids = [i for (i,) in con.execute("SELECT id FROM topics WHERE name LIKE '%/Color_0/%camera_info'")]
        assert len(ids) == 2
        con.executemany("DELETE FROM messages WHERE topic_id = ?", [(i,) for i in ids])
        con.executemany("DELETE FROM topics WHERE id = ?", [(i,) for i in ids])
    out = tmp_path / "out.gscan"
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(path), "-o", str(out)], capture_output=True,
                       text=True, cwd=ROOT, timeout=300, check=False)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith(f"error: {path}: no CameraInfo for /device_0/sensor_1/Color_0/image/data/compressed")
    assert "Color_0/image/camera_info" in lines[0] and not out.exists()


def _gscan(*args: str | Path) -> dict:
    r = subprocess.run([sys.executable, "-m", "gscan.cli", *map(str, args), "--json"], capture_output=True,
                       text=True, cwd=ROOT, timeout=600, check=False)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _poses(folder: Path) -> dict[str, np.ndarray]:
    return {p.stem: np.loadtxt(p) for p in sorted(folder.glob("*.txt"))}


@pytest.mark.slow
def test_scan_track_and_capture_of_a_db3_as_of_its_frames(db3, folder, tmp_path):
    """`gscan scan` of the SDK's .db3 gives the poses a scan of the folder of the same frames gives, bit for bit;
    `track` through it gives the folder's poses; `capture --from` it writes the frames fed."""
    scan_rec = _gscan("scan", db3, "-o", tmp_path / "rec.gscan")
    scan_dir = _gscan("scan", folder, "-o", tmp_path / "dir.gscan")
    assert scan_rec["registered"] == scan_dir["registered"] == 12
    def poses(p: Path) -> dict:
        with TemplateDB.open(p) as t:
            return {k: np.asarray(v) for k, v in t.poses()["frames"].items()}

    a, b = poses(tmp_path / "rec.gscan"), poses(tmp_path / "dir.gscan")
    assert sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)

    track_rec = _gscan("track", tmp_path / "dir.gscan", db3, "-o", tmp_path / "track_rec")
    track_dir = _gscan("track", tmp_path / "dir.gscan", folder, "-o", tmp_path / "track_dir")
    assert track_rec["frames"] == track_dir["frames"] == 12 and track_rec["with_pose"] == track_dir["with_pose"] > 0
    a, b = _poses(tmp_path / "track_rec"), _poses(tmp_path / "track_dir")
    assert sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)

    cap = _gscan("capture", "--from", db3, "-o", tmp_path / "cap", "--every", "1")
    # every recorded frame, but those the SDK's playback skipped on a loaded machine, which are named
    numbers = [f["number"] for f in json.loads((tmp_path / "cap" / "capture.json").read_text())["frames"].values()]
    assert sorted([f"{k:06d}" for k in numbers] + cap["skipped"]) == [f"{k:06d}" for k in range(12)], cap
    got, ref = open_sequence(tmp_path / "cap"), open_sequence(folder)
    assert got.intrinsics == K_COLOR and cap["frames"] == len(numbers)
    for new, number in zip(got.names, numbers, strict=True):
        old = ref.names[number]
        assert np.array_equal(got[new].color, ref[old].color) and np.array_equal(got[new].depth, ref[old].depth)
