"""A pose for every frame (issue 44): frames that frame selection skips (the view barely moved) are placed by
registration to the kept frame each was compared with, listed in `poses --json` with that frame, not fused and
never keyframes."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gscan import synth
from gscan.geometry.transforms import inv_T, mean_pose, rotation_angle_deg
from gscan.template.db import TemplateDB

# (elevation, azimuth) deg: three views a fraction of a degree from the one before them
ANGLES = [(35.0, 0.0), (35.0, 0.2), (35.0, 20.0), (35.0, 40.0), (35.0, 40.3), (35.0, 60.0), (35.0, 80.0),
          (35.0, 80.1)]
NEAR = {"000001": "000000", "000004": "000003", "000007": "000006"}


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    root = tmp_path_factory.mktemp("near")
    box = synth.box_mesh((0.07, 0.05, 0.11), synth.procedural_box_texture(11, (512, 768)), name="box")
    synth.render_capture(box, root / "cap", len(ANGLES), view_angles_deg=ANGLES, seed=2)
    out = root / "near.gscan"
    proc = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(root / "cap"), "-o", str(out), "--json"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    poses = subprocess.run([sys.executable, "-m", "gscan.cli", "poses", str(out), "--json"], capture_output=True,
                           text=True, timeout=300)
    return root / "cap", out, json.loads(proc.stdout), json.loads(poses.stdout)


def test_frames_skipped_by_selection_get_a_pose_from_their_reference(scanned):
    cap, out, res, poses = scanned
    assert res["selection"]["skipped"] == len(NEAR), res["selection"]
    assert set(poses["skipped_by_selection"]) == set(NEAR)
    assert poses["from_reference"] == NEAR
    assert sorted(poses["frames"]) == [f"{i:06d}" for i in range(len(ANGLES))]  # every input frame has a pose
    gt = {f.stem: inv_T(np.loadtxt(f)) for f in (cap / "annotated_poses").glob("*.txt")}
    T = {n: np.asarray(v) for n, v in poses["frames"].items()}
    A = mean_pose([T[n] @ inv_T(gt[n]) for n in T if n not in NEAR])  # from the kept frames alone
    for n in NEAR:
        D = inv_T(A @ gt[n]) @ T[n]
        assert rotation_angle_deg(D[:3, :3]) < 1.0 and np.linalg.norm(D[:3, 3]) < 0.005, (n, D)
    with TemplateDB.open(out) as db:  # placed, not fused: no view of them, so never a keyframe
        assert not set(NEAR) & set(db.view_names())
