"""Recall on the failure kinds of a fixed match-count threshold (issue: the estimator missed objects it should
find), with templates gscan scanned itself from rendered captures: a thin flat box, an object lying on a side
relative to its scan, a can with a curved label, a small object with few keypoints per view, and a view
between the scan's keyframes. Every such scene is found within 1 cm and 10 deg with ADD below 10 % of the
object's bounding-box diagonal, and no wrong pose is returned in
scenes without the object or with a look-alike box of the same size in its place."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from gscan.estimate.estimator import Estimator
from gscan.evaluate.bop19 import template_to_gt
from gscan.evaluate.metrics import add
from gscan.geometry.transforms import look_at, pose_error, rotvec_to_R, transform_points
from gscan.io import open_sequence
from gscan.io.camera import RGBDFrame
from gscan.scanning.api import scan
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    box_mesh,
    load_textured_mesh,
    place_distractors,
    procedural_box_texture,
    render_capture,
    rest_on_table,
)
from gscan.synth.mesh import cylinder_mesh

pytestmark = pytest.mark.slow

DISTRACTORS = ("Apples_to_Apples_Kids_Edition", "Whey_Protein_Chocolate_12_Packets",
               "Nestle_Carnation_Cinnamon_Coffeecake_Kit_1913OZ")
SIDE = rotvec_to_R([np.pi / 2, 0.0, 0.0])  # lying on a side: turned 90 deg about a horizontal axis

# object -> scenes: (yaw deg, lying on a side, camera elevation deg, azimuth deg, distance m, table, seed). Before
# acceptance from the evidence (a fixed 14 matches) and joint matching, the first thin box scene (12 matches),
# the first two can scenes (5 and 7 matches), the can scene 208 (found 6 deg off), both small-object scenes (8)
# and the first view between keyframes (8) were missed.
SCENES = {
    "thinbox": [(93, False, 14.7, 323.82, 0.61, "wood", 0), (330, False, 20.0, 19.56, 0.61, "fabric", 7)],
    "side": [(301, True, 48.0, 14.25, 0.61, "wood", 100), (55, True, 69.3, 198.67, 0.58, "fabric", 101)],
    "can": [(165, False, 61.0, 210.62, 0.72, "plain", 202), (102, True, 31.3, 8.1, 0.6, "wood", 203),
            (321, False, 35.2, 356.99, 0.56, "plain", 208)],
    "small": [(24, True, 60.0, 84.69, 0.65, "fabric", 301), (102, False, 61.6, 336.32, 0.6, "plain", 302)],
    "between": [(0, False, 15.0, 11.25, 0.55, "plain", 9), (0, False, 78.0, 33.75, 0.6, "fabric", 10)],
}


def make_object(kind: str, meshes_dir: Path):
    if kind == "thinbox":
        return box_mesh((0.20, 0.14, 0.03), procedural_box_texture(3, (256, 384)), name="thinbox")
    if kind == "can":
        return cylinder_mesh(0.035, 0.12, procedural_box_texture(5, (256, 512)), name="can")
    if kind == "small":
        return load_textured_mesh(meshes_dir / "Nestle_Raisinets_Milk_Chocolate_35_oz_992_g" / "model_0.obj", 0.6)
    if kind == "side":
        return load_textured_mesh(meshes_dir / "Little_Debbie_Cloud_Cakes_10_ct" / "model_0.obj")
    return load_textured_mesh(meshes_dir / "Crayola_Bonus_64_Crayons" / "model_0.obj")


def render_scene(obj, scene, distractors, with_target: bool = True, stand_in=None):
    """(RGBDFrame, T_cam_obj of the object's place) of the object among the distractors."""
    yaw, lying, el, az, dist, table, seed = scene
    R = rotvec_to_R([0.0, 0.0, np.radians(yaw)]) @ (SIDE if lying else np.eye(3))
    T_wo = rest_on_table(obj, R)
    d_poses = place_distractors(obj, T_wo, distractors, np.random.default_rng(seed))
    first = [(stand_in if stand_in is not None else obj, T_wo)] if with_target else []
    c = transform_points(T_wo, obj.center[None])[0]
    e, a = np.radians(el), np.radians(az)
    T_wc = look_at(c + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]), c)
    r = SynthScene(first + list(zip(distractors, d_poses, strict=True)), seed=seed, table_kind=table).render(
        T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng([seed, 1]))
    return RGBDFrame(f"scene{seed}", r.color, r.depth, DEFAULT_INTRINSICS), np.linalg.inv(T_wc) @ T_wo


@pytest.fixture(scope="module")
def distractors(meshes_dir: Path):
    return [load_textured_mesh(meshes_dir / n / "model_0.obj") for n in DISTRACTORS]


@pytest.fixture(scope="module")
def scanned(meshes_dir: Path, tmp_path_factory):
    """kind -> (mesh, Estimator of its scanned template, T_obj_gt): each object scanned by gscan from a rendered
    16-frame capture standing on a newspaper table (rings at 30 and 55 deg), aligned to the ground truth by the
    capture's own poses (the template frame rule)."""
    root = tmp_path_factory.mktemp("recall")
    out = {}
    for kind in SCENES:
        mesh = make_object(kind, meshes_dir)
        render_capture(mesh, root / kind, 16, seed=11)
        scan(root / kind, root / f"{kind}.gscan")
        out[kind] = (mesh, Estimator.from_path(root / f"{kind}.gscan"),
                     template_to_gt(root / f"{kind}.gscan", open_sequence(root / kind).gt_T_cam_obj))
    return out


@pytest.fixture(scope="module")
def rendered(scanned, distractors) -> Callable[[str, int, bool], tuple[RGBDFrame, np.ndarray]]:
    """(kind, scene index, with the object) -> `render_scene` of that scene, rendered once for the module (the
    recall test and the no-wrong-pose test both estimate on the first scene of every object); the frames are
    read-only, so that no estimate can change what another one reads."""
    frames: dict[tuple[str, int, bool], tuple[RGBDFrame, np.ndarray]] = {}

    def get(kind: str, i: int, with_target: bool) -> tuple[RGBDFrame, np.ndarray]:
        if (kind, i, with_target) not in frames:
            frame, T_gt = render_scene(scanned[kind][0], SCENES[kind][i], distractors, with_target=with_target)
            frame.color.setflags(write=False)
            frame.depth.setflags(write=False)
            frames[kind, i, with_target] = frame, T_gt
        return frames[kind, i, with_target]
    return get


@pytest.mark.parametrize("kind", list(SCENES))
def test_failure_kinds_are_found(kind, scanned, rendered):
    mesh, est, T_obj_gt = scanned[kind]
    for i, scene in enumerate(SCENES[kind]):
        frame, T_gt = rendered(kind, i, True)
        res = est.estimate(frame)
        assert res.found, (kind, scene, res.reason)
        T_est = res.T_cam_obj @ T_obj_gt
        deg, m = pose_error(T_est, T_gt)
        # ADD within 10 % of the size (the LINEMOD criterion): a rotation the surface does not show is no error
        # of a grasp (the can turned 6.5 deg about its axis moves its label by 4 mm, 3 % of its 14 cm diagonal)
        size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        assert add(mesh.vertices, T_est, T_gt) < 0.1 * size and m < 0.01 and deg < 10.0, (kind, scene, deg, m)
        ev = res.evidence
        assert ev is not None and ev.score >= est.params.accept.min_score


def test_no_wrong_pose_without_the_object(scanned, distractors, rendered):
    """Every template against the first scene of each other object, its own first scene with the object removed,
    and a box of the thin box's size with another print in its place (its depth alone would confirm the pose)."""
    for kind, (_, est, _) in scanned.items():
        for other in SCENES:
            frame, _ = rendered(other, 0, other != kind)
            res = est.estimate(frame)
            assert not res.found, (kind, other, SCENES[other][0], res.evidence)
    thin, est, _ = scanned["thinbox"]
    lookalike = box_mesh((0.20, 0.14, 0.03), procedural_box_texture(1003, (256, 384)), name="lookalike")
    for scene in SCENES["thinbox"]:
        frame, _ = render_scene(thin, scene, distractors, stand_in=lookalike)
        res = est.estimate(frame)
        assert not res.found, (scene, res.evidence)
