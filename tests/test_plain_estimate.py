"""A plain object found in clutter with the template a scan of it made: the Crayola box made plain (one colour,
held out by bench/plain.py), scanned on a 36-frame turntable on `both` keypoints, estimated at the defaults in
bench/plain.py's cluttered scenes (the box upright at a random yaw beside a printed shared mesh and another plain
box, on four kinds of table, 20-50 deg elevation) and in scenes of the two others alone."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tests._scan_checks import plain_turntable_scan

ROOT = Path(__file__).resolve().parents[1]
NAME = "Crayola_Bonus_64_Crayons"
SCENES, NEGATIVES = 8, 3


@pytest.mark.slow
def test_a_plain_box_is_found_in_clutter_and_never_wrong(tmp_path, meshes_dir):
    """At least 6 of its 8 scenes found within 2 cm ADD-S (bench/plain.py --estimate: 7 of 8), no pose wrong, no
    pose in a scene without it; each miss says why. About 60 s."""
    sys.path.insert(0, str(ROOT / "bench"))
    from plain import HELD_OUT, TUNE, estimate_scenes, plain
    from recall import DISTRACTOR_POOL
    from recall import MESHES as RECALL_MESHES

    from gscan.estimate import Estimator
    from gscan.evaluate.bop19 import template_to_gt
    from gscan.evaluate.metrics import adds
    from gscan.geometry.transforms import inv_T
    from gscan.synth.mesh import load_textured_mesh

    _, _, gt, _ = plain_turntable_scan(NAME, tmp_path, meshes_dir)
    to_gt = template_to_gt(tmp_path / "box.gscan", {n: inv_T(T) for n, T in gt.items()})
    est = Estimator.from_path(tmp_path / "box.gscan")
    printed = {d: load_textured_mesh(RECALL_MESHES / d / "model_0.obj") for d in DISTRACTOR_POOL
               if d not in TUNE + HELD_OUT}
    verts = plain(NAME).vertices
    found, misses, wrong = 0, [], []
    for label, frame, T_gt in estimate_scenes(NAME, (TUNE + HELD_OUT).index(NAME), SCENES, printed, NEGATIVES):
        res = est.estimate(frame)
        if not res.found:
            assert res.reason, label
            misses.append((label, str(res.reason)[:80]))
        elif T_gt is None or adds(verts, res.T_cam_obj @ to_gt, T_gt) > 0.02:
            wrong.append(label)
        else:
            found += 1
    assert not wrong, wrong
    assert found >= 6, misses
