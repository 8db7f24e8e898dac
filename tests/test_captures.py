"""Several captures of one object, one template (issue 38): the captures a scan reads (`gscan.io.captures`), and
end to end a box scanned upright and upside down (the object moved against the table between the captures) with a
capture of another object given by mistake."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from gscan import synth
from gscan.errors import InputError
from gscan.geometry.transforms import inv_T, mean_pose, rotation_angle_deg, transform_points
from gscan.io.captures import capture_inputs
from gscan.scanning.api import scan
from gscan.synth.cases import Case, two_sided_captures
from gscan.template.db import TemplateDB
from tests._scan_checks import WRONG_RENDERED

BOX_SIZE = (0.08, 0.05, 0.12)


def _folder(path: Path) -> Path:
    path.mkdir(parents=True)
    return path


def test_capture_names_are_the_folders_made_unique(tmp_path):
    a, b = _folder(tmp_path / "one" / "cap"), _folder(tmp_path / "two" / "cap")
    rec = tmp_path / "shelf.bag"
    rec.write_bytes(b"")
    got = capture_inputs([a, b, rec, a], None)
    assert [c.name for c in got] == ["cap", "cap-2", "shelf", "cap-3"]
    assert [c.source for c in got] == [a, b, rec, a]


def test_bop_onboarding_captures_of_one_object(tmp_path):
    ds = tmp_path / "ds"
    for d in ["onboarding_static/obj_000002_down", "onboarding_static/obj_000002_up", "onboarding_dynamic/obj_000002",
              "onboarding_static/obj_000005_up", "onboarding_static/notes"]:
        _folder(ds / d)
    got = capture_inputs([ds], 2)
    assert [c.name for c in got] == ["obj_000002_up", "obj_000002_down", "obj_000002"]
    assert all(c.obj_id == 2 and c.format == "bop" for c in got)
    with pytest.raises(InputError, match="objects 2, 5: choose one"):
        capture_inputs([ds], None)
    with pytest.raises(InputError, match="no onboarding capture of object 7"):
        capture_inputs([ds], 7)
    with pytest.raises(InputError, match="give it alone"):
        capture_inputs([ds, _folder(tmp_path / "other")], 2)
    assert [c.name for c in capture_inputs([ds], 5)] == ["obj_000005_up"]


def _gt_T_obj_cam(capture: Path) -> dict[str, np.ndarray]:
    """frame -> ground-truth T_obj_cam (the mesh's frame) of a rendered capture."""
    return {f.stem: inv_T(np.loadtxt(f)) for f in sorted((capture / "annotated_poses").glob("*.txt"))}


def _completeness(db_path: Path, mesh: synth.TexturedMesh, T_tmpl_mesh: np.ndarray, tol: float = 0.005) -> float:
    """Share of the true surface (sampled evenly) within `tol` of the template's fused cloud (observed surface
    only: the cloud holds no filled hole)."""
    with TemplateDB.open(db_path) as db:
        pts, _ = db.cloud()
    tm = trimesh.Trimesh(mesh.vertices, mesh.triangles, process=False)
    samples, _ = trimesh.sample.sample_surface_even(tm, 20000, seed=0)
    d, _ = cKDTree(pts).query(transform_points(T_tmpl_mesh, samples))
    return float((d < tol).mean())


@pytest.fixture(scope="module")
def two_sided(tmp_path_factory, meshes_dir):
    """A printed box scanned upright and upside down, with a capture of another object given by mistake."""
    root = tmp_path_factory.mktemp("two_sided")
    box = synth.box_mesh(BOX_SIZE, synth.procedural_box_texture(3, (512, 768)), name="box")
    up, down = two_sided_captures(box, root / "box", n_views=12)
    other = synth.load_textured_mesh(meshes_dir / "Vans_Cereal_Honey_Nut_Crunch_11_oz_box" / "model_0.obj")
    synth.render_capture(other, root / "cereal", 8, seed=5, table_kind="wood")
    out = root / "box.gscan"
    proc = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(up.path), str(down.path),
                           str(root / "cereal"), "-o", str(out), "--json"], capture_output=True, text=True,
                          timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return box, up, down, out, json.loads(proc.stdout)


@pytest.mark.slow
def test_two_sided_scan_joins_both_sides_and_refuses_another_object(two_sided):
    box, up, down, out, res = two_sided
    caps = {c["name"]: c for c in res["captures"]}
    assert caps["up"]["joined"] and caps["down"]["joined"], caps
    assert caps["down"]["joined_at_turn"] is None, caps  # joined at the motion its view pairs agree on
    assert not caps["cereal"]["joined"] and caps["cereal"]["reason"], caps
    assert "join" in res["timings_s"]
    with TemplateDB.open(out) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    # every frame of both captures in one object frame, named CAPTURE/FRAME; nothing of the other object
    gt = {f"{c.path.name}/{n}": T for c in (up, down) for n, T in _gt_T_obj_cam(c.path).items()}
    assert set(poses) == set(gt), sorted(set(poses) ^ set(gt))
    cereal = [n for n in res["unregistered"] if n.startswith("cereal/")]
    assert len(cereal) == 8 and all("capture cereal was not joined" in res["unregistered_reasons"][n] for n in cereal)
    assert sorted(cereal) in [sorted(p) for p in res["parts"]]
    T_tmpl_mesh = mean_pose([poses[n] @ inv_T(gt[n]) for n in poses])
    for n, T in poses.items():
        D = inv_T(T_tmpl_mesh @ gt[n]) @ T
        assert rotation_angle_deg(D[:3, :3]) < WRONG_RENDERED[0] and np.linalg.norm(D[:3, 3]) < WRONG_RENDERED[1], n
    # the fused surface, as observed, covers the whole box, the bottom included (the upright capture alone covers
    # about 90 % of it: the face it stands on is never seen)
    assert _completeness(out, box, T_tmpl_mesh) >= 0.97
    assert not any("bottom" in m for m in res["coverage"]["missing"]), res["coverage"]


@pytest.fixture(scope="module")
def upright_only(two_sided, tmp_path_factory):
    """The upright capture alone, scanned: the template captures are appended to."""
    _, up, _, _, _ = two_sided
    out = tmp_path_factory.mktemp("upright") / "up.gscan"
    scan(up.path, out)
    return out


@pytest.mark.slow
def test_append_gives_the_poses_of_scanning_both_at_once(two_sided, upright_only, tmp_path):
    _, _, down, both, _ = two_sided
    out = tmp_path / "appended.gscan"
    out.write_bytes(upright_only.read_bytes())
    with TemplateDB.open(out) as db:
        before = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
        cov = db.coverage()
        assert cov is not None and any("bottom" in m for m in cov.missing()), "the upright capture sees no bottom"
    res = scan(down.path, out, append=True)
    assert res.coverage is not None and not any("bottom" in m for m in res.coverage["missing"]), res.coverage
    assert [c["name"] for c in res.captures] == ["up", "down"] and all(c["joined"] for c in res.captures)
    with TemplateDB.open(out) as db:
        after = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    with TemplateDB.open(both) as db:
        at_once = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    # the template's views keep their poses (its frame is kept), renamed up/FRAME as a scan of several names them
    assert {f"up/{n}" for n in before} == {n for n in after if n.startswith("up/")}
    for n, T in before.items():
        np.testing.assert_allclose(after[f"up/{n}"], T, atol=1e-9)
    assert set(after) == set(at_once)
    # the same poses as the scan of both at once, up to the template frame: that scan sets it from the surface of
    # both captures, the appended one keeps the upright capture's (measured: 0.8 deg / 6 mm apart); the views
    # relative to each other agree within 0.1 deg / 1 mm
    A = mean_pose([at_once[n] @ inv_T(after[n]) for n in after])
    assert rotation_angle_deg(A[:3, :3]) < 2.0 and np.linalg.norm(A[:3, 3]) < 0.015
    for n in after:
        D = inv_T(at_once[n]) @ A @ after[n]
        assert rotation_angle_deg(D[:3, :3]) < 0.1 and np.linalg.norm(D[:3, 3]) < 0.001, n


@pytest.mark.slow
def test_append_of_a_capture_that_cannot_be_joined_leaves_the_template_as_it_was(two_sided, upright_only, tmp_path):
    _, _, _, both, _ = two_sided
    out = tmp_path / "up.gscan"
    out.write_bytes(upright_only.read_bytes())
    before = out.read_bytes()
    cereal = both.parent / "cereal"
    proc = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(cereal), "-o", str(out), "--append"],
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and str(cereal) in lines[0] and "cannot be joined" in lines[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["up.gscan"]


@pytest.fixture(scope="module")
def pepsi_sides(tmp_path_factory, meshes_dir) -> tuple[Case, Case]:
    """The Pepsi 12-pack, whose top and bottom carry the same print, rendered upright and upside down (12 views
    each); the tests only read the captures."""
    pack = synth.load_textured_mesh(meshes_dir / "Pepsi_Caffeine_Free_Diet_12_CT" / "model_0.obj")
    return two_sided_captures(pack, tmp_path_factory.mktemp("pepsi") / "pack", n_views=12)


@pytest.fixture(scope="module")
def pepsi_template(pepsi_sides, tmp_path_factory) -> Path:
    """The Pepsi 12-pack's two captures scanned into one template, checked joined right (`_joined_right`)."""
    up, down = pepsi_sides
    out = tmp_path_factory.mktemp("pepsi_tpl") / "pack.gscan"
    poses = _joined_right(up, down, out)
    assert sum(n.startswith("down/") for n in poses) == 12
    return out


@pytest.mark.slow
def test_a_print_repeated_on_top_and_bottom_joins_at_the_half_turn_of_the_motion_found(pepsi_template):
    """The Pepsi 12-pack carries the same print on its top and bottom: the view pairs of the two sides agree on a
    motion that turns the object 180 deg (45 pairs; it once joined the upside-down capture there, all 12 frames
    180 deg off). On the surface patches both overlap, its half turn about the first principal axis wins 18 to 1
    (refused as ambiguous before): the capture is joined at that turn, refined on its 113 keypoint pairs, every
    frame within the wrong-pose bound of the truth (the fixture), and the template says it was joined at a turn."""
    with TemplateDB.open(pepsi_template) as db:
        join = next(c["join"] for c in db.meta()["captures"] if c["name"] == "down")
    assert "180 deg" in join["joined_at_turn"], join


@pytest.mark.slow
def test_a_weak_pose_of_a_print_repeated_on_top_and_bottom_is_never_its_twin(pepsi_sides, pepsi_template,
                                                                              meshes_dir):
    """bench/two_sided.py's Pepsi scene 1: the pack lies on its side, small among two other packs. With the
    two-sided template a pose 179 deg off (its top's print laid on the template's bottom) was accepted on 11
    supporters within 2 cm; the turn, the truth, fits the depth as well, and 10 keypoints for the pose alone
    against 4 for the turn do not tell them apart. The estimate is the true pose or a refusal as ambiguous."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from recall import distractor_pool
    from two_sided import OBJECTS, scenes

    from gscan.estimate import Estimator

    oi, spec = next((i, s) for i, (s, _) in enumerate(OBJECTS) if s.name == "pepsi_pack")
    mesh = synth.load_textured_mesh(meshes_dir / spec.source / "model_0.obj")
    _, _, frame, T_gt = next(x for k, x in enumerate(scenes(spec, oi, mesh, distractor_pool(), 10)) if k == 1)
    with TemplateDB.open(pepsi_template) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    gt = _gt_T_obj_cam(pepsi_sides[0].path)
    res = Estimator.from_path(pepsi_template).estimate(frame)
    if res.found:
        T_tmpl_mesh = mean_pose([poses[f"up/{n}"] @ inv_T(T) for n, T in gt.items()])
        D = inv_T(T_gt @ inv_T(T_tmpl_mesh)) @ res.T_cam_obj
        assert rotation_angle_deg(D[:3, :3]) < WRONG_RENDERED[0], res
    else:
        assert res.reason.startswith("ambiguous view"), res.reason


def _joined_right(up: Case, down: Case, out: Path) -> dict[str, np.ndarray]:
    """The template's frame poses of `scan([up, down], out)`, asserting the down capture joined and every frame
    within the wrong-pose bound of the truth (the up capture's frames place the mesh in the template)."""
    res = scan([up.path, down.path], out)
    caps = {c["name"]: c for c in res.captures}
    assert caps["down"]["joined"], caps
    with TemplateDB.open(out) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    gt = {f"{c.path.name}/{n}": T for c in (up, down) for n, T in _gt_T_obj_cam(c.path).items()}
    T_tmpl_mesh = mean_pose([poses[n] @ inv_T(gt[n]) for n in poses if n.startswith("up/")])
    for n, T in poses.items():
        D = inv_T(T_tmpl_mesh @ gt[n]) @ T
        assert rotation_angle_deg(D[:3, :3]) < WRONG_RENDERED[0] and np.linalg.norm(D[:3, 3]) < WRONG_RENDERED[1], n
    return poses


@pytest.mark.slow
def test_a_box_printed_alike_on_top_and_bottom_joins_at_the_right_motion(tmp_path):
    """A flat box whose top and bottom carry a print partly alike: turned 180 deg, the upside-down capture's bottom
    lies on the upright capture's top with a quarter of its textured tiles lining up (and more keypoints agreeing
    than under the right motion), which the nearest views alone did not refute (0.34 of their tiles); over every
    view pair it lines up in a third as many tiles as the right motion, and the capture is joined at that."""
    box = synth.box_mesh((0.18, 0.12, 0.05), synth.procedural_box_texture(33, (256, 384)), name="box_flat")
    up, down = two_sided_captures(box, tmp_path / "flat", n_views=12)
    assert any(n.startswith("down/") for n in _joined_right(up, down, tmp_path / "flat.gscan"))


@pytest.mark.slow
def test_a_soft_pack_joins_where_its_print_sampled_finely_refutes_the_half_turn(tmp_path, meshes_dir):
    """The Tena pads (bench/two_sided.py's held-out split): the join's motion found is right, and its half turn about
    the second axis lost 11 surface patches to 1 of 14 on the default samples (p = 0.0032, short of the 0.001 a
    refutation needs: not joined); on tiles sampled every 2 px it is refuted and the capture joined, every frame
    within the wrong-pose bound of the truth."""
    pads = synth.load_textured_mesh(meshes_dir / "Tena_Pads_Heavy_Long_42_pads" / "model_0.obj")
    up, down = two_sided_captures(pads, tmp_path / "pads", n_views=12)
    assert sum(n.startswith("down/") for n in _joined_right(up, down, tmp_path / "pads.gscan")) == 12


@pytest.mark.slow
def test_a_one_sided_template_never_takes_the_bottom_for_the_top(pepsi_sides, tmp_path):
    """The Pepsi 12-pack scanned upright only: its template has never seen the bottom, which carries the top's
    print. Seen upside down, the pack's bottom matches the template's top at the pose turned 180 deg, and that pose
    was accepted: all 12 views before the unseen-side rule, 2 of 12 (000004, 000009) while the keypoints on the top's
    rim counted as telling the turn (under it they lie on the bottom's rim, within reach of the seen sides; the
    rule now counts a keypoint within reach of unseen surface as on it). Every estimate on the upside-down views
    must be the true pose or a refusal that says why."""
    from gscan.estimate import Estimator
    from gscan.io.sequence import open_sequence

    up, down = pepsi_sides
    scan(up.path, tmp_path / "up.gscan")
    with TemplateDB.open(tmp_path / "up.gscan") as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    gt_up = _gt_T_obj_cam(up.path)
    T_tmpl_mesh = mean_pose([poses[n] @ inv_T(gt_up[n]) for n in poses])
    est = Estimator.from_path(tmp_path / "up.gscan")
    seq = open_sequence(down.path)
    reasons = []
    for i in range(len(seq)):
        frame = seq[i]
        res = est.estimate(frame)
        if not res.found:
            reasons.append(res.reason)
            continue
        D = inv_T(seq.gt_T_cam_obj[frame.name] @ inv_T(T_tmpl_mesh)) @ res.T_cam_obj
        assert rotation_angle_deg(D[:3, :3]) < WRONG_RENDERED[0], (frame.name, res.reason)
    assert reasons and all("side the template has not seen" in r for r in reasons if r.startswith("ambiguous")), reasons
