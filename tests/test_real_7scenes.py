"""Real Kinect v1 frames with ground truth (7-Scenes "redkitchen", shared test data real/7scenes_redkitchen):
the scan through the real CLI, every frame registered or explained, the count of frames at wrong poses, the ATE
against a plain SIFT + RANSAC + ICP chain run on the same frames here, and pose estimation on the 30 query frames
the scan never saw, with no wrong pose returned.

7-Scenes records colour and depth with two cameras; the scan gets the calibration published for the data through
--intrinsics, --depth-intrinsics and --depth-to-color (bench/real.py: the values and their source, and the rows
these tests assert). The capture sweeps a kitchen corner rather than keeping one object in view, so the template is
the scene's (--no-segment), and the default segmented template (the table the views look at) is checked too. The
ground truth (KinectFusion) is good to about 1 cm / 1 deg by the data's README, and less where the camera moves
fast.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from real import (
    NO_CALIBRATION,
    ground_truth,
    published_calibration,
    scan_with_cli,
    score_queries,
    score_trajectory,
    subsampled,
    template_poses,
    texture_check,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def kitchen(real_dir: Path, tmp_path_factory) -> dict:
    """`gscan scan --no-segment` of scan/ with the published calibration: its JSON summary, the template, the
    calibration and the ground truth in the colour camera."""
    root = real_dir / "7scenes_redkitchen"
    work = tmp_path_factory.mktemp("kitchen")
    calib = published_calibration(work)
    out = work / "kitchen.gscan"
    summary = scan_with_cli(root, out, calib, "--no-segment")
    return {"summary": summary, "template": out, "calib": calib, "root": root, "gt": ground_truth(root, calib)}


def test_real_kinect_scan_registers_every_frame_and_beats_the_odometry_chain(kitchen):
    """60 of 60 frames registered, at least 8 keyframes; at most one frame whose median relative-pose error against
    the other registered frames is beyond 5 deg / 10 cm (frame 000010 at 10.5 cm when measured: the first 14
    frames move fastest, 3.6-7.8 cm between frames, where the ground truth itself is weakest: the depth of that
    frame's pairs agrees with the scan's poses as well as with the ground truth's, and the images' texture lines
    up better under the scan's relative poses than under the ground truth's, there and in 110 of 117 neighbour
    pairs, which this test checks); ATE below 5 cm and below the SIFT + RANSAC + ICP chain's on the same frames
    (3.1 cm against 7.0 cm when measured)."""
    from peers import sift_ransac_icp_chain

    from gscan.io import open_sequence

    s = kitchen["summary"]
    assert s["registered"] == 60 and s["frames"] == 60 and s["keyframes"] >= 8, s
    ours = score_trajectory(template_poses(kitchen["template"]), kitchen["gt"])
    assert ours.registered == 60 and len(ours.wrong) <= 1, ours
    seq = open_sequence(kitchen["root"] / "scan", **kitchen["calib"].sequence_kwargs())
    tex = texture_check(template_poses(kitchen["template"]), kitchen["gt"], seq)
    assert tex.median_scan > tex.median_gt and tex.scan_better > 0.8 * tex.pairs, tex
    peer = sift_ransac_icp_chain([seq[n] for n in seq.names])
    theirs = score_trajectory({n: T for n, T in peer.T_world_cam.items() if T is not None}, kitchen["gt"])
    assert ours.ate_m < 0.05 and ours.ate_m < theirs.ate_m, (ours, theirs)


def test_real_kinect_queries_are_found_and_never_wrong(kitchen):
    """Pose estimation against the real template on 30 query frames the scan never saw: at least 20 found within
    5 deg / 5 cm of the truth (27 when measured), and no pose returned beyond 10 deg / 10 cm."""
    q = score_queries(kitchen["template"], kitchen["root"], kitchen["calib"], kitchen["gt"])
    assert not q.wrong, q.wrong
    assert len(q.found) >= 20, q


def test_real_kinect_scan_with_the_readme_intrinsics_finds_the_colour_camera(real_dir: Path, tmp_path_factory):
    """The scan as a new user runs it: the README's one focal length (585 px) for both cameras, no calibration
    options. The texture of neighbouring frames says the colour camera's focal length is not 585 px (published:
    525); the scan finds it (500-550 px) and registers at least 58 of the 60 frames (59-60 when measured), none
    wrong, each frame left out with its reason (before the check: 13 wrong, ATE 7.0 cm). Query frames read with
    the same README intrinsics are read as the scan read the capture: at least 20 found, none wrong (before: 8
    returned 10-19 cm off)."""
    root = real_dir / "7scenes_redkitchen"
    out = tmp_path_factory.mktemp("kitchen_readme") / "kitchen.gscan"
    summary = scan_with_cli(root, out, NO_CALIBRATION, "--no-segment")
    cam = summary["camera"]
    assert cam["corrected"] and cam["verdict"] == "corrected", cam
    gt = ground_truth(root, NO_CALIBRATION)
    ours = found_or_flagged(summary, out, root, gt)
    assert ours.registered >= 58 and not ours.wrong, ours
    assert set(summary["unregistered_reasons"]) == set(summary["unregistered"]), summary
    q = score_queries(out, root, NO_CALIBRATION, gt)
    assert not q.wrong, q.wrong
    assert len(q.found) >= 20, q


PUBLISHED_COLOUR_FOCAL_PX = 525.0  # bench/real.py's calibration


def found_or_flagged(summary: dict, template: Path, root: Path, gt: dict):
    """The scan's colour camera check on 7-Scenes with the README's 585 px for both cameras: either it confirms a
    focal length, which is then the colour camera's (within 2 % of the published 525 px, inside its interval) and no
    registered frame lies beyond 5 deg / 10 cm but one where the ground truth is the weaker (`gt_weaker_at`, as
    the calibrated scan's test allows), or it says it could not confirm the focal length (a warning) and names
    every frame as resting on it. Either way the depth edges say the depth is not registered to the colour and
    name the flags that fix it. The trajectory's score."""
    cam = summary["camera"]
    edges = cam["depth_edges"]
    assert edges["verdict"] == "not registered" and "--depth-intrinsics" in edges["fix"], edges
    assert "--depth-to-color" in edges["fix"], edges
    T = template_poses(template)
    ours = score_trajectory(T, gt)
    if cam["confirmed"]:
        assert cam["verdict"] in ("kept", "corrected") and cam["warning"] is None, cam
        assert abs(cam["colour_focal_px"][0] / PUBLISHED_COLOUR_FOCAL_PX - 1) <= 0.02, cam
        lo, hi = cam["interval_px"]
        assert lo is not None and hi is not None and lo <= cam["colour_focal_px"][0] <= hi, cam
        assert len(ours.wrong) <= 1 and all(gt_weaker_at(n, T, gt, root, cam) for n in ours.wrong), ours
    else:
        assert cam["verdict"] == "could not confirm" and "could not confirm" in cam["warning"], cam
        assert set(cam["unconfirmed_frames"]) == set(gt), cam
    return ours


def gt_weaker_at(name: str, T_obj_cam: dict, gt: dict, root: Path, cam: dict) -> bool:
    """Every pair of `name` and a frame up to two from it lines up the images' texture better under the scan's
    relative pose than under the ground truth's (`texture_check`, the frames read as the scan read them). Pairs of
    two other frames say nothing of `name`'s pose (their texture ties where scan and ground truth agree)."""
    from gscan.io import open_sequence
    from gscan.io.camera import DepthCamera, Intrinsics

    kw = {}
    if cam["corrected"]:
        kw = {"intrinsics": Intrinsics.from_dict(cam["colour_intrinsics"]),
              "depth_camera": DepthCamera(Intrinsics.from_dict(cam["given_intrinsics"]))}
    seq = open_sequence(root / "scan", **kw)
    names = sorted(T_obj_cam)
    i = names.index(name)
    checks = [texture_check({n: T_obj_cam[n] for n in (name, other)}, gt, seq)
              for other in names[max(0, i - 2):i + 3] if other != name]
    return bool(checks) and all(tex.pairs == 1 and tex.scan_better == 1 for tex in checks)


def test_real_kinect_every_second_frame_with_the_readme_intrinsics(real_dir: Path, tmp_path_factory):
    """Every second frame of scan/ (0.33 s apart), the README's 585 px for both cameras: the check finds the colour
    camera's focal length within 2 % and no frame is wrong, or it warns and flags every frame (`found_or_flagged`;
    before the check's interval it said "checked, kept 585 px"); the frames it registers are at least 25 of 30.
    Measured: corrected to 526.4 px (504.2-553.4), 30 of 30 registered, one frame beyond 10 cm (000005, the
    original 000010 at 1.7 deg / 10.5 cm, where every neighbour pair's texture lines up better under the scan's
    poses than under the ground truth's: the calibrated scan's test finds the same frame at 10.5 cm)."""
    work = tmp_path_factory.mktemp("kitchen_half")
    root = subsampled(real_dir / "7scenes_redkitchen", 2, work / "data")
    out = work / "half.gscan"
    summary = scan_with_cli(root, out, NO_CALIBRATION, "--no-segment")
    ours = found_or_flagged(summary, out, root, ground_truth(root, NO_CALIBRATION))
    assert ours.registered >= 25, ours


def test_real_kinect_default_template_is_the_table_the_views_are_centred_on(real_dir: Path, tmp_path_factory):
    """The default scan (segmented, the README's intrinsics) keeps the object the views look at: the capture sweeps
    past a table (mugs, magazines) into a kitchen corner, no one thing on the table is at the centre of most views,
    so the object is the table top under the fixation point and what stands on it, not a chair's rail at its
    edge nor a strip of the counter beyond it (before: 6 of 30 queries found). The cameras, hand-held over it, are
    0.4-1.0 m above its plane (the floor is 1.3 m or more below them). Against that template at least 20 of the
    30 queries are found within 5 deg / 5 cm (22 when measured; 19 with the published calibration), and no pose
    is returned beyond 10 deg / 10 cm."""
    import numpy as np

    root = real_dir / "7scenes_redkitchen"
    out = tmp_path_factory.mktemp("kitchen_object") / "kitchen.gscan"
    summary = scan_with_cli(root, out, NO_CALIBRATION)
    obj = summary["object"]
    assert obj["by"] == "fixation" and obj["on_support"], obj
    assert obj["centre_share"] > 0 and obj["size_m"][2] < 0.5, obj
    heights = [T[2, 3] for T in template_poses(out).values()]  # template frame: z up from the support plane
    assert 0.4 < float(np.median(heights)) < 1.0, heights
    q = score_queries(out, root, NO_CALIBRATION, ground_truth(root, NO_CALIBRATION))
    assert not q.wrong, q.wrong
    assert len(q.found) >= 20, q
