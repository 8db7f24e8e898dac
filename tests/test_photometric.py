"""Photometric refinement (gscan.registration.photometric): the glossy bottle's consecutive views, whose keypoints
under-turn, turned by their pixels as far as the bottle turned; no pose from texture that does not line up; the
disagreement of two estimates of one rotation; and a two-frame capture it places or refuses."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.geometry.symmetry import axis_rotation
from gscan.geometry.transforms import inv_T, make_T, pose_error, rotvec_to_R
from gscan.io.camera import RGBDFrame
from gscan.registration.dense import DenseGeometry, pose_information, pose_sigma
from gscan.registration.noise import DepthNoise
from gscan.registration.photometric import inner_pixels, refine_photometric, rotation_disagreement
from gscan.synth.cases import glossy_bottle_frames

ROOT = Path(__file__).resolve().parents[1]
PAIRS = (0, 6, 12, 18, 24, 30)  # source views; each registered to the next, 10 deg further round
NONE = np.zeros((0, 3))


@pytest.fixture(scope="module")
def bottle():
    return glossy_bottle_frames(36, seed=1)[1]


def _dense(f) -> DenseGeometry:
    return DenseGeometry.from_depth(f.depth, f.intrinsics, f.mask, image=f.color)


def _truth(frames, i: int) -> np.ndarray:
    return frames[i + 1].T_cam_obj @ inv_T(frames[i].T_cam_obj)


def _under_turned(frames, i: int, deg: float) -> np.ndarray:
    """The true pose of view i in view i + 1, turned back by `deg` about the bottle's axis (as its keypoints do)."""
    T_cam_obj = frames[i + 1].T_cam_obj
    back = axis_rotation(T_cam_obj[:3, 2], T_cam_obj[:3, 3], np.radians(-deg))
    return back @ _truth(frames, i)


def test_the_pixels_turn_the_bottle_as_far_as_it_turned(bottle):
    """From a pose 2.5 deg short of each 10 deg turn (the keypoints' median error: their support crosses the
    outline, which stays put while the bottle turns), the pixels bring it within 1.5 deg of the truth, a median
    below 0.8 deg, claiming sigmas below 1 deg that the errors exceed at most 4 times (measured: 3.6 times at
    the view 30, where the keypoints err most, 6 deg; the median error is 1.0 sigma)."""
    noise = DepthNoise()
    errors, ratios = [], []
    for i in PAIRS:
        src, tgt = _dense(bottle[i]), _dense(bottle[i + 1])
        T0 = _under_turned(bottle, i, 2.5)
        fit = refine_photometric(src, tgt, T0, pose_information(src, tgt, NONE, NONE, T0, noise, noise), noise)
        assert fit is not None, i
        deg = pose_error(fit.T_tgt_src, _truth(bottle, i))[0]
        errors.append(deg)
        ratios.append(deg / fit.sigma_deg)
        assert deg < 1.5 and deg < 4 * fit.sigma_deg and fit.sigma_deg < 1.0, (i, deg, fit.sigma_deg)
        assert fit.sigma_deg >= fit.jackknife_sigma_deg and fit.sigma_deg >= fit.model_sigma_deg
        assert np.isclose(pose_sigma(fit.information, np.zeros((0, 3)))[0], fit.sigma_deg)  # what rule 2 reads
        assert fit.pixels >= 1000
    assert np.median(errors) < 0.8 and np.median(ratios) < 1.5, (errors, ratios)


def test_texture_that_does_not_line_up_gives_no_pose(bottle):
    """The bottle turned upside down fits the depth (a cylinder) but not the label: its pixels do not correlate, so
    there is no photometric pose; nor without the full depth, nor on a frame without texture."""
    noise = DepthNoise()
    src, tgt = _dense(bottle[0]), _dense(bottle[1])
    T_cam_obj = bottle[1].T_cam_obj
    flip = axis_rotation(T_cam_obj[:3, 0], T_cam_obj[:3, 3], np.pi) @ _truth(bottle, 0)
    assert pose_error(flip, _truth(bottle, 0))[0] > 170
    info = pose_information(src, tgt, NONE, NONE, flip, noise, noise)
    assert refine_photometric(src, tgt, flip, info, noise) is None
    T = _truth(bottle, 0)
    info = pose_information(src, tgt, NONE, NONE, T, noise, noise)
    assert refine_photometric(src, tgt, T, info, noise) is not None
    plain = DenseGeometry.from_depth(bottle[0].depth, bottle[0].intrinsics, bottle[0].mask)
    assert refine_photometric(plain, tgt, T, info, noise) is None
    grey = np.full_like(bottle[0].color, 128)
    assert refine_photometric(DenseGeometry.from_depth(bottle[0].depth, bottle[0].intrinsics, bottle[0].mask,
                                                       image=grey), tgt, T, info, noise) is None


def test_inner_pixels_keep_away_from_outlines_and_depth_edges():
    """A 100 x 100 px face 1 m away with a 5 cm step down its middle: the interior keeps the pixels farther than
    EDGE_PX from the mask's outline and from the step and the hole."""
    from gscan.registration.photometric import EDGE_PX

    depth = np.zeros((200, 200), np.float32)
    depth[50:150, 50:150] = 1.0
    depth[50:150, 100:150] = 1.05
    depth[120, 70] = 0.0
    inner = inner_pixels(depth, depth > 0)
    v, u = np.nonzero(inner)
    assert v.min() > 50 + EDGE_PX - 1 and v.max() < 150 - EDGE_PX and u.min() > 50 + EDGE_PX - 1
    assert not inner[:, 100 - EDGE_PX:100 + EDGE_PX].any()  # the step
    assert not inner[120 - EDGE_PX:121 + EDGE_PX, 70 - EDGE_PX:71 + EDGE_PX].any()  # the hole
    assert inner[80, 75] and inner[80, 125]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3), st.floats(0.001, 0.05), st.floats(0.001, 0.05),
       st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3))
def test_rotation_disagreement_is_the_turn_over_both_sigmas(w, sa, sb, t):
    """Two estimates with isotropic rotation sigmas sa, sb (rad) a rotation w apart: chi-square |w|^2 / (sa^2 +
    sb^2), whatever the translations."""
    info_a = np.diag([1 / sa ** 2] * 3 + [1e4] * 3)
    info_b = np.diag([1 / sb ** 2] * 3 + [1e6] * 3)
    T_a = make_T(rotvec_to_R(np.array([0.3, -0.2, 0.1])), np.array(t))
    T_b = make_T(rotvec_to_R(np.array(w)), np.zeros(3)) @ T_a
    got = rotation_disagreement(T_a, info_a, T_b, info_b)
    assert np.isclose(got, float(np.dot(w, w)) / (sa ** 2 + sb ** 2), rtol=1e-6, atol=1e-9)


def test_a_lone_edge_the_keypoints_pin_loosely_is_placed_by_its_pixels(bottle):
    """Crayola (held out) seen from 0 and 60 deg, object pixels: the keypoints and depth pin the pose to more than
    1 deg (refused as weak geometry without the pixels); the pixels place it, right and nearer the truth. The
    bottle's views 30 and 31: the keypoints put the turn 6 deg off claiming 1.7 deg, the pixels turn it 7 deg back:
    the two disagree beyond both sigmas, and the edge is refused for it rather than placed on either."""
    sys.path.insert(0, str(ROOT / "bench"))
    from acceptance import is_right, meshes
    from match import render_views

    from gscan.registration.frames import register_frames
    from gscan.registration.pairwise import RegisterParams

    held = meshes("held-out")
    seed = [m.name for m in held].index("Crayola_Bonus_64_Crayons")
    (a, T_world_a), (b, T_world_b) = render_views(held[seed], [0.0, 60.0], seed=seed, table_kind="plain")
    T_gt = inv_T(T_world_b) @ T_world_a
    before = register_frames(a, b, RegisterParams(photometric=False), use_masks=True)
    assert not before.accepted and before.reason.startswith("weak geometry"), before.reason
    r = register_frames(a, b, use_masks=True)
    assert r.accepted, r.reason
    deg, m = pose_error(r.T_tgt_src, T_gt)
    assert is_right({"deg": deg, "m": m}) and deg < pose_error(before.T_tgt_src, T_gt)[0]
    assert r.sigma_deg is not None and r.sigma_deg <= 1.0 and "photometric" in r.timings_ms

    a, b = (RGBDFrame(str(k), bottle[k].color, bottle[k].depth, bottle[k].intrinsics, bottle[k].mask) for k in (30, 31))
    r = register_frames(a, b, use_masks=True)
    assert not r.accepted and r.reason.startswith("texture disagrees"), r.reason
