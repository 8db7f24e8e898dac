"""Registration's acceptance against the evidence: a glossy bottle whose edges are each too loose to place a frame
alone, and two-frame captures of the shared meshes far apart (a held-out split, bench/acceptance.py's).

What is asked of a rule that follows the evidence: the bottle registers at least 90 % of its frames, the two-frame
captures at least 93 / 57 / 41 % of their pairs at 20 / 60 / 120 deg, none beyond 5 deg / 2 cm. The current rule
(a fixed bound on how tightly an edge pins its pose, gscan.registration.pairwise rule "weak geometry", with a
two-frame capture's lone edge refined on its pixels where its keypoints pin it loosely,
gscan.registration.photometric, and weighed against the object's half turns, gscan.registration.turns) does
not reach that; those tests are expected to fail (strict) until a rule does, and the tests that no frame or pair is
wrong must pass with any rule.
"""
from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from gscan.synth import cases as C
from tests._scan_checks import Outcome, scan_case

ROOT = Path(__file__).resolve().parents[1]
GAPS = (20.0, 60.0, 120.0)
EARLIER_SUCCESS = {20.0: 0.93, 60.0: 0.57, 120.0: 0.41}  # the rules before the fixed bound, on unseen objects


@pytest.fixture(scope="module")
def bottle(tmp_path_factory) -> Outcome:
    root = tmp_path_factory.mktemp("bottle")
    return scan_case(C.glossy_bottle_capture(root / "cap", n_views=36, seed=1), root / "bottle.gscan")


@pytest.mark.slow
def test_glossy_bottle_no_frame_wrong(bottle):
    """The bottle's edges claim a rotation sigma of 1.4-3.8 deg and are a median 3.3 deg off the truth (39 of 126
    beyond 5 deg, though they pass the depth and colour checks): pooled as if independent, they place 34 of the 36
    frames 19-49 deg off. No frame may be placed wrong; every unplaced frame says why."""
    bottle.check_reasons()
    assert not bottle.wrong, bottle.describe()


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="the fixed bound refuses the bottle's loose edges one at a time (1 of 36 "
                   "frames registered); pooling them as measured is not safe (34 of 36 wrong): keypoints whose "
                   "support crosses the bottle's static outline lag its turn (bench/bottle_edges.py). Its pixels "
                   "place each turn within 1.6 deg (tests/test_photometric.py), but a scan on them is a chain whose "
                   "ring no loop closes (a half turn of the 41 px wide bottle is not refuted: it has fewer than 60 "
                   "image keypoints and 8 textured 48 px tiles) and which drifts 1-2 deg: 6 of 26 frames wrong")
def test_glossy_bottle_registers_nine_in_ten(bottle):
    """At least 90 % of the bottle's 36 frames registered, none wrong."""
    assert len(bottle.registered) >= 0.9 * len(bottle.case.object_frames) and not bottle.wrong, bottle.describe()


@pytest.fixture(scope="module")
def pairs() -> dict[float, list[dict]]:
    """bench/acceptance.py's two-frame captures of the held-out meshes, plain table, object pixels, start 0."""
    sys.path.insert(0, str(ROOT / "bench"))
    from acceptance import run

    return run("held-out", [0.0], list(GAPS), "plain", masks=True)


def _right(r: dict) -> bool:
    from acceptance import is_right

    return is_right(r)


@pytest.mark.parametrize("split, name, azimuths, refused, off_deg", [
    ("held-out", "Frozen_Scrabble_Jr", (90.0, 210.0), "colour disagrees (sampled finely", 180.0),
    ("development", "Whey_Protein_Chocolate_12_Packets", (270.0, 390.0), "ambiguous shape: the only edge", 90.0),
])
def test_two_views_of_a_box_matched_at_its_turn_are_refused(split, name, azimuths, refused, off_deg):
    """Two views of a box whose sides look alike, object pixels, matched strongly at a turn of the truth (sigma
    0.2-0.3 deg, the depth check and the colour check of the default samples pass); the pair is the only evidence
    placing one view. Frozen Scrabble Jr (held out) from 90 and 210 deg, 180 deg off: its print, sampled finely,
    lines up in 7 of 35 tiles under the pose, and rule 3 refuses it (before, refused as ambiguous). Whey Protein
    (development) from 270 and 30 deg, 90 deg off: its print, sampled finely, refutes each of the object's half
    turns, but the quarter turn the pose is off by (the right pose) stands: refused, naming the quarter turn
    (weighing the half turns alone, the edge was accepted 90 deg off)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from acceptance import meshes
    from match import render_views

    from gscan.geometry.transforms import inv_T, pose_error
    from gscan.registration.frames import register_frames

    ms = meshes(split)
    seed = [m.name for m in ms].index(name)
    (a, T_world_a), (b, T_world_b) = render_views(ms[seed], list(azimuths), seed=seed, table_kind="plain")
    r = register_frames(a, b, use_masks=True)
    assert r.T_tgt_src is not None and r.reason is not None and r.reason.startswith(refused), r.reason
    assert off_deg == 180.0 or "quarter" in r.reason, r.reason
    deg, _ = pose_error(r.T_tgt_src, inv_T(T_world_b) @ T_world_a)
    assert abs(deg - off_deg) < 5.0  # the pose the rule refused is the wrong one


@pytest.mark.parametrize("azimuths", [(90.0, 110.0), (0.0, 20.0)])
def test_a_turn_of_a_printed_box_is_refuted_by_its_texture(azimuths):
    """Vans (held out), object pixels, the pose right in both pairs. From 90 and 110 deg its print, sampled finely,
    lines up in fewer than the 9 in 10 tiles that settle it, and the fine tiles leave the box's half turn about its
    second face axis standing (tiles across outlines and creases line up under a box's turn as under its pose); on
    the faces' interiors, where texture is print, the turn is refuted. From 0 and 20 deg, nearly edge on, the frames
    hold 50 and 71 image keypoints and the faces' interiors 7 tiles (no print), but the fine texture lines up in 18
    of 18 tiles under the pose and 0 of 12 under the half turn its shape fits, which it refutes. Both pairs
    registered (before, refused as ambiguous)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from acceptance import is_right, meshes
    from match import render_views

    from gscan.geometry.transforms import inv_T, pose_error
    from gscan.registration.frames import register_frames

    held = meshes("held-out")
    seed = [m.name for m in held].index("Vans_Cereal_Honey_Nut_Crunch_11_oz_box")
    (a, T_world_a), (b, T_world_b) = render_views(held[seed], list(azimuths), seed=seed, table_kind="plain")
    r = register_frames(a, b, use_masks=True)
    assert r.accepted, r.reason
    deg, m = pose_error(r.T_tgt_src, inv_T(T_world_b) @ T_world_a)
    assert is_right({"deg": deg, "m": m})


def test_two_whole_views_far_apart_are_placed_where_the_table_refutes_the_half_turns():
    """Crayola (held out) on a printed table seen whole from 0 and 120 deg: the object's half turns about axes
    along the table put the second camera under it (`support_plane`), and the turn about the table's normal lays
    the print off: the pose stands (without the table's plane the edge was refused as ambiguous). With the
    object's pixels alone there is no table. Clue (held out) on a plain table from 0 and 60 deg registers 1.2 deg
    / 21 mm off (claiming 0.14 deg): the table's plane would refute its turns, but its faint print does not
    confirm the pose, so the plane is not used and the edge stays refused."""
    sys.path.insert(0, str(ROOT / "bench"))
    from acceptance import is_right, meshes
    from match import render_views

    from gscan.geometry.symmetry import axis_rotation
    from gscan.geometry.transforms import inv_T, pose_error
    from gscan.registration.frames import register_frames
    from gscan.registration.turns import support_plane

    held = meshes("held-out")
    seed = [m.name for m in held].index("Crayola_Bonus_64_Crayons")
    (a, T_world_a), (b, T_world_b) = render_views(held[seed], [0.0, 120.0], seed=seed, table_kind="newspaper")
    T_gt = inv_T(T_world_b) @ T_world_a
    r = register_frames(a, b, use_masks=False)
    assert r.accepted, r.reason
    deg, m = pose_error(r.T_tgt_src, T_gt)
    assert is_right({"deg": deg, "m": m})

    from gscan.registration.dense import DenseGeometry
    from gscan.registration.pairwise import RegisterParams

    params = RegisterParams()
    whole = [DenseGeometry.from_depth(f.depth, f.intrinsics, image=f.color) for f in (a, b)]
    plane = support_plane(*whole, T_gt, params)
    assert plane is not None and plane.height(np.zeros(3)) > 0  # the normal towards src's camera
    assert plane.height(inv_T(T_gt)[:3, 3]) > 0  # both cameras above it
    along = np.cross(plane.normal, [1.0, 0.0, 0.0])  # an axis along the table, through its point below src's camera
    flip = axis_rotation(along / np.linalg.norm(along), -plane.offset * plane.normal, np.pi)
    assert plane.height(inv_T(T_gt @ flip)[:3, 3]) < 0  # the turn puts tgt's camera under the table
    masked = [DenseGeometry.from_depth(f.depth, f.intrinsics, f.mask) for f in (a, b)]
    assert support_plane(*masked, T_gt, params) is None
    seed = [m.name for m in held].index("Clue_Board_Game_Classic_Edition")
    (a, T_world_a), (b, T_world_b) = render_views(held[seed], [0.0, 60.0], seed=seed, table_kind="plain")
    r = register_frames(a, b, use_masks=False)
    assert r.T_tgt_src is not None and r.reason is not None
    assert r.reason.startswith("ambiguous shape: the only edge"), r.reason
    deg, m = pose_error(r.T_tgt_src, inv_T(T_world_b) @ T_world_a)
    assert not is_right({"deg": deg, "m": m})
    plain = [DenseGeometry.from_depth(f.depth, f.intrinsics, image=f.color) for f in (a, b)]
    assert support_plane(*plain, r.T_tgt_src, params) is None


def test_a_scan_of_two_frames_weighs_its_one_edge_against_the_half_turns(tmp_path):
    """Whey Protein's pack (development split) seen from 270 and 30 deg, given to `gscan.scan` as a capture of two
    frames: without the lone edge's weighing the scan registered the second frame 90 deg off (its texture lined up
    well enough); its one edge alone places that frame, so the scan weighs it as `register_frames` does and leaves
    the frame unregistered, with the reason."""
    sys.path.insert(0, str(ROOT / "bench"))
    from acceptance import meshes
    from match import render_views

    from gscan.geometry.transforms import inv_T
    from gscan.scanning.api import scan
    from gscan.synth import DEFAULT_INTRINSICS, load_textured_mesh, rest_on_table
    from gscan.synth.capture import write_capture

    dev = meshes("development")
    seed = [m.name for m in dev].index("Whey_Protein_Chocolate_12_Packets")
    T_world_obj = rest_on_table(load_textured_mesh(dev[seed] / "model_0.obj"))
    views = render_views(dev[seed], [270.0, 390.0], seed=seed, table_kind="plain")
    frames = [SimpleNamespace(color=f.color, depth=f.depth, mask=f.mask, T_cam_obj=inv_T(T) @ T_world_obj)
              for f, T in views]
    res = scan(write_capture(tmp_path / "cap", frames, DEFAULT_INTRINSICS), tmp_path / "two.gscan")
    assert res.unregistered == ["000001"], (res.registered, res.unregistered_reasons)
    assert "ambiguous shape: the only edge" in res.unregistered_reasons["000001"], res.unregistered_reasons


@pytest.mark.slow
def test_two_frame_captures_none_wrong(pairs):
    """No pair of the held-out split registered beyond 5 deg / 2 cm, at any gap."""
    wrong = [(g, r["mesh"], round(r["deg"], 1), round(r["m"], 3)) for g, rs in pairs.items() for r in rs
             if r["accepted"] and not _right(r)]
    assert not wrong, wrong


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="from start 0, 92 / 67 / 42 % (94 / 79 / 29 % on all four starts): at 20 "
                   "deg the Raisinets box seen nearly edge on has no print verdict (under 60 image keypoints, its "
                   "faces' interiors under 8 tiles), and a quarter turn that fits its shape stands: its fine "
                   "texture lines up in 3 of 7 tiles under it, too few tiles for a verdict")
def test_two_frame_captures_reach_the_earlier_success(pairs):
    """At each gap, at least the earlier rules' success on unseen objects (93 / 57 / 41 %)."""
    got = {g: float(np.mean([r["accepted"] and _right(r) for r in rs])) for g, rs in pairs.items()}
    assert all(got[g] >= EARLIER_SUCCESS[g] for g in GAPS), got
