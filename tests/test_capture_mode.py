"""Capture-mode detection, background masks and keyframe selection on rendered captures."""
from __future__ import annotations

import numpy as np
import pytest

from gscan.io.camera import RGBDFrame
from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT, detect_mode, moving_object_masks
from gscan.scanning.keyframes import select_keyframes, view_direction
from gscan.synth import DEFAULT_INTRINSICS, box_mesh, procedural_box_texture, render_capture


@pytest.fixture(scope="module")
def box():
    return box_mesh((0.14, 0.09, 0.07), procedural_box_texture(3, (512, 768)))


def _frames(rendered, masks: bool) -> list[RGBDFrame]:
    return [RGBDFrame(f"{i:06d}", r.color, r.depth, DEFAULT_INTRINSICS, r.mask if masks else None)
            for i, r in enumerate(rendered)]


@pytest.mark.parametrize("masks", [False, True])
def test_static_and_turntable_are_told_apart(box, masks):
    static = render_capture(box, None, 8, mode="static", elevations_deg=(40.0,), seed=1)
    turn = render_capture(box, None, 8, mode="turntable", seed=1)
    d_static = detect_mode(_frames(static, masks))
    d_turn = detect_mode(_frames(turn, masks))
    # a static object: the background moves with the camera, so few of its pixels stay unchanged
    assert d_static.mode == STATIC_OBJECT and d_static.static_fraction < 0.3
    assert d_turn.mode == MOVING_OBJECT and d_turn.static_fraction > 0.7


def test_moving_object_masks_find_the_turning_object(box):
    turn = render_capture(box, None, 10, mode="turntable", seed=2)
    masks, planes = moving_object_masks(_frames(turn, False))
    assert all(p is not None and abs(p.normal[1]) > 0.5 for p in planes), planes  # the turntable, below the object
    ious = [(m & r.mask).sum() / (m | r.mask).sum() for m, r in zip(masks, turn, strict=True)]
    assert min(ious) > 0.8, ious


def test_keyframes_cover_directions_and_respect_the_cap():
    angles = np.radians(np.arange(0, 360, 5))  # 72 views on a ring, 5 degrees apart
    dirs = {i: np.array([np.cos(a), np.sin(a), 0.0]) for i, a in enumerate(angles)}
    kf = select_keyframes(dirs, min_angle_deg=12.0, max_views=100)
    assert kf[0] == 0 and len(kf) == 24  # every third view (15 degrees apart)
    for a in kf:
        for b in kf:
            if a != b:
                # keyframes at least 12 deg apart: arccos of float64 unit vectors, away from 0 (1e-9 deg for rounding)
                assert np.degrees(np.arccos(np.clip(dirs[a] @ dirs[b], -1, 1))) >= 12.0 - 1e-9
    capped = select_keyframes(dirs, min_angle_deg=12.0, max_views=10)
    assert 1 < len(capped) <= 10


def test_keyframes_of_a_short_sweep_are_the_views_with_object_keypoints():
    """A sideways sweep (optical axis fixed, 60 frames over 1.2 m at 1.8 m from the object: 37 deg of view
    direction) keeps at least min_views keyframes, each among the views with enough object keypoints; the
    optical axis alone would see one direction."""
    from gscan.geometry.transforms import look_at

    T_obj_cam = []
    for x in np.linspace(-0.6, 0.6, 60):
        T = look_at(np.array([x, -1.8, 0.5]), np.array([x, 0.0, 0.0]))  # every camera looks straight ahead
        T_obj_cam.append(T)
    assert all(np.allclose(T[:3, 2], T_obj_cam[0][:3, 2]) for T in T_obj_cam)
    dirs = {k: view_direction(T) for k, T in enumerate(T_obj_cam)}
    spread = np.degrees(np.arccos(np.clip(dirs[0] @ dirs[59], -1, 1)))
    assert 35 < spread < 40
    counts = {k: (5 if k % 3 == 0 else 100 + k) for k in dirs}  # every third view sees the object badly
    kf = select_keyframes(dirs, 12.0, 120, counts, min_keypoints=24, min_views=8)
    assert len(kf) >= 8 and all(counts[k] >= 24 for k in kf), kf
    assert select_keyframes(dirs, 12.0, 120, counts, min_keypoints=24, min_views=1) == sorted(
        select_keyframes(dirs, 12.0, 120, counts, min_keypoints=24, min_views=1))
    assert len(select_keyframes(dirs, 12.0, 120, counts, min_keypoints=24, min_views=1)) == 3  # 37 deg / 12 deg
    none_rich = {k: 3 if k > 1 else 30 for k in dirs}  # 2 views have enough, fewer than 8: all are candidates
    assert len(select_keyframes(dirs, 12.0, 120, none_rich, min_keypoints=24, min_views=8)) >= 8
    assert len(select_keyframes(dirs, 12.0, 5, counts, min_keypoints=24, min_views=8)) == 5  # the cap wins


def test_a_side_seen_only_by_poorly_supplied_views_keeps_keyframes():
    """Two rings of 12 views (an upright capture at elevation 30 deg, an upside-down one below the object): the
    upright ring's half on one side sees a plainly printed face (few object keypoints). More than min_views views
    are well supplied, yet that half keeps keyframes: no well-supplied view looks from there. A poorly supplied
    view next to a well-supplied one (within the angle) is still left out."""
    def ring(el_deg: float, az0: float) -> list[np.ndarray]:
        e = np.radians(el_deg)
        return [np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
                for a in np.radians(az0 + np.arange(0, 360, 30))]

    dirs = dict(enumerate(ring(-30.0, 0.0) + ring(30.0, 40.0)))
    counts = {k: (11 if k < 12 and dirs[k][0] < 0 else 60) for k in dirs}  # the -x half of the upright ring: poor
    kf = select_keyframes(dirs, 12.0, 120, counts, min_keypoints=24, min_views=8)
    assert sorted(kf) == sorted(dirs), kf  # every view: none lies within 12 deg of another
    poor = [k for k in kf if counts[k] < 24]
    assert len(poor) == sum(counts[k] < 24 for k in dirs) > 0
    near = dict(dirs)
    near[24] = dirs[0] + np.array([0.0, 0.05, 0.0])  # 3 deg from view 0, well supplied
    near[24] /= np.linalg.norm(near[24])
    counts[24] = 80
    counts[0] = 11  # view 0 poorly supplied now: view 24 covers its direction
    kf = select_keyframes(near, 12.0, 120, counts, min_keypoints=24, min_views=8)
    assert 24 in kf and 0 not in kf, kf
    # the well-supplied keyframes are chosen as without the poor views: 14 views 7 deg apart give 7 at 12 deg,
    # fewer than min_views, so the angle shrinks until all 14 are kept; a poor view far off is added to them
    arc = {k: np.array([np.cos(a), np.sin(a), 0.0]) for k, a in enumerate(np.radians(7.0 * np.arange(14)))}
    arc[14] = np.array([-1.0, 0.0, 0.0])
    kf = select_keyframes(arc, 12.0, 120, {k: 11 if k == 14 else 60 for k in arc}, min_keypoints=24, min_views=8)
    assert kf == list(range(15)), kf


def test_frames_without_the_object_are_nokeyframe_candidates():
    """A registered frame whose object mask is empty (a sweep that starts elsewhere) offers no keyframe: its stored
    object keypoints would be none, and the template its background; unregistered frames neither. With no frame
    showing the object, every registered frame is a candidate."""
    from gscan.scanning.keyframes import keyframe_candidates

    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, -1.0]
    empty, full = np.zeros((4, 4), bool), np.ones((4, 4), bool)
    def shows(masks):
        return lambda k: masks[k] is None or bool(masks[k].any())

    assert sorted(keyframe_candidates([T, T, None, T, T], shows([empty, full, full, None, empty]))) == [1, 3]
    assert sorted(keyframe_candidates([T, None, T], shows([empty, full, empty]))) == [0, 2]
    np.testing.assert_allclose(keyframe_candidates([T], shows([full]))[0], [0.0, 0.0, 1.0])
