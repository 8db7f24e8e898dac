"""Tracking through a rendered RGB-D sequence (gscan.estimate.track, `gscan track`): the object slides and turns on
a cluttered table, leaves the view for three frames and comes back."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscan.errors import InputError
from gscan.estimate import Estimator, Tracker, track_sequence, write_poses
from gscan.geometry.transforms import look_at, make_T, pose_error, rotvec_to_R, transform_points
from gscan.io import open_sequence
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    load_textured_mesh,
    place_distractors,
    rest_on_table,
    write_capture,
)

TARGET = "Frozen_Scrabble_Jr"
DISTRACTORS = ("Crayola_Bonus_64_Crayons", "Little_Debbie_Cloud_Cakes_10_ct")
N_FRAMES = 16
AWAY = (8, 9, 10)  # frames in which the object is out of the view


@pytest.fixture(scope="module")
def template(cad_template) -> Path:
    return cad_template(TARGET, 16)


@pytest.fixture(scope="module")
def sequence(meshes_dir: Path, tmp_path_factory) -> Path:
    """A static camera over a wood table; the target slides 1 cm and turns 4 deg per frame, is carried out of the
    view for frames AWAY and put back where it would have been. Capture layout with ground truth."""
    target = load_textured_mesh(meshes_dir / TARGET / "model_0.obj")
    distractors = [load_textured_mesh(meshes_dir / n / "model_0.obj") for n in DISTRACTORS]
    rng = np.random.default_rng(4)
    T0 = rest_on_table(target, rotvec_to_R([0.0, 0.0, 0.4]))
    d_poses = [make_T(np.eye(3), [0.0, 0.0, 0.0]) @ T
               for T in place_distractors(target, T0, distractors, rng, gap=0.12)]
    scene = SynthScene([(target, T0)] + list(zip(distractors, d_poses, strict=True)), seed=4, table_kind="wood")
    c = transform_points(T0, target.center[None])[0]
    el, az = np.radians(40.0), np.radians(-70.0)
    eye = c + 0.75 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T_wc = look_at(eye, c)
    frames = []
    for i in range(N_FRAMES):
        R = rotvec_to_R([0.0, 0.0, np.radians(4.0 * i)])
        shift = np.array([0.01 * i, -0.004 * i, 0.0]) + (np.array([3.0, 0.0, 0.0]) if i in AWAY else 0.0)
        T = make_T(R, c - R @ c + shift) @ T0
        frames.append(scene.render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng([4, i]),
                                   T_world_obj_override=T))
    out = tmp_path_factory.mktemp("track") / "sequence"
    write_capture(out, frames, DEFAULT_INTRINSICS, write_masks=False)
    for i in AWAY:
        assert not frames[i].mask.any()
    return out


def _check_run(statuses: dict[str, str], poses: dict[str, np.ndarray | None], gt: dict[str, np.ndarray]) -> None:
    names = sorted(gt)
    for i, name in enumerate(names):
        if i in AWAY:
            assert statuses[name] == "lost" and poses[name] is None, (name, statuses[name])
            continue
        assert poses[name] is not None, (name, statuses[name])
        deg, m = pose_error(poses[name], gt[name])
        assert deg < 5.0 and m < 0.01, (name, statuses[name], deg, m)
    assert statuses[names[0]] == "found"
    assert statuses[names[AWAY[-1] + 1]] == "refound"
    tracked = [n for n in names if statuses[n] == "tracked"]
    assert len(tracked) >= N_FRAMES - len(AWAY) - 4, statuses  # the prior held in most visible frames


def test_tracker_follows_loses_and_refinds(template, sequence):
    est = Estimator.from_path(template)
    seq = open_sequence(sequence)
    run = track_sequence(est, seq)
    assert [s.frame for s in run.steps] == seq.names
    _check_run({s.frame: s.status for s in run.steps}, {s.frame: s.result.T_cam_obj for s in run.steps},
               seq.gt_T_cam_obj)
    for s in run.steps:  # a tracked frame is refined from the prior, never re-estimated from the whole frame
        assert (s.result.method == "track") == (s.status == "tracked")
    out = run.to_json()
    assert out["lost"] == [seq.names[i] for i in AWAY] and out["refound"] == [seq.names[AWAY[-1] + 1]]
    assert out["frames"] == N_FRAMES and out["with_pose"] == N_FRAMES - len(AWAY)


def test_tracker_refuses_a_prior_that_no_longer_holds(template, sequence):
    """A prior 10 cm off the object: the local refinement must not report it; a full estimate finds the object."""
    est = Estimator.from_path(template)
    seq = open_sequence(sequence)
    tracker = Tracker(est)
    first = tracker.step(seq[0])
    assert first.status == "found"
    tracker._T = make_T(np.eye(3), [0.1, 0.0, 0.0]) @ first.result.T_cam_obj  # a stale, wrong prior
    tracker._T_before = None
    step = tracker.step(seq[1])
    assert step.status == "found" and step.result.method == "gmatch"
    deg, m = pose_error(step.result.T_cam_obj, seq.gt_T_cam_obj[seq.names[1]])
    assert deg < 5.0 and m < 0.01


def test_track_cli_writes_ob_in_cam_files(template, sequence, tmp_path):
    out = tmp_path / "poses"
    cmd = [sys.executable, "-m", "gscan.cli", "track", str(template), str(sequence), "-o", str(out), "--json"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    seq = open_sequence(sequence)
    statuses = {f["frame"]: f["status"] for f in summary["per_frame"]}
    poses = {n: (np.loadtxt(out / f"{n}.txt") if (out / f"{n}.txt").exists() else None) for n in seq.names}
    _check_run(statuses, poses, seq.gt_T_cam_obj)
    assert summary["output"] == str(out) and json.loads((out / "summary.json").read_text())["frames"] == N_FRAMES
    assert sorted(p.name for p in out.iterdir()) == sorted([f"{n}.txt" for n, T in poses.items() if T is not None]
                                                           + ["summary.json"])
    # an existing output is refused without --force (exit 2, one line naming it), kept as it was
    before = sorted(p.name for p in out.iterdir())
    r2 = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert r2.returncode == 2 and str(out) in r2.stderr and len(r2.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in out.iterdir()) == before


def test_write_poses_refuses_occupied_output(tmp_path):
    from gscan.estimate import TrackRun

    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "keep.txt").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        write_poses(TrackRun([]), occupied)
    assert (occupied / "keep.txt").read_text() == "x"
    write_poses(TrackRun([]), occupied, force=True)
    assert sorted(p.name for p in occupied.iterdir()) == ["summary.json"]
