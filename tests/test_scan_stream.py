"""How a scan writes its database and holds its frames: each stage's writes in one transaction (a chunk of a long
stage at most), each view's images written once, the finished file a rollback-journal database."""
from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from gscan import synth
from gscan.scanning.api import scan
from gscan.template.db import TemplateDB
from tests._scan_checks import box_ring_capture

INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240
N_VIEWS = 6  # 60 degree steps on one ring


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return box_ring_capture(tmp_path_factory.mktemp("stream") / "capture", N_VIEWS, INTR)


def test_scan_commits_per_stage_and_writes_each_view_once(capture: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Every SQL statement the scan's connection runs is traced: each view row is inserted once (its images
    encoded once; the last stage sets its pose, mask and keyframe flag), and the scan commits once per stage (not
    once per view and edge: each commit of a rollback journal costs an fsync); the file it leaves is a
    rollback-journal database with nothing beside it."""
    statements: list[str] = []
    connect = TemplateDB._connect

    def traced(path: Path, writable: bool = True, wal: bool = False) -> sqlite3.Connection:
        conn = connect(path, writable, wal)
        conn.set_trace_callback(statements.append)
        return conn

    monkeypatch.setattr(TemplateDB, "_connect", staticmethod(traced))
    out = tmp_path / "obj.gscan"
    res = scan(capture, out)
    assert res.registered == N_VIEWS
    inserts = [s for s in statements if s.startswith("INSERT INTO views")]
    commits = [s for s in statements if s.startswith("COMMIT")]
    assert len(inserts) == N_VIEWS, len(inserts)
    # the schema, then the stages that write (features, noise, sequential edges, loop closures, the last stage)
    assert len(commits) <= 6, (len(commits), len(statements))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obj.gscan"]
    assert out.read_bytes()[18:20] == b"\x01\x01"  # rollback journal, not WAL


# ------------------------------------------------------------------------------------------ frame selection
def _ring_frames(azimuths: list[float], elevation: float = 40.0, seed: int = 0) -> list:
    """Frames of the box capture's scene seen from a ring of cameras at the azimuths (deg), each with its own
    sensor noise (two frames at one azimuth are a camera standing still)."""
    from gscan.io.camera import RGBDFrame
    from gscan.synth.capture import default_distance, orbit_poses, rest_on_table
    from gscan.synth.render import SynthScene

    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    T_world_obj = rest_on_table(mesh)
    scene = SynthScene([(mesh, T_world_obj)], seed=seed)
    centre = (T_world_obj[:3, :3] @ mesh.center + T_world_obj[:3, 3])
    out = []
    for i, az in enumerate(azimuths):
        T_wc = orbit_poses(centre, default_distance(mesh, INTR), [elevation], 1, azimuth0_deg=az)[0]
        r = scene.render(T_wc, INTR, rng=np.random.default_rng([seed, i]))
        out.append(RGBDFrame(f"{i:06d}", r.color, r.depth, INTR, mask=r.mask))
    return out


def test_selection_skips_still_and_blurred_frames_and_keeps_a_blurred_one_before_a_gap() -> None:
    """A camera on a ring: frames taken standing still or a fraction of a degree on are skipped for little motion;
    a blurred frame that moved enough is passed over for the sharp one after it; a blurred frame that moved more
    than twice the step is kept (a blurred view beats a gap); a capture moving a degree a frame keeps every one."""
    import cv2

    from gscan.scanning.select import BLURRED, LITTLE_MOTION, FrameSelector, SelectionParams

    azimuths = [0.0, 0.0, 0.2, 0.8, 0.95, 1.05, 3.0, 3.0, 4.0, 5.0, 6.0]
    frames = _ring_frames(azimuths)
    for k in (3, 6):  # motion blur: a horizontal smear of 9 px
        frames[k].color = cv2.blur(frames[k].color, (9, 1))
    sel = FrameSelector(SelectionParams(min_motion_deg=0.5, blur_ratio=0.5))
    got = []
    for f in frames:
        why = sel.consider(f)
        if why is None:
            sel.keep(f)
        got.append("kept" if why is None else why[0])
    assert got == ["kept", LITTLE_MOTION, LITTLE_MOTION, BLURRED, "kept", LITTLE_MOTION, "kept", LITTLE_MOTION,
                   "kept", "kept", "kept"], got
    plain = FrameSelector(SelectionParams(min_motion_deg=0.0))
    assert all(plain.consider(f) is None for f in frames)  # 0: every frame kept


def test_selection_follows_a_turning_object_not_the_still_background() -> None:
    """A static camera and an object turning in front of it (a turntable): the motion measured is the object's,
    on its mask, so frames turning two degrees each are all kept though most of the image stands still, and frames
    where the object stops are skipped."""
    from gscan.io.camera import RGBDFrame
    from gscan.scanning.select import LITTLE_MOTION, FrameSelector, SelectionParams
    from gscan.synth.capture import default_distance, orbit_poses, rest_on_table, turntable_poses
    from gscan.synth.render import SynthScene

    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(5, (512, 768)))
    T_world_obj = rest_on_table(mesh)
    scene = SynthScene([(mesh, T_world_obj)], seed=1)
    centre = T_world_obj[:3, :3] @ mesh.center + T_world_obj[:3, 3]
    T_wc = orbit_poses(centre, default_distance(mesh, INTR), [30.0], 1, azimuth0_deg=-90.0)[0]
    spins = turntable_poses(T_world_obj, mesh, 360)  # 1 degree apart (the cue measures a small object turning low)
    turns = [0, 0, 0, 2, 4, 6, 6, 6, 8]
    sel = FrameSelector(SelectionParams(), mask_needed=True)
    got = []
    for i, t in enumerate(turns):
        r = scene.render(T_wc, INTR, rng=np.random.default_rng([1, i]), T_world_obj_override=spins[t])
        f = RGBDFrame(f"{i:06d}", r.color, r.depth, INTR)
        why = sel.consider(f)
        if why is None:
            sel.keep(f, r.mask)
        got.append("kept" if why is None else why[0])
    assert got == ["kept", LITTLE_MOTION, LITTLE_MOTION, "kept", "kept", "kept", LITTLE_MOTION, LITTLE_MOTION,
                   "kept"], got


# the camera orbits 15 degrees a frame and stands still twice (frames repeated with fresh sensor noise)
STOP_AZIMUTHS = [0, 15, 30, 45, 45, 45, 45, 60, 75, 90, 105, 120, 135, 150, 165, 180, 180, 180, 195, 210, 225, 240,
                 255, 270, 285, 300, 315, 330, 345]
STILL = {4, 5, 6, 16, 17}  # the frames taken standing still


@pytest.fixture(scope="module")
def stops(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A scan of the capture with stops, every RGBDFrame the scan makes counted while alive: the result, the
    template, the capture and the most frames alive at once."""
    import threading
    import weakref

    from gscan.io.camera import RGBDFrame

    root = tmp_path_factory.mktemp("stops")
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, root / "capture", len(STOP_AZIMUTHS), mode="static", intr=INTR,
                         view_angles_deg=[(40.0, float(a)) for a in STOP_AZIMUTHS])
    alive, peak, lock = [0], [0], threading.Lock()
    post_init = RGBDFrame.__post_init__

    def gone() -> None:
        with lock:
            alive[0] -= 1

    def counted(self: RGBDFrame) -> None:
        post_init(self)
        with lock:
            alive[0] += 1
            peak[0] = max(peak[0], alive[0])
        weakref.finalize(self, gone)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(RGBDFrame, "__post_init__", counted)
        res = scan(root / "capture", root / "stops.gscan")
    return {"result": res, "template": root / "stops.gscan", "capture": root / "capture", "peak": peak[0]}


def test_still_frames_are_skipped_and_reported_not_failed(stops: dict, capsys: pytest.CaptureFixture) -> None:
    """The frames taken standing still are skipped by frame selection and reported as such (scan summary and
    --json, poses --json, info), not as unregistered; every frame the camera moved to is kept, registered and at
    the right pose (ATE within 5 mm, none wrong)."""
    import json
    import subprocess
    import sys

    from gscan.cli.scan import print_scan_summary
    from gscan.evaluate.metrics import ate_rmse, frame_errors
    from gscan.geometry.transforms import inv_T
    from gscan.io import open_sequence

    res = stops["result"]
    names = [f"{i:06d}" for i in range(len(STOP_AZIMUTHS))]
    still = {names[i] for i in STILL}
    out = res.to_json()
    assert out["frames"] == len(names) and out["registered"] == len(names) - len(STILL), out
    assert out["unregistered"] == [] and out["unregistered_reasons"] == {}
    assert out["selection"] == {"kept": len(names) - len(STILL), "skipped": len(STILL),
                                "reasons": {"moved less than 0.5 deg since the last kept frame": len(STILL)}}
    print_scan_summary(res)
    assert f"frame selection: {len(names) - len(STILL)} frames kept, {len(STILL)} skipped" in capsys.readouterr().err

    def cli(*args: str) -> subprocess.CompletedProcess:
        r = subprocess.run([sys.executable, "-m", "gscan.cli", *args], capture_output=True, text=True, timeout=300,
                           check=False)
        assert r.returncode == 0, r.stderr
        return r

    poses = json.loads(cli("poses", str(stops["template"]), "--json").stdout)
    # every frame has a pose: the still ones placed by registration to the frame they stood still at
    assert set(poses["frames"]) == set(names) and poses["unregistered"] == []
    assert set(poses["skipped_by_selection"]) == still and set(poses["from_reference"]) == still
    assert set(poses["from_reference"].values()) <= {"000003", "000015"}, poses["from_reference"]
    for why in poses["skipped_by_selection"].values():  # the frame it stood still at: the one before the stop
        assert why.startswith("moved 0.0") and ("since frame 000003" in why or "since frame 000015" in why), why
    info = json.loads(cli("info", str(stops["template"]), "--json").stdout)
    assert info["selection"] == out["selection"] and info["views"] == len(names) - len(STILL)
    assert "frame selection: 24 frames kept, 5 skipped" in cli("info", str(stops["template"])).stderr
    gt = {n: inv_T(T) for n, T in open_sequence(stops["capture"]).gt_T_cam_obj.items()}
    est = {n: np.asarray(T) for n, T in poses["frames"].items()}
    assert not frame_errors(est, {n: gt[n] for n in est}).wrong(5.0, 0.02)
    assert ate_rmse([est[n] for n in est], [gt[n] for n in est]) <= 0.005


def test_frames_held_in_memory_stay_few(stops: dict) -> None:
    """While the capture streams through the scan, at most a few frames' images are in memory at once (the
    read-ahead, the frames the workers process): a bound that does not grow with the capture's length."""
    assert stops["peak"] <= 8, stops["peak"]
    assert stops["peak"] < len(STOP_AZIMUTHS) - len(STILL)  # what holding every kept frame would take
