"""Real Kinect v1 frames with ground truth (7-Scenes "redkitchen", shared test data real/7scenes_redkitchen):
the default scan through the real CLI, every frame registered or explained, the count of frames at wrong poses,
the ATE against a plain SIFT + RANSAC + ICP chain run on the same frames here, and pose estimation on the 30
query frames the scan never saw, with no wrong pose returned.

7-Scenes records colour and depth with two cameras. Its README states one approximate focal length for both (585);
the calibration published for the data (the depth camera f = 585, the colour camera f = 525, both centred at
(320, 240), and the depth-to-colour extrinsics below) is the one 7-Scenes relocalisation work uses (Brachmann
et al., "On the Limits of Pseudo Ground Truth in Visual Camera Re-localisation", ICCV 2021). The scan gets it
through --intrinsics, --depth-intrinsics and --depth-to-color. The ground truth (KinectFusion) tracks the depth
camera; it is moved to the colour camera by the same extrinsics. Good to about 1 cm / 1 deg by the README, and
less where the camera moves fast (the paper above).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscan.evaluate.metrics import ate, frame_errors
from gscan.geometry.transforms import inv_T, pose_error
from gscan.io.poses import read_open3d_log

pytestmark = pytest.mark.slow

T_COLOR_DEPTH = np.array([[0.99996518, 0.00267651, -0.00790410, -0.02555894],
                          [-0.00274093, 0.99996303, -0.00815045, 0.00010110],
                          [0.00788199, 0.00817183, 0.99993555, 0.00203183],
                          [0.0, 0.0, 0.0, 1.0]])
WRONG_DEG, WRONG_M = 10.0, 0.10  # a frame beyond either is at a wrong pose (the README's 1 cm / 1 deg, ten-fold)
FOUND_DEG, FOUND_M = 5.0, 0.05   # a query pose within both is found


@pytest.fixture(scope="module")
def kitchen(real_dir: Path, tmp_path_factory) -> dict:
    """The scan of scan/ by `gscan scan` with the published calibration: its JSON summary, the template, the
    calibration files and the ground truth in the colour camera (frame name -> T_world_cam)."""
    root = real_dir / "7scenes_redkitchen"
    work = tmp_path_factory.mktemp("kitchen")
    np.savetxt(work / "color_K.txt", [[525.0, 0, 320.0], [0, 525.0, 240.0], [0, 0, 1]])
    np.savetxt(work / "depth_K.txt", [[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
    np.savetxt(work / "T_color_depth.txt", T_COLOR_DEPTH)
    out = work / "kitchen.gscan"
    run = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(root / "scan"), "-o", str(out), "--json",
                          "--intrinsics", str(work / "color_K.txt"), "--depth-intrinsics", str(work / "depth_K.txt"),
                          "--depth-to-color", str(work / "T_color_depth.txt")],
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    T_depth_color = inv_T(T_COLOR_DEPTH)
    gt = {f"{k:06d}": T @ T_depth_color for k, T in read_open3d_log(root / "scan" / "trajectory.log")}
    return {"summary": json.loads(run.stdout), "template": out, "work": work, "root": root, "gt": gt}


def test_real_kinect_scan_registers_every_frame_and_beats_the_odometry_chain(kitchen):
    """60 of 60 frames registered (every frame registered or explained); at most one frame beyond 10 deg / 10 cm
    of the ground truth (frame 000010, 12 cm: the first 14 frames move fastest, 3.6-7.8 cm between frames, where
    the ground truth itself is weakest); ATE below the SIFT + RANSAC + ICP chain's on the same frames (3.1 cm
    against 7.0 cm when measured)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from peers import sift_ransac_icp_chain

    from gscan.io import open_sequence
    from gscan.template.db import TemplateDB

    s = kitchen["summary"]
    assert s["registered"] == 60 and s["frames"] == 60 and s["keyframes"] >= 8, s
    with TemplateDB.open(kitchen["template"]) as db:
        ours = {v.name: v.T_obj_cam for v in db.views() if v.T_obj_cam is not None}
    gt = kitchen["gt"]
    wrong = frame_errors(ours, gt).wrong(WRONG_DEG, WRONG_M)
    assert len(wrong) <= 1, wrong
    names = sorted(ours)
    ate_ours = ate([ours[n] for n in names], [gt[n] for n in names]).rmse

    w = kitchen["work"]
    seq = open_sequence(kitchen["root"] / "scan", intrinsics=w / "color_K.txt", depth_intrinsics=w / "depth_K.txt",
                        T_color_depth=w / "T_color_depth.txt")
    peer = sift_ransac_icp_chain([seq[n] for n in seq.names])
    theirs = {n: T for n, T in peer.T_world_cam.items() if T is not None}
    ate_peer = ate([theirs[n] for n in sorted(theirs)], [gt[n] for n in sorted(theirs)]).rmse
    assert ate_ours < 0.05 and ate_ours < ate_peer, (ate_ours, ate_peer)


def test_real_kinect_queries_are_found_and_never_wrong(kitchen):
    """Pose estimation against the real template on 30 query frames the scan never saw: at least 8 found within
    5 deg / 5 cm of the truth (8 when measured), and no pose returned beyond 10 deg / 10 cm. The truth of a query
    relative to the template follows from the ground truth and the template's poses (aligned by ATE)."""
    from gscan.estimate.estimator import Estimator
    from gscan.io import open_sequence
    from gscan.template.db import TemplateDB

    gt, w = kitchen["gt"], kitchen["work"]
    with TemplateDB.open(kitchen["template"]) as db:
        ours = {v.name: v.T_obj_cam for v in db.views() if v.T_obj_cam is not None}
    names = sorted(ours)
    T_world_obj = ate([ours[n] for n in names], [gt[n] for n in names]).T_gt_est
    qroot = kitchen["root"] / "queries"
    q = open_sequence(qroot, intrinsics=w / "color_K.txt", depth_intrinsics=w / "depth_K.txt",
                      T_color_depth=w / "T_color_depth.txt")
    gq = {k: np.asarray(v) @ inv_T(T_COLOR_DEPTH)
          for k, v in json.loads((qroot / "gt_T_world_cam.json").read_text()).items()}
    est = Estimator.from_path(kitchen["template"])
    found, wrong = [], []
    for n in q.names:
        r = est.estimate(q[n])
        if r.T_cam_obj is None:
            continue
        deg, m = pose_error(r.T_cam_obj, inv_T(gq[n]) @ T_world_obj)
        if deg < FOUND_DEG and m < FOUND_M:
            found.append(n)
        if deg > WRONG_DEG or m > WRONG_M:
            wrong.append((n, round(deg, 1), round(m, 3)))
    assert not wrong, wrong
    assert len(found) >= 8, found
