"""The join's comparison of a turned motion's texture with the motion found's (`gscan.registration.join`), on the
tile counts measured over every view pair of rendered two-sided captures (bench/two_sided.py's objects); and, end
to end on rendered two-sided captures (their views placed at the rendered poses, so no scan is needed), two motions
compared on the surface patches both overlap."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from gscan import synth
from gscan.features.keypoints import OBJECT_FEATURES, extract_features_in_mask
from gscan.geometry.transforms import inv_T, rotation_angle_deg
from gscan.io.camera import RGBDFrame
from gscan.io.sequence import spread_indices
from gscan.registration.colour import ColourAgreement
from gscan.registration.edges import RegData
from gscan.registration.join import Join, JoinParams, JoinView, _texture_outweighs, join_captures
from gscan.registration.pairwise import RegisterParams
from gscan.scanning.config import ScanConfig, for_capture
from gscan.scanning.modes import MOVING_OBJECT
from gscan.synth.cases import half_turn_box, two_sided_frames
from tests._scan_checks import WRONG_RENDERED

RATIO = JoinParams().turn_texture_ratio
RP = RegisterParams()


def test_a_turn_a_partly_repeated_print_supports_is_outweighed():
    # Crayola: the right motion lines up in 58 of 67 tiles, the half turn in 25 of 74 (above a third: not refuted
    # on its own); the flat box: 19 of 23 against 124 of 469
    assert _texture_outweighs(ColourAgreement(67, 58), ColourAgreement(74, 25), RATIO, RP)
    assert _texture_outweighs(ColourAgreement(23, 19), ColourAgreement(469, 124), RATIO, RP)


def test_the_right_motion_is_never_outweighed_by_a_print_repeated_on_top_and_bottom():
    # the Pepsi pack: the wrong motion (top laid on bottom, both seen squarely) lines up in 374 of 411 tiles, the
    # right one (the sides, seen obliquely) in 42 of 67; Frozen Scrabble Jr's half turn, 171 of 288, against the
    # right motion's 103 of 111: neither motion outweighs the other
    assert not _texture_outweighs(ColourAgreement(411, 374), ColourAgreement(67, 42), RATIO, RP)
    assert not _texture_outweighs(ColourAgreement(111, 103), ColourAgreement(288, 171), RATIO, RP)


def test_too_few_textured_tiles_outweigh_nothing():
    few = RP.min_colour_tiles - 1
    assert not _texture_outweighs(ColourAgreement(few, few), ColourAgreement(100, 0), RATIO, RP)
    assert not _texture_outweighs(ColourAgreement(100, 100), ColourAgreement(few, 0), RATIO, RP)


def _join_rendered(mesh: synth.TexturedMesh, n_views: int) -> tuple[Join, np.ndarray]:
    """Two-sided captures of `mesh` rendered (`two_sided_frames`), each view placed at its rendered pose in its
    capture's world (the table's), joined as a scan joins them (the object's own keypoints and depth; a moving
    object's registration settings): (the join, the true T_a_b [4 x 4])."""
    up, down = two_sided_frames(mesh, n_views)
    rparams = for_capture(ScanConfig(), MOVING_OBJECT).registration

    def views(frames: list, side: str) -> list[JoinView]:
        out = []
        for i in spread_indices(len(frames), JoinParams().views, nearest=True):
            f = frames[i]
            feats = extract_features_in_mask(RGBDFrame(f"{side}/{i}", f.color, f.depth, synth.DEFAULT_INTRINSICS),
                                             f.mask, OBJECT_FEATURES)
            out.append(JoinView(f"{side}/{i}", RegData.of_frame(feats, f.depth, f.color, synth.DEFAULT_INTRINSICS,
                                                                 f.mask, rparams.icp_voxel), f.T_world_cam))
        return out

    T_true = up[0].T_world_cam @ up[0].T_cam_obj @ inv_T(down[0].T_world_cam @ down[0].T_cam_obj)
    with ThreadPoolExecutor(2) as pool:
        return join_captures(views(up, "up"), views(down, "down"), rparams, JoinParams(), pool), T_true


def test_two_motions_are_told_apart_by_the_texture_both_overlap(meshes_dir):
    """Frozen Scrabble Jr upright and upside down: view pairs agree on two motions, the right one and a half turn
    under which much of the print lines up too (18 and 9 pairs), which once left the capture unjoined. Refined
    alike on the keypoints, the two are compared on the surface patches both overlap, and the half turn loses
    nearly every one: the capture is joined at the right motion."""
    mesh = synth.load_textured_mesh(meshes_dir / "Frozen_Scrabble_Jr" / "model_0.obj")
    join, T_true = _join_rendered(mesh, 8)
    assert join.T_a_b is not None, join.reason
    D = join.T_a_b @ inv_T(T_true)
    assert rotation_angle_deg(D[:3, :3]) < WRONG_RENDERED[0] and np.linalg.norm(D[:3, 3]) < WRONG_RENDERED[1]


def test_a_print_alike_under_a_half_turn_is_never_joined():
    """A box printed alike under a half turn about its z axis, bottom included: the two motions it joins at are
    supported alike by every patch, and the capture is refused as ambiguous."""
    join, _ = _join_rendered(half_turn_box((0.14, 0.09, 0.07), seed=3)[0], 8)
    assert join.T_a_b is None and join.reason is not None and join.reason.startswith("ambiguous"), join.reason
