"""End-to-end scans of captures rendered from the shared meshes (known poses) and of real frames.

Each synthetic capture is 12 views on one ring at 40 degrees elevation around a scanned textured
mesh resting on a textured table (static object), rendered with RealSense-like depth noise by
gscan.synth, or a 24-frame turntable (object turns, camera and table static).
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscan.evaluate.metrics import ate_rmse, frame_errors
from gscan.geometry.transforms import inv_T, pose_error
from gscan.io import open_sequence
from gscan.scanning.api import scan
from gscan.synth import load_textured_mesh, render_capture
from gscan.template.db import TemplateDB

MESHES = ["Crayola_Bonus_64_Crayons", "Frozen_Scrabble_Jr", "Mattel_SKIP_BO_Card_Game"]


def _ate_to_gt(db_path: Path, capture: Path) -> tuple[float, int]:
    """(ATE in metres of the registered camera positions vs ground truth, frames compared)."""
    with TemplateDB.open(db_path) as db:
        poses = db.poses()["frames"]
    gt = open_sequence(capture).gt_T_cam_obj
    names = [n for n in poses if n in gt]
    return ate_rmse([np.asarray(poses[n]) for n in names], [inv_T(gt[n]) for n in names]), len(names)


def _wrong_frames(db_path: Path, capture: Path, max_deg: float = 5.0, max_m: float = 0.02) -> list[str]:
    """Registered frames whose pose is beyond max_deg / max_m of the ground truth (the rendered benchmark's
    bound), relative to the other registered frames (`frame_errors`: free of the template's frame)."""
    with TemplateDB.open(db_path) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    gt = open_sequence(capture).gt_T_cam_obj
    return frame_errors(poses, {n: inv_T(T) for n, T in gt.items()}).wrong(max_deg, max_m)


@pytest.fixture(scope="module")
def captures(tmp_path_factory, meshes_dir):
    """mesh name -> (capture folder with masks, a copy without masks, true mesh vertices)."""
    root = tmp_path_factory.mktemp("captures")
    out = {}
    for k, name in enumerate(MESHES):
        mesh = load_textured_mesh(meshes_dir / name / "model_0.obj")
        cap = root / name
        render_capture(mesh, cap, 12, mode="static", elevations_deg=(40.0,), seed=k)
        bare = root / f"{name}_nomask"
        shutil.copytree(cap, bare)
        shutil.rmtree(bare / "masks")
        out[name] = (cap, bare, mesh.vertices)
    return out


@pytest.mark.parametrize("mesh", MESHES)
@pytest.mark.parametrize("masks", [False, True], ids=["auto-segment", "masks"])
def test_static_capture_registers_every_frame(captures, tmp_path, mesh, masks):
    cap = captures[mesh][0 if masks else 1]
    res = scan(cap, tmp_path / "obj.gscan")
    assert res.mode == "static-object"
    assert res.registered == 12 and res.unregistered == []
    ate, n = _ate_to_gt(tmp_path / "obj.gscan", captures[mesh][0])
    # rendered captures with noisy depth: the registered trajectory within 5 mm of the truth (ATE); a misregistered view
    # is centimetres off
    assert n == 12 and ate <= 0.005, f"ATE {ate * 1000:.2f} mm"
    assert res.mesh_vertices > 1000
    with TemplateDB.open(tmp_path / "obj.gscan") as db:
        info = db.summary()
        V = db.mesh().vertices
    assert info.status == "complete" and info.source == "scan"
    # the fused mesh is the object alone, not the table: its sorted extents match the true mesh's
    true_extent = np.sort(np.ptp(captures[mesh][2], axis=0))
    # the fused object's extents within 1.5 cm of the mesh's (the unseen bottom, segmentation at the table)
    assert np.all(np.abs(np.sort(np.ptp(V, axis=0)) - true_extent) < 0.015), (np.ptp(V, axis=0), true_extent)


def test_turntable_capture_registers_on_the_object(tmp_path, meshes_dir):
    # a turntable capture turns the object 15 degrees per frame (24 frames a turn)
    mesh = load_textured_mesh(meshes_dir / MESHES[1] / "model_0.obj")
    cap = tmp_path / "turntable"
    render_capture(mesh, cap, 24, mode="turntable", seed=5)
    res = scan(cap, tmp_path / "tt.gscan")
    assert res.mode == "moving-object"
    assert res.registered == 24, res.unregistered
    # before a static camera the texture cannot check the focal length (the background lines up at any): it says so
    from gscan.scanning.camera import MOVED_NOT
    assert res.camera is not None and res.camera["verdict"] == "could not confirm" and not res.camera["corrected"]
    assert res.camera["reason"] == MOVED_NOT and MOVED_NOT in res.camera["warning"], res.camera
    ate, n = _ate_to_gt(tmp_path / "tt.gscan", cap)
    # a turntable capture: trajectory within 5 mm of the truth
    assert n == 24 and ate <= 0.005, f"ATE {ate * 1000:.2f} mm"


def test_real_open3d_sequence_matches_trajectory_log(real_dir, tmp_path):
    rgbd = real_dir / "open3d_rgbd" / "RGBD"
    K = real_dir / "open3d_rgbd" / "camera_primesense.json"
    out = tmp_path / "room.gscan"
    proc = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(rgbd), "-o", str(out), "--format", "open3d",
                           "--intrinsics", str(K), "--no-segment", "--json"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["frames"] == 5 and summary["registered"] == 5 and summary["mode"] == "static-object"
    assert set(summary) >= {"output", "frames", "registered", "unregistered", "edges", "mode", "mesh", "timings_s"}
    poses = json.loads(subprocess.run([sys.executable, "-m", "gscan.cli", "poses", str(out), "--json"],
                                      capture_output=True, text=True, check=True).stdout)["frames"]
    gt = open_sequence(rgbd, format="open3d", intrinsics=K).gt_T_world_cam
    names = sorted(gt)
    for name in names[1:]:
        est = inv_T(np.asarray(poses[names[0]])) @ np.asarray(poses[name])
        true = inv_T(gt[names[0]]) @ gt[name]
        rot, trans = pose_error(est, true)
        motion_rot, motion_trans = pose_error(np.eye(4), true)
        # real frames (trajectory.log ground truth): each pose within a degree and 2 cm
        assert rot < 1.0 and trans < 0.02, (name, rot, trans)
        assert rot < motion_rot / 2 and trans < motion_trans / 2, (name, rot, trans, motion_rot, motion_trans)


def test_turntable_whose_print_repeats_on_opposite_faces(tmp_path, meshes_dir):
    """A 24-frame turntable of a card box 2.5 cm thick, printed alike on opposite faces; it turns edge on at frames 0
    and 12. Loop closures between its two faces are 180 deg off, and the edge-on views pin their pairs' poses only
    to 1.2-3.8 deg (its narrow side a few depth samples wide), beyond registration's 1 deg rule: nothing joins the
    two halves of the turn with confidence. The larger half is registered, no frame of it wrong (5 deg / 2 cm
    relative to the others) or beyond 3 deg of the truth; the other half is reported as a separate part, each frame
    with its reason. Refined on depth normals taken across the box's edge, the edge-on pairs claimed 0.5 deg at 3-5
    deg off and held 23 frames here (none of them wrong on this capture; 1 wrong on seed 10's, 24 without masks)."""
    from gscan.evaluate.bop19 import template_to_gt

    mesh = load_textured_mesh(meshes_dir / "Mattel_SKIP_BO_Card_Game" / "model_0.obj")
    cap = tmp_path / "turntable"
    render_capture(mesh, cap, 24, mode="turntable", seed=0, write_masks=False)
    out = tmp_path / "tt.gscan"
    res = scan(cap, out)
    assert res.mode == "moving-object" and res.registered >= 12, res.unregistered
    assert set(res.unregistered_reasons) == set(res.unregistered), res.unregistered_reasons
    assert sorted(n for part in res.parts for n in part) == sorted(res.unregistered) and len(res.parts) == 1, res.parts
    gt = open_sequence(cap).gt_T_cam_obj
    T_obj_gt = template_to_gt(out, gt)
    with TemplateDB.open(out) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    assert not frame_errors(poses, {n: inv_T(gt[n]) for n in poses}).wrong(5.0, 0.02)
    errs = {n: pose_error(T, T_obj_gt @ inv_T(gt[n]))[0] for n, T in poses.items()}
    assert max(errs.values()) < 3.0, errs


@pytest.mark.slow  # about 30 s: a 30-view scan
def test_wide_view_spacing_with_symmetric_print(tmp_path, meshes_dir):
    """36 degrees between views on three rings: the low ring sees the box's matching prints and the
    repetitive table from opposite sides, so some pairs give consistent but 180-degree-wrong lists (9-33
    inliers, and the depth of a box on a flat table is the same turned 180 degrees). They must be outvoted
    by the well-supported edges (50-800 inliers) or refuted by the texture around the box. Frame 4's edges are
    such flipped lists (the texture lines up in 7-25 % of the overlap, against 58-92 % for right edges here): it
    is left out with that reason rather than fused at a guess. Before weak edges were made doubtful, this capture
    scanned with an ATE of 87 mm."""
    mesh = load_textured_mesh(meshes_dir / MESHES[0] / "model_0.obj")
    cap = tmp_path / "wide"
    render_capture(mesh, cap, 30, mode="static", elevations_deg=(20.0, 40.0, 60.0), seed=0)
    res = scan(cap, tmp_path / "wide.gscan")
    assert res.registered >= 28, res.unregistered_reasons
    assert all(any(why in r for why in ("contradicted", "inconsistent", "colour disagrees"))
               for r in res.unregistered_reasons.values()), res.unregistered_reasons
    ate, n = _ate_to_gt(tmp_path / "wide.gscan", cap)
    # trajectory within 5 mm of the truth (it was 87 mm before weak edges were made doubtful), no frame wrong
    assert n == res.registered and ate <= 0.005, f"ATE {ate * 1000:.2f} mm"
    assert not _wrong_frames(tmp_path / "wide.gscan", cap), "a frame registered at a wrong pose"


def test_unusable_frames_are_named_in_input_order(tmp_path, monkeypatch):
    """The colour camera's check reads frames on two threads, so unreadable frames fail in any order. With every
    colour image truncated, the one-line error names the first frame in input order, whatever order they failed
    in (here the check reads them last to first)."""
    import gscan.scanning.pipeline as pipeline
    from gscan.demo import SAMPLES
    from gscan.errors import InputError

    cap = tmp_path / "cap"
    shutil.copytree(SAMPLES / "capture", cap)
    for p in sorted((cap / "rgb").glob("*.jpg")):
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])  # the header reads, the image does not decode

    def backwards(source, seq, opts, detections, mode):
        for name in reversed(seq.names):
            with pytest.raises(InputError):
                seq[name]
        return seq, None

    monkeypatch.setattr(pipeline, "check_camera", backwards)
    with pytest.raises(InputError, match=r"no usable frame \(30 unusable\); first: 000000: .*000000\.jpg"):
        scan(cap, tmp_path / "out.gscan")
