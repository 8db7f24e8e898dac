"""A look-alike beside the object (gscan.estimate.instances.elsewhere): a box of the same size printed alike on
every face but its front stands beside the templated box. When both show faces they share, the single estimate
cannot tell which one is meant: it refuses the view as ambiguous, naming both places, instead of returning the
pose of whichever shows more of the print (the look-alike's, turned 50 deg and 38 cm from the box, before the
search elsewhere); a mask on the box gives its pose. When the look-alike shows its own front, its print rules it
out and the box is found. One CAD template of 16 views and four rendered frames (21 s at load 10 on 2 cores)."""
from __future__ import annotations

import re

import numpy as np
import pytest

from gscan.estimate import Estimator
from gscan.estimate.rivals import AMBIGUOUS
from gscan.geometry.transforms import look_at, pose_error, rotvec_to_R, transform_points
from gscan.io.camera import RGBDFrame
from gscan.scanning.cad import template_from_mesh
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    box_mesh,
    procedural_box_texture,
    rest_on_table,
    save_textured_mesh,
)

SIZE = (0.12, 0.05, 0.16)  # the front (+y) and back (-y) are the large faces
TEXTURE = (384, 576)
FRONT = 2  # +y: the third cell of box_mesh's 3 x 2 atlas (+x, -x, +y / -y, +z, -z)
BOX_XY, OTHER_XY = (-0.12, 0.25), (0.12, -0.05)  # m: the box behind, the look-alike in front


def reprinted(texture: np.ndarray, cell: int, other: np.ndarray) -> np.ndarray:
    """`texture` with the atlas cell `cell` (box_mesh's 3 x 2 grid) taken from `other`: one face printed
    differently, the others alike."""
    h, w = texture.shape[:2]
    out = texture.copy()
    x0, y0 = (cell % 3) * w // 3, (cell // 3) * h // 2
    out[y0:y0 + h // 2, x0:x0 + w // 3] = other[y0:y0 + h // 2, x0:x0 + w // 3]
    return out


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """(estimator of the box, the box, the look-alike)."""
    root = tmp_path_factory.mktemp("lookalike")
    texture = procedural_box_texture(21, TEXTURE)
    box = box_mesh(SIZE, texture, name="box")
    other = box_mesh(SIZE, reprinted(texture, FRONT, procedural_box_texture(1021, TEXTURE)), name="lookalike")
    save_textured_mesh(box, root / "box.obj")
    template_from_mesh(root / "box.obj", root / "box.gscan", n_views=16)
    return Estimator.from_path(root / "box.gscan"), box, other


def render(setup, yaw_deg: float, other_yaw_deg: float | None = None,
           look_alike: bool = True) -> tuple[RGBDFrame, np.ndarray, np.ndarray]:
    """(frame, the box's pose T_cam_obj, its visible pixels [H x W]): the box and the look-alike stand on the
    table 26 cm apart, turned yaw_deg and other_yaw_deg (default -yaw_deg) about the vertical (0: the back, -y,
    faces the camera; 180: the front)."""
    _, box, other = setup
    other_yaw = -yaw_deg if other_yaw_deg is None else other_yaw_deg
    T_box = rest_on_table(box, rotvec_to_R([0.0, 0.0, np.radians(yaw_deg)]), xy=BOX_XY)
    T_other = rest_on_table(other, rotvec_to_R([0.0, 0.0, np.radians(other_yaw)]), xy=OTHER_XY)
    objects = [(box, T_box)] + ([(other, T_other)] if look_alike else [])
    r = SynthScene(objects, seed=5, table_kind="wood").render(
        look_at(np.array([0.0, -0.55, 0.35]), np.array([0.0, 0.0, 0.07])))
    return RGBDFrame("query", r.color, r.depth, DEFAULT_INTRINSICS), r.T_cam_obj, r.mask


def assert_at(res, T_true: np.ndarray) -> None:
    assert res.found, res.reason
    deg, m = pose_error(res.T_cam_obj, T_true)
    assert deg < 5 and m < 0.01, (deg, m)


def test_the_object_alone_is_found(setup):
    """The control: without the look-alike the box, its back in view, is found where it is."""
    frame, T_true, _ = render(setup, 50.0, look_alike=False)
    assert_at(setup[0].estimate(frame), T_true)


def test_a_look_alike_beside_it_makes_the_view_ambiguous(setup):
    """The look-alike beside it, both backs in view, the look-alike's squarely (more of its print agrees than of
    the box's, turned 50 deg): no pose is returned (neither the box's nor the look-alike's), and the reason
    names both places (their centres in the camera frame, to the centimetre); a mask on the box (the other
    place outside it) gives the box's pose."""
    est = setup[0]
    frame, T_true, mask = render(setup, 50.0, 0.0)
    res = est.estimate(frame)
    assert res.T_cam_obj is None, pose_error(res.T_cam_obj, T_true)
    assert res.reason.startswith(AMBIGUOUS) and "two places" in res.reason, res.reason
    places = [np.array(m.split(", "), float) for m in re.findall(r"\(([-0-9.]+, [-0-9.]+, [-0-9.]+)\) m", res.reason)]
    centre = transform_points(T_true, est.model.center[None])[0]
    assert len(places) == 2 and min(np.abs(c - centre).max() for c in places) <= 0.01, (centre, res.reason)
    assert_at(est.estimate(frame, mask=mask), T_true)


def test_a_look_alike_showing_its_other_front_is_no_second_place(setup):
    """Both fronts in view: the look-alike's print differs there, so no pose fits it and the box is found."""
    frame, T_true, _ = render(setup, 200.0, 180.0)
    assert_at(setup[0].estimate(frame), T_true)
