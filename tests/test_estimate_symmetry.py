"""Estimation and tracking of objects that look the same under a half turn (gscan.estimate.symmetric): a box
printed alike under a half turn about its z axis (`half_turn_box`) has two right poses in every view. A symmetry
that holds in shape and texture makes them one answer, picked by a fixed rule; one in shape alone leaves the
texture to decide, and a view the texture cannot decide stays refused. Every pose is scored against the ground
truth up to the symmetries that hold in texture (none wrong)."""
from __future__ import annotations

import itertools
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gscan.errors import InputError
from gscan.estimate import Estimator, Tracker
from gscan.estimate.params import EstimateParams, SymmetryParams
from gscan.estimate.rivals import AMBIGUOUS
from gscan.estimate.symmetric import R_REF, PoseGroup
from gscan.geometry.symmetry import Symmetries, axis_rotation
from gscan.geometry.transforms import look_at, make_T, pose_error, rotvec_to_R, transform_points
from gscan.io.camera import RGBDFrame
from gscan.scanning.cad import template_from_mesh
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    box_mesh,
    procedural_box_texture,
    rest_on_table,
    save_textured_mesh,
    view_on_table,
)
from gscan.synth.cases import half_turn_box
from gscan.template.db import TemplateDB

SIZE = (0.16, 0.10, 0.06)
RZ = axis_rotation(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.pi)


def make_template(mesh, sym: Symmetries, out: Path, grasp: np.ndarray | None = None) -> Path:
    """`template-from-mesh` of the rendered mesh, its symmetries (and a grasp) set in the template."""
    tpl = out.with_suffix(".gscan")
    template_from_mesh(save_textured_mesh(mesh, out.with_suffix(".obj")), tpl, n_views=36)
    with TemplateDB.open(tpl, writable=True) as db:
        db.set_meta("symmetries", sym.to_json())
        if grasp is not None:
            db.add_grasp("top", grasp)
    return tpl


@pytest.fixture(scope="module")
def alike(tmp_path_factory):
    """The box printed alike under the half turn, bottom too: the turn holds in shape and texture."""
    mesh, sym = half_turn_box(SIZE, seed=3)
    grasp = make_T(rotvec_to_R([np.pi, 0.0, 0.0]), [0.03, 0.01, 0.03])
    return mesh, make_template(mesh, sym, tmp_path_factory.mktemp("sym") / "alike", grasp)


@pytest.fixture(scope="module")
def bottom_differs(tmp_path_factory):
    """The same box with its own print on the bottom: the turn holds in shape only, and a box on a table (its
    bottom hidden) looks the same turned."""
    mesh, sym = half_turn_box(SIZE, seed=3, bottom_alike=False)
    assert sym.holds_in == "shape"
    return mesh, make_template(mesh, sym, tmp_path_factory.mktemp("sym") / "bottom")


def on_table(mesh, azimuth_deg: float, yaw: float = 0.3):
    """The box resting on the table, seen from 50 deg elevation and 0.4 m: (frame, T_cam_obj)."""
    r = view_on_table(mesh, yaw, azimuth_deg, 50.0, 0.4)
    return RGBDFrame("query", r.color, r.depth, DEFAULT_INTRINSICS), r.T_cam_obj


def error_up_to(T: np.ndarray, T_gt: np.ndarray, group: list[np.ndarray]) -> tuple[float, float]:
    """(deg, m) of T against the nearest of T_gt @ S, S in `group` (the identity included)."""
    return min((pose_error(T, T_gt @ S) for S in group), key=lambda e: e[0])


def test_a_symmetric_view_gives_one_pose_the_same_every_run(alike):
    """Ignoring the symmetry, the view is ambiguous (the trap is real); with it, one pose, right up to the turn,
    marked, and the same pose on every run and from a fresh estimator."""
    mesh, tpl = alike
    frame, T_gt = on_table(mesh, 40.0)
    before = Estimator.from_path(tpl, EstimateParams(symmetry=SymmetryParams(enabled=False))).estimate(frame)
    assert not before.found and before.reason.startswith(AMBIGUOUS), before.reason
    est = Estimator.from_path(tpl)
    res = est.estimate(frame)
    assert res.found, res.reason
    assert res.symmetry == "180 deg about [0, 0, 1]", res.symmetry
    deg, m = error_up_to(res.T_cam_obj, T_gt, [np.eye(4), RZ])
    assert deg < 2 and m < 0.005, (deg, m)
    again = [est.estimate(frame).T_cam_obj, Estimator.from_path(tpl).estimate(frame).T_cam_obj]
    assert all(np.array_equal(T, res.T_cam_obj) for T in again)
    assert res.to_json()["symmetry"] == res.symmetry


def test_views_of_turned_boxes_get_the_same_answer(alike):
    """The box turned by the half turn shows the same picture: the answers agree (the rule reads the pose, not
    the hypothesis), and each is right up to the turn."""
    mesh, tpl = alike
    est = Estimator.from_path(tpl)
    for yaw in (0.3, 1.9):
        a, T_a = on_table(mesh, 120.0, yaw)
        b, T_b = on_table(mesh, 120.0, yaw + np.pi)
        assert pose_error(T_a, T_b @ RZ)[0] < 1e-6
        ra, rb = est.estimate(a), est.estimate(b)
        assert ra.found and rb.found, (ra.reason, rb.reason)
        for res, T_gt in ((ra, T_a), (rb, T_b)):
            deg, m = error_up_to(res.T_cam_obj, T_gt, [np.eye(4), RZ])
            assert deg < 2 and m < 0.005, (yaw, deg, m)
        deg, m = pose_error(ra.T_cam_obj, rb.T_cam_obj)
        assert deg < 2 and m < 0.005, (yaw, deg, m)


def test_grasps_are_offered_in_each_equivalent(alike):
    mesh, tpl = alike
    est = Estimator.from_path(tpl)
    frame, _ = on_table(mesh, 200.0)
    res = est.estimate(frame)
    assert res.found, res.reason
    G = est.model.grasps["top"]
    offered = res.grasp_equivalents["top"]
    assert len(offered) == 2
    assert np.allclose(offered[0], res.grasps["top"]) and np.allclose(offered[0], res.T_cam_obj @ G)
    assert np.allclose(offered[1], res.T_cam_obj @ RZ @ G)
    assert len(res.to_json()["grasp_equivalents"]["top"]) == 2


def test_malformed_symmetries_name_the_template(alike, tmp_path):
    path = tmp_path / "bad.gscan"
    shutil.copy(alike[1], path)
    with TemplateDB.open(path, writable=True) as db:
        db.set_meta("symmetries", {"discrete": [[1.0, 2.0]]})
    with pytest.raises(InputError, match="bad.gscan.*symmetries cannot be read"):
        Estimator.from_path(path)


def test_a_shape_only_symmetry_leaves_a_tie_refused(bottom_differs):
    """On the table the bottom that tells the turn is hidden: the views are exact ties and stay refused. From
    250 deg, the symmetries ignored, the keypoints' sign test let the turned pose win (a wrong pose): the turn by
    the symmetry in shape is weighed on keypoints that agree at either pose. Seen from below, the bottom's print
    decides and the pose is right."""
    mesh, tpl = bottom_differs
    est = Estimator.from_path(tpl, EstimateParams(symmetry=SymmetryParams(weigh_shape_turns=True)))
    frame, T_gt = on_table(mesh, 250.0)
    before = Estimator.from_path(tpl, EstimateParams(symmetry=SymmetryParams(enabled=False))).estimate(frame)
    assert before.found and pose_error(before.T_cam_obj, T_gt)[0] > 170, "the trap"
    for az in (40.0, 250.0):
        frame, _ = on_table(mesh, az)
        res = est.estimate(frame)
        assert not res.found and res.reason.startswith(AMBIGUOUS), (az, res.reason)
    T_world_obj = make_T(rotvec_to_R([2.8, 0.0, 0.3]), [0.0, 0.0, 0.3])
    eye = T_world_obj[:3, 3] + 0.4 * np.array([0.5, -0.3, 0.8]) / np.linalg.norm([0.5, -0.3, 0.8])
    r = SynthScene([(mesh, T_world_obj)], table=False, seed=0).render(look_at(eye, T_world_obj[:3, 3]),
                                                                      DEFAULT_INTRINSICS, rng=np.random.default_rng(0))
    res = est.estimate(RGBDFrame("below", r.color, r.depth, DEFAULT_INTRINSICS))
    assert res.found, res.reason
    deg, m = pose_error(res.T_cam_obj, r.T_cam_obj)
    assert deg < 2 and m < 0.005 and res.symmetry is None, (deg, m)


@pytest.mark.slow
def test_a_printed_box_with_shape_symmetries_is_told_apart_by_its_print(tmp_path):
    """A box printed differently on every face, its three half turns declared in shape only: the print decides,
    the pose is the true one (not an equivalent)."""
    mesh = box_mesh(SIZE, procedural_box_texture(5))
    sym = Symmetries(half_turn_box(SIZE)[1].discrete, (False, False, False))
    est = Estimator.from_path(make_template(mesh, sym, tmp_path / "printed"),
                              EstimateParams(symmetry=SymmetryParams(weigh_shape_turns=True)))
    for az in (40.0, 200.0):
        frame, T_gt = on_table(mesh, az)
        res = est.estimate(frame)
        assert res.found, res.reason
        deg, m = pose_error(res.T_cam_obj, T_gt)
        assert deg < 2 and m < 0.005 and res.symmetry is None, (az, deg, m)


@pytest.mark.slow
def test_a_half_turn_tracked_never_flips(alike):
    """The box turns 15 deg per frame through 165 deg, carried out of the view for three frames in the middle. The
    estimator's answers for the first and last frames are different equivalents (the rule's choice changes with
    the turn), yet the tracker keeps one: every pose is ground truth @ the first frame's equivalent, and no two
    consecutive poses jump."""
    mesh, tpl = alike
    est = Estimator.from_path(tpl)
    T0 = rest_on_table(mesh, rotvec_to_R([0.0, 0.0, 0.3]))
    c = transform_points(T0, mesh.center[None])[0]
    el, az = np.radians(45.0), np.radians(-70.0)
    T_wc = look_at(c + 0.45 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]), c)
    scene = SynthScene([(mesh, T0)], seed=1)
    away = (4, 5, 6)
    frames = []
    for i in range(12):
        R = rotvec_to_R([0.0, 0.0, np.radians(15.0 * i)])
        T = make_T(R, c - R @ c + (np.array([3.0, 0.0, 0.0]) if i in away else 0.0)) @ T0
        frames.append(scene.render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng([1, i]),
                                   T_world_obj_override=T))
    first, last = (est.estimate(RGBDFrame("f", r.color, r.depth, DEFAULT_INTRINSICS)) for r in (frames[0], frames[-1]))
    S_first = min((np.eye(4), RZ), key=lambda S: pose_error(first.T_cam_obj, frames[0].T_cam_obj @ S)[0])
    assert pose_error(last.T_cam_obj, frames[-1].T_cam_obj @ S_first)[0] > 170, "the trap: the rule's choice flips"
    tracker = Tracker(est)
    poses = []
    for i, r in enumerate(frames):
        step = tracker.step(RGBDFrame(f"{i:06d}", r.color, r.depth, DEFAULT_INTRINSICS))
        if i in away:
            assert step.result.T_cam_obj is None
            continue
        assert step.result.T_cam_obj is not None, (i, step.status, step.result.reason)
        deg, m = pose_error(step.result.T_cam_obj, r.T_cam_obj @ S_first)
        assert deg < 3 and m < 0.005, (i, step.status, deg, m)
        poses.append((i, step.result.T_cam_obj))
        assert np.allclose(step.result.grasp_equivalents["top"][0], step.result.grasps["top"])
    for (i, a), (j, b) in itertools.pairwise(poses):
        assert pose_error(a, b)[0] < 15.0 * (j - i) + 3.0, (i, j)  # the turn between the frames; a flip is 180


# ------------------------------------------------------------------------------------------------ the rule


@st.composite
def poses(draw) -> np.ndarray:
    rv = draw(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
    t = draw(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3))
    return make_T(rotvec_to_R(np.array(rv)), np.array(t))


AXIS = (np.array([0.0, 0.6, 0.8]), np.array([0.01, -0.02, 0.0]))
CAN = PoseGroup.of(Symmetries((axis_rotation(np.array([1.0, 0.0, 0.0]), AXIS[1], np.pi),), (True,), (AXIS,),
                              (True,)))


@given(poses(), st.floats(0.0, 2 * np.pi))
def test_the_rule_reads_the_pose_not_the_equivalent(T, theta):
    """A body of revolution with a flip: any equivalent of a pose gives the same canonical pose, which is nearer
    R_REF than every sampled equivalent."""
    E = T @ axis_rotation(*AXIS, theta)
    a, b = CAN.canonical(T), CAN.canonical(E)
    assert pose_error(a, b)[0] < 1e-6 and pose_error(a, b)[1] < 1e-9
    assert CAN.apart(E, T)[0] < 1e-6
    cos = np.trace(R_REF.T @ a[:3, :3])
    assert all(np.trace(R_REF.T @ Q[:3, :3]) <= cos + 1e-9 for Q in CAN.equivalents(T, 5.0))


def test_a_continuous_axis_offers_grasps_at_the_stated_step():
    T = make_T(rotvec_to_R([0.3, -0.2, 1.0]), [0.0, 0.0, 0.5])
    eq = CAN.equivalents(T, 30.0)
    assert len(eq) == 24 and np.array_equal(eq[0], T)  # 12 turns, each with and without the flip
    none = PoseGroup.of(Symmetries())
    assert not none and len(none.equivalents(T, 30.0)) == 1 and np.array_equal(none.canonical(T), T)
