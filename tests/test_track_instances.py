"""Tracking every instance (gscan.estimate.track_instances, `gscan track --all`): three copies of a box side by side
on a table under a static camera; all still, then one slides and turns, then another is hidden behind a box held
in front of it and uncovered again."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscan.estimate import Estimator
from gscan.estimate.result import found, not_found
from gscan.estimate.track import InstanceStep, TrackRun, TrackStep, write_poses
from gscan.estimate.track_instances import InstanceTracker
from gscan.geometry.transforms import make_T, pose_error
from gscan.io import open_sequence
from gscan.io.camera import RGBDFrame
from gscan.synth import DEFAULT_INTRINSICS, load_textured_mesh, write_capture
from gscan.synth.piles import render_row_sequence

TARGET = "Frozen_Scrabble_Jr"
OCCLUDER = "Crayola_Bonus_64_Crayons"
N_FRAMES = 12
MOVING, MOVES = 2, range(3, 9)  # copy 2 slides 1 cm and turns 3 deg in each of these frames
HIDDEN, HIDES = 0, (7, 8, 9)  # copy 0 is behind the occluder in these frames


@pytest.fixture(scope="module")
def template(cad_template) -> Path:
    return cad_template(TARGET, 16)


@pytest.fixture(scope="module")
def sequence(meshes_dir: Path) -> tuple[list, np.ndarray, np.ndarray]:
    """The rendered frames, T_cam_obj of every copy per frame and their fractions in sight (`render_sequence`)."""
    box = load_textured_mesh(meshes_dir / TARGET / "model_0.obj")
    occ = load_textured_mesh(meshes_dir / OCCLUDER / "model_0.obj")
    rs = render_row_sequence(box, 3, N_FRAMES, 5, MOVING, MOVES, HIDDEN, HIDES, occ)
    frames, truths, seen = rs.frames, rs.T_cam_objs, rs.seen
    assert (seen[list(HIDES), HIDDEN] < 0.15).all() and (seen[:, [i for i in range(3) if i != HIDDEN]] > 0.6).all()
    return frames, truths, seen


def rgbd(frames: list) -> list[RGBDFrame]:
    return [RGBDFrame(f"{i:06d}", f.color, f.depth, f.intrinsics) for i, f in enumerate(frames)]


def check_identities(steps: list[TrackStep], truths: np.ndarray) -> dict[int, int]:
    """Every pose within 5 deg / 1 cm of one copy, each identity on the same copy in every frame, no two
    identities on one copy, nothing where no copy is; returns identity -> copy."""
    copy_of: dict[int, int] = {}
    for f, s in enumerate(steps):
        assert s.instances is not None
        on: list[int] = []
        for i in s.instances:
            T = i.result.T_cam_obj
            if T is None:
                assert i.status == "lost", (f, i.id, i.status)
                continue
            near = [j for j in range(3) if all(np.array(pose_error(T, truths[f, j])) <= (5.0, 0.01))]
            assert near, (f, i.id, "a pose at no copy", [pose_error(T, truths[f, j]) for j in range(3)])
            assert copy_of.setdefault(i.id, near[0]) == near[0], (f, i.id, "identity swapped", copy_of, near)
            on.append(near[0])
        assert len(on) == len(set(on)), (f, "two identities on one copy")
    return copy_of


@pytest.mark.slow
def test_every_instance_keeps_its_identity(template, sequence):
    """Three identities from the first frame, held while still and while one moves; the hidden one lost while
    hidden and re-found with its own identity; statuses as the single tracker's."""
    frames, truths, _ = sequence
    tracker = InstanceTracker(Estimator.from_path(template))
    steps = [tracker.step(f) for f in rgbd(frames)]
    copy_of = check_identities(steps, truths)
    assert sorted(copy_of) == [1, 2, 3] and sorted(copy_of.values()) == [0, 1, 2]
    hidden = next(k for k, j in copy_of.items() if j == HIDDEN)
    status = [{i.id: i.status for i in s.instances or []} for s in steps]
    assert status[0] == {1: "found", 2: "found", 3: "found"}
    for f in range(1, N_FRAMES):
        for k in (1, 2, 3):
            if f in HIDES and k == hidden:
                assert status[f][k] == "lost", (f, status[f])
            elif f == HIDES[-1] + 1 and k == hidden:
                assert status[f][k] == "refound", (f, status[f])
            else:
                assert steps[f].instances[k - 1].result.T_cam_obj is not None, (f, k, status[f])  # type: ignore
        assert sum(s == "tracked" for s in status[f].values()) >= 1, (f, status[f])
    # the still copies are held by their priors, not searched for again
    still = [k for k, j in copy_of.items() if j not in (HIDDEN, MOVING)]
    assert sum(status[f][still[0]] == "tracked" for f in range(1, N_FRAMES)) >= N_FRAMES - 3
    # a single-instance reader reads the lowest identity with a pose
    for s in steps:
        first = next(i for i in s.instances or [] if i.result.T_cam_obj is not None)
        assert s.result is first.result and s.status == first.status
    check_assignment(tracker, copy_of)


def check_assignment(tracker: InstanceTracker, copy_of: dict[int, int]) -> None:
    """Every identity lost, poses found by a search: each takes the identity whose last pose is nearest (one to one),
    a pose beyond the gate of every waiting identity is a new identity, or with the cap reached goes to the nearest
    waiting one."""
    last = {k: t.last_pose for k, t in tracker._trackers.items()}
    for t in tracker._trackers.values():
        t.record(not_found("hidden"), False)
    a, b = sorted(last)[::2]
    poses = [found(last[k], 0.9, 20, "v", "gmatch") for k in (b, a)]
    got = tracker._assign(poses, [1, 2, 3], {}, 8)
    assert sorted(got) == [a, b] and got[b] is poses[0] and got[a] is poses[1]
    end, mid = (next(k for k, j in copy_of.items() if j == c) for c in (2, 1))
    out = last[end][:3, 3] - last[mid][:3, 3]  # away from the row, beyond the gate
    far = found(make_T(np.eye(3), 0.3 * out / np.linalg.norm(out)) @ last[end], 0.9, 20, "v", "gmatch")
    got = tracker._assign([far], [1, 2, 3], {}, 8)
    assert list(got) == [4] and got[4] is far
    got = tracker._assign([far], [1, 2, 3], {}, 3)  # the cap reached: the nearest waiting identity
    assert list(got) == [end] and got[end] is far
    # two identities refined onto one instance: the one that moved less from its own prediction keeps it
    held = {a: found(last[a], 0.9, 20, "v", "track"), b: found(last[a], 0.9, 20, "v", "track")}
    tracker._one_per_instance(held, {a: last[a], b: last[b]})
    assert list(held) == [a]


@pytest.mark.slow
def test_track_all_cli_writes_every_instance(template, sequence, tmp_path):
    frames, truths, _ = sequence
    seq_dir = tmp_path / "seq"
    n = 4  # the first frames: every copy found, then held
    write_capture(seq_dir, frames[:n], DEFAULT_INTRINSICS, write_masks=False)
    out = tmp_path / "poses"
    cmd = [sys.executable, "-m", "gscan.cli", "track", str(template), str(seq_dir), "-o", str(out), "--all",
           "--max-instances", "3", "--json"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    names = open_sequence(seq_dir).names
    assert [i["id"] for i in summary["instances"]] == [1, 2, 3]
    for f, pf in enumerate(summary["per_frame"]):
        # the single-instance fields are the first instance's
        assert pf["T_cam_obj"] == pf["instances"][0]["T_cam_obj"] and pf["status"] == pf["instances"][0]["status"]
        for inst in pf["instances"]:
            T = np.loadtxt(out / f"instance_{inst['id']}" / f"{names[f]}.txt")
            assert np.allclose(T, np.array(inst["T_cam_obj"]), atol=1e-6)
            assert min(pose_error(T, truths[f, j])[1] for j in range(3)) < 0.01
    assert sorted(p.name for p in out.iterdir()) == sorted([f"{nm}.txt" for nm in names] + ["summary.json"]
                                                           + [f"instance_{k}" for k in (1, 2, 3)])
    single = subprocess.run([sys.executable, "-m", "gscan.cli", "track", str(template), str(seq_dir),
                             "--max-instances", "2"], capture_output=True, text=True, timeout=600, check=False)
    assert single.returncode == 2 and "--all" in single.stderr and len(single.stderr.strip().splitlines()) == 1


def test_single_instance_output_is_unchanged(tmp_path):
    """A single-instance track's JSON and files carry no instance fields."""
    res = found(np.eye(4), 0.9, 20, "v", "gmatch")
    run = TrackRun([TrackStep("a", "found", res)])
    js = run.to_json()
    assert "instances" not in js and "instances" not in js["per_frame"][0] and "frame_ms" not in js["per_frame"][0]
    write_poses(run, tmp_path / "one")
    assert sorted(p.name for p in (tmp_path / "one").iterdir()) == ["a.txt", "summary.json"]
    multi = TrackRun([TrackStep("a", "found", res, [InstanceStep(1, "found", res)], 12.0)])
    assert multi.to_json()["instances"] == [{"id": 1, "frames": 1, "first": "a", "last": "a", "lost": [],
                                              "refound": []}]
