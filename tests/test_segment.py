"""Object segmentation: support plane + component on single frames, working volume over a sequence."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.errors import InputError
from gscan.geometry.plane import Plane, ransac_plane
from gscan.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from gscan.io.camera import RGBDFrame
from gscan.scanning.segment import (
    ObjectHint,
    WorkingVolume,
    estimate_working_volume,
    fit_support_plane,
    object_hint,
    segment_frame,
    segment_in_volume,
    segment_sequence,
)
from gscan.synth import (
    DEFAULT_INTRINSICS,
    DepthNoise,
    SynthScene,
    box_mesh,
    orbit_poses,
    procedural_box_texture,
    rest_on_table,
)

INTR = DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240 keeps the test fast
# the synth's discontinuity test looks at 3x3 pixels: at half resolution the depth step across an
# oblique face doubles, so its relative jump threshold is doubled to keep such faces (as at 640 x 480)
NOISE = DepthNoise(edge_jump=0.04)
TARGET_SIZE = (0.12, 0.08, 0.10)


@pytest.fixture(scope="module")
def scene():
    """A printed box (target) and a distractor box 0.25 m away on a newspaper-textured table."""
    target = box_mesh(TARGET_SIZE, procedural_box_texture(1))
    distractor = box_mesh((0.06, 0.06, 0.14), procedural_box_texture(2), name="distractor")
    T_t = rest_on_table(target, rotvec_to_R(np.radians([0, 0, 20.0])))
    T_d = rest_on_table(distractor, None, (0.25, 0.05))
    sc = SynthScene([(target, T_t), (distractor, T_d)], seed=0, table_texture_size=1024)
    poses = orbit_poses(np.array([0.0, 0.0, 0.05]), 0.45, [30.0, 50.0], 4)
    renders = [sc.render(T, INTR, rng=np.random.default_rng(k), noise_params=NOISE) for k, T in enumerate(poses)]
    frames = [RGBDFrame(f"{k:06d}", r.color, r.depth, INTR) for k, r in enumerate(renders)]
    return frames, poses, renders, T_t


def iou_valid(mask: np.ndarray, r) -> float:
    """IoU with the ground-truth mask restricted to pixels with depth (no method can see depth holes)."""
    gt = r.mask & (r.depth > 0)
    return float((mask & gt).sum() / max((mask | gt).sum(), 1))


def test_single_frame_plane_segmentation(scene):
    frames, poses, renders, _ = scene
    for k in (0, 3, 5):
        seg = segment_frame(frames[k])
        assert seg.method == "plane" and seg.plane_cam is not None
        assert iou_valid(seg.mask, renders[k]) >= 0.9, k
        assert not np.any(seg.mask & (renders[k].labels == 1)), "distractor pixels in the mask"
        # plane: normal = world up in the camera frame, offset = camera height above the table
        up_cam = inv_T(poses[k])[:3, :3] @ np.array([0.0, 0.0, 1.0])
        # a RANSAC plane fitted to the noisy table: its normal within a degree of the truth
        assert np.degrees(np.arccos(np.clip(seg.plane_cam.normal @ up_cam, -1, 1))) < 1.0
        # its offset (the camera's height above the table) within 4 mm, a few times the depth noise
        assert seg.plane_cam.offset == pytest.approx(poses[k][2, 3], abs=0.004)
    # against the full ground-truth mask (depth holes included: the sensor model drops the silhouette
    # band and steep faces, no depth-based method can label those pixels) the IoU stays above 0.8
    for k in range(len(frames)):
        seg = segment_frame(frames[k])
        assert iou_valid(seg.mask, renders[k]) >= 0.95, k
        raw = (seg.mask & renders[k].mask).sum() / (seg.mask | renders[k].mask).sum()
        assert raw >= 0.8, (k, raw)


def test_sequence_segmentation_with_working_volume(scene):
    frames, poses, renders, T_t = scene
    segs, vol = segment_sequence(frames, poses)
    assert isinstance(vol, WorkingVolume)
    # the sequence's plane: normal within 0.01 (0.6 deg) of up
    np.testing.assert_allclose(vol.plane_world.normal, [0, 0, 1], atol=0.01)
    assert abs(vol.plane_world.offset) < 0.003  # and within 3 mm of the table's height
    centre_gt = T_t[:3, 3]
    # the working volume's centre on the object's footprint centre within 1.5 cm (the volume is centimetres wider than
    # the object)
    assert np.linalg.norm(vol.center_world[:2] - centre_gt[:2]) < 0.015
    half_diag = 0.5 * np.hypot(*TARGET_SIZE[:2])
    assert half_diag < vol.radius < half_diag + 0.04
    assert TARGET_SIZE[2] < vol.height < TARGET_SIZE[2] + 0.04
    for seg, r in zip(segs, renders, strict=True):
        assert seg.method == "volume"
        assert iou_valid(seg.mask, r) >= 0.9
        assert not np.any(seg.mask & (r.labels == 1))
        # per frame, the plane's normal within 0.01 (0.6 deg) of up
        assert np.allclose(seg.plane_cam.normal, inv_T(r.T_world_cam)[:3, :3] @ [0, 0, 1], atol=0.01)


def test_given_masks_win_and_unregistered_frames(scene):
    frames, poses, renders, _ = scene
    f = frames[2]
    given_mask = np.zeros(f.depth.shape, bool)
    given_mask[50:120, 100:200] = True
    seg = segment_frame(f, mask=given_mask)
    assert seg.method == "given"
    np.testing.assert_array_equal(seg.mask, given_mask)
    with pytest.raises(InputError):
        segment_frame(f, mask=given_mask[:-1])
    framed = RGBDFrame(f.name, f.color, f.depth, f.intrinsics, mask=given_mask)
    assert segment_frame(framed).method == "given"
    segs, _ = segment_sequence([frames[0], framed, frames[4]], [poses[0], poses[2], None])
    assert segs[1].method == "given" and not segs[2].mask.any() and segs[2].reason == "frame not registered"


def test_no_plane_falls_back_to_central_component():
    """Object floating in front of an empty background (no table): the central component."""
    target = box_mesh(TARGET_SIZE, procedural_box_texture(3))
    sc = SynthScene([(target, make_T(np.eye(3), [0, 0, 0.05]))], table=False, seed=1)
    T = orbit_poses(np.array([0.0, 0.0, 0.05]), 0.4, [20.0], 3)[0]
    r = sc.render(T, INTR, rng=np.random.default_rng(0), noise_params=NOISE)
    seg = segment_frame(RGBDFrame("x", r.color, r.depth, INTR))
    assert seg.method == "depth" and seg.plane_cam is None and seg.reason
    assert iou_valid(seg.mask, r) >= 0.9
    # a sequence without a plane falls back frame by frame
    segs, vol = segment_sequence([RGBDFrame("x", r.color, r.depth, INTR)], [T])
    assert vol is None and iou_valid(segs[0].mask, r) >= 0.9


def test_deterministic(scene):
    frames, poses, _, _ = scene
    a, b = segment_frame(frames[1]), segment_frame(frames[1])
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_array_equal(a.plane_cam.normal, b.plane_cam.normal)
    va = estimate_working_volume(frames, poses)
    vb = estimate_working_volume(frames, poses)
    np.testing.assert_array_equal(va.center_world, vb.center_world)
    assert va.radius == vb.radius


def test_fit_support_plane_rejects_clutter():
    rng = np.random.default_rng(0)
    assert fit_support_plane(rng.uniform(-0.3, 0.3, size=(5000, 3)) + [0, 0, 1.0], np.zeros(3)) is None
    pts = np.c_[rng.uniform(-0.3, 0.3, size=(4000, 2)), np.full(4000, 0.8)]
    plane = fit_support_plane(pts, np.zeros(3))
    np.testing.assert_allclose(plane.normal, [0, 0, -1], atol=1e-6)  # towards the viewpoint
    # 4000 exact points on z = 0.8: a least-squares fit exact to float64 rounding
    assert plane.offset == pytest.approx(0.8, abs=1e-6)


def test_ransac_plane_skips_a_face_with_points_behind_it():
    """A face seen head-on (600 points at z 0.5) outnumbers the table behind it (400 points at z 1.0):
    without `max_behind` the face wins, with it the table does (40 % of the points lie behind the face,
    none behind the table). Normals point to the viewpoint; inliers are exact; per-point distances work."""
    rng = np.random.default_rng(1)
    face = np.c_[rng.uniform(-0.05, 0.05, (600, 2)), np.full(600, 0.5)]
    table = np.c_[rng.uniform(-0.4, 0.4, (400, 2)), np.full(400, 1.0)]
    S = np.vstack([face, table])
    plane, inl = ransac_plane(S, 200, np.random.default_rng(0), 0.004, np.zeros(3))
    # exact points on the planes: the fitted normal to float64 rounding
    np.testing.assert_allclose(plane.normal, [0, 0, -1], atol=1e-9)
    # the 0.5 m face plane, exactly
    assert plane.offset == pytest.approx(0.5) and np.array_equal(inl, np.arange(1000) < 600)
    plane, inl = ransac_plane(S, 200, np.random.default_rng(0), np.full(1000, 0.004), np.zeros(3), max_behind=0.05)
    # exact points on the planes: the fitted normal to float64 rounding
    np.testing.assert_allclose(plane.normal, [0, 0, -1], atol=1e-9)
    # the 1.0 m table plane, exactly
    assert plane.offset == pytest.approx(1.0) and np.array_equal(inl, np.arange(1000) >= 600)
    line = np.c_[np.linspace(0, 1, 50), np.zeros(50), np.ones(50)]  # every triplet degenerate
    assert ransac_plane(line, 100, np.random.default_rng(0), 0.004, np.zeros(3)) is None
    # a convex ridge pointing at the camera: each face has more than 5 % of the points (the other face)
    # behind its plane, so no hypothesis qualifies and there is no plane (not the first one drawn)
    r = np.random.default_rng(0)
    x = np.r_[r.uniform(-0.3, 0.0, 700), r.uniform(0.0, 0.1, 300)]
    ridge = np.c_[x, r.uniform(-0.2, 0.2, 1000), 0.8 + 0.5 * np.abs(x)]
    assert ransac_plane(ridge, 64, np.random.default_rng(0), 0.006, np.zeros(3), max_behind=0.05) is None
    assert ransac_plane(ridge, 64, np.random.default_rng(0), 0.006, np.zeros(3)) is not None


@settings(deadline=None, max_examples=30)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6), st.floats(-1, 1))
def test_plane_transform_preserves_heights(v, off):
    n = np.array([0.2, -0.3, 0.9])
    plane = Plane(n / np.linalg.norm(n), off)
    T_b_a = make_T(rotvec_to_R(np.array(v[:3])), v[3:])
    pts_a = np.random.default_rng(0).normal(size=(20, 3))
    # heights kept by a rigid motion: float64 rounding of O(1) values
    np.testing.assert_allclose(plane.transformed(T_b_a).height(transform_points(T_b_a, pts_a)),
                               plane.height(pts_a), atol=1e-9)
    vol = WorkingVolume(plane, -plane.offset * plane.normal, 0.1, 0.2)
    inside = vol.center_world + 0.05 * plane.normal
    assert vol.contains(inside[None])[0] and not vol.contains((inside + 0.3 * plane.normal)[None])[0]


@pytest.mark.parametrize("stem", ["000001", "000002"])
def test_real_ycbv_frame(real_dir, stem):
    """Real cluttered table (YCB-Video): the mask lies on labelled objects and covers the central one."""
    import cv2
    import scipy.io as sio

    d = real_dir / "ycbv_frames" / "data"
    color = cv2.imread(str(d / f"{stem}-color.png"), cv2.IMREAD_COLOR)[..., ::-1].copy()
    depth = cv2.imread(str(d / f"{stem}-depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 10000.0
    labels = cv2.imread(str(d / f"{stem}-label.png"), cv2.IMREAD_UNCHANGED)
    K = sio.loadmat(str(d / f"{stem}-meta.mat"))["intrinsic_matrix"]
    from gscan.io.camera import Intrinsics

    intr = Intrinsics.from_matrix(K, color.shape[1], color.shape[0])
    seg = segment_frame(RGBDFrame(stem, color, depth, intr))
    assert seg.method == "plane"
    assert seg.plane_cam.normal[1] < -0.7  # the table faces the camera from below (OpenCV y down)
    lab = labels[seg.mask]
    assert (lab > 0).mean() > 0.95  # precision: the mask is on objects, not on the table
    ids, counts = np.unique(lab[lab > 0], return_counts=True)
    best = ids[np.argmax(counts)]
    assert counts.max() / (labels == best).sum() > 0.85  # the main object is covered


def test_working_volume_camera_fast_path_matches_world():
    rng = np.random.default_rng(1)
    n = np.array([0.1, 0.2, 0.95])
    plane = Plane(n / np.linalg.norm(n), -0.02)
    p = np.array([0.01, -0.02, 0.0])
    centre = p - plane.height(p[None])[0] * plane.normal  # on the plane
    vol = WorkingVolume(plane, centre, 0.08, 0.12)
    T_world_cam = make_T(rotvec_to_R(np.array([2.2, 0.3, -0.4])), [0.1, -0.3, 0.45])
    world = centre + rng.uniform(-0.15, 0.15, size=(2000, 3))
    pts_cam = transform_points(inv_T(T_world_cam), world).reshape(50, 40, 3)
    inside_w = vol.contains(world, 0.004).reshape(50, 40)
    inside_c = vol.contains_camera(pts_cam, T_world_cam, 0.004)
    assert inside_w.sum() > 50 and (~inside_w).sum() > 50
    assert (inside_w != inside_c).sum() <= 2  # float32 rounding at the boundary only


def test_turntable_sequence_in_object_frame():
    """Moving object, static camera: poses are camera-in-object; the table plane stays z = 0 there."""
    from gscan.synth import turntable_poses

    target = box_mesh(TARGET_SIZE, procedural_box_texture(4))
    distractor = box_mesh((0.06, 0.06, 0.14), procedural_box_texture(5), name="distractor")
    T_t = rest_on_table(target)
    sc = SynthScene([(target, T_t), (distractor, rest_on_table(distractor, None, (0.2, 0.15)))], seed=2,
                    table_texture_size=1024, wall_y=0.6)
    T_world_cam = orbit_poses(np.array([0.0, 0.0, 0.05]), 0.45, [35.0], 1)[0]
    spins = turntable_poses(T_t, target, 6)
    renders = [sc.render(T_world_cam, INTR, rng=np.random.default_rng(k), noise_params=NOISE,
                         T_world_obj_override=T) for k, T in enumerate(spins)]
    frames = [RGBDFrame(f"{k:06d}", r.color, r.depth, INTR) for k, r in enumerate(renders)]
    T_obj_cam = [inv_T(r.T_cam_obj) for r in renders]
    segs, vol = segment_sequence(frames, T_obj_cam)
    assert vol is not None
    for seg, r in zip(segs, renders, strict=True):
        assert iou_valid(seg.mask, r) >= 0.9
        assert not np.any(seg.mask & (r.labels == 1))


def _footprint_centre(T_world_obj: np.ndarray) -> np.ndarray:
    return T_world_obj[:2, 3]


def test_the_object_chosen_is_the_one_the_views_are_centred_on(scene):
    """The default choice says why: the target the orbit looks at, at the centre of every view, standing on the
    table, its footprint and height those of the box (within the volume's margin and the depth noise)."""
    frames, poses, _, T_t = scene
    vol = estimate_working_volume(frames, poses)
    assert vol is not None and vol.chosen is not None
    c = vol.chosen
    assert c.by == "fixation" and c.on_support and c.centre_share == 1.0, c
    assert c.fixation_m is not None and c.fixation_m < 0.05, c
    length, width, height = c.size_m
    diag = np.hypot(*TARGET_SIZE[:2])
    assert TARGET_SIZE[0] - 0.02 < length < diag + 0.02 and TARGET_SIZE[1] - 0.02 < width < diag, c
    assert abs(height - TARGET_SIZE[2]) < 0.02, c
    assert c.to_json()["by"] == "fixation" and c.reason


def test_a_larger_structure_at_the_edge_of_the_views_is_not_chosen():
    """A tall panel at the table's edge, larger than the target and in most views, but at their edge: the
    target the views are centred on is chosen."""
    target = box_mesh(TARGET_SIZE, procedural_box_texture(6))
    panel = box_mesh((0.40, 0.06, 0.30), procedural_box_texture(7), name="panel")
    T_t = rest_on_table(target)
    sc = SynthScene([(target, T_t), (panel, rest_on_table(panel, None, (0.0, 0.30)))], seed=3,
                    table_texture_size=1024)
    poses = orbit_poses(np.array([0.0, 0.0, 0.05]), 0.5, [35.0], 6, azimuth0_deg=200.0)
    poses = [T for T in poses if T[1, 3] < 0.2]  # the panel never between the camera and the target
    renders = [sc.render(T, INTR, rng=np.random.default_rng(k), noise_params=NOISE) for k, T in enumerate(poses)]
    frames = [RGBDFrame(f"{k:06d}", r.color, r.depth, INTR) for k, r in enumerate(renders)]
    assert sum((r.labels == 1).sum() > (r.labels == 0).sum() for r in renders) >= 1  # the panel is the larger
    vol = estimate_working_volume(frames, poses)
    assert vol is not None and vol.chosen is not None
    assert np.linalg.norm(vol.center_world[:2] - T_t[:2, 3]) < 0.02, (vol.center_world, vol.chosen)
    assert vol.radius < 0.15


@pytest.mark.parametrize("by", ["roi", "mask"])
def test_roi_and_mask_choose_the_object_inside_them(scene, tmp_path, by):
    """A box or a mask around the distractor in the first frame: the distractor is chosen, not the target the
    views are centred on; the volume's centre projects inside the box."""
    frames, poses, renders, _ = scene
    sel = renders[0].labels == 1
    ys, xs = np.nonzero(sel)
    x0, y0 = max(0, int(xs.min()) - 3), max(0, int(ys.min()) - 3)
    roi = (x0, y0, min(INTR.width, int(xs.max()) + 4) - x0, min(INTR.height, int(ys.max()) + 4) - y0)
    if by == "roi":
        hint = object_hint(roi, None, frames[0], tmp_path)
    else:
        import cv2

        cv2.imwrite(str(tmp_path / "m.png"), sel.astype(np.uint8) * 255)
        hint = object_hint(None, tmp_path / "m.png", frames[0], tmp_path)
    assert isinstance(hint, ObjectHint) and hint.by == by
    vol = estimate_working_volume(frames, poses, hint=hint)
    assert vol is not None and vol.chosen is not None and vol.chosen.by == by
    # the distractor (0.06 x 0.06 x 0.14 m at (0.25, 0.05)): the volume's centre on its footprint, and the first
    # frame's mask inside the box and on the distractor
    assert np.linalg.norm(vol.center_world[:2] - [0.25, 0.05]) < 0.015, vol.center_world
    m = segment_in_volume(frames[0], poses[0], vol).mask
    x, y, w, h = roi
    in_box = np.zeros_like(m)
    in_box[y:y + h, x:x + w] = True
    assert m.sum() > 100 and (m & in_box).sum() >= 0.95 * m.sum() and iou_valid(m, renders[0]) < 0.05
    assert (m & sel).sum() >= 0.8 * (sel & (frames[0].depth > 0)).sum()
    segs = segment_sequence(frames, poses)[0]  # without a hint: the target
    assert not np.any(segs[0].mask & sel)


def test_object_hint_rejects_bad_boxes_and_masks(scene, tmp_path):
    """A box outside the image, an empty mask, a mask of another size, no file: InputError whose fix names
    the option."""
    import cv2

    frame = scene[0][0]
    H, W = frame.depth.shape
    for roi in ((W - 10, 0, 20, 20), (0, 0, W + 1, H), (W + 5, H + 5, 10, 10)):
        with pytest.raises(InputError) as e:
            object_hint(roi, None, frame, tmp_path)
        assert e.value.fix == "roi" and str(W) in str(e.value)
    cv2.imwrite(str(tmp_path / "empty.png"), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(tmp_path / "big.png"), np.full((2 * H, 2 * W), 255, np.uint8))
    for name, words in (("empty.png", "empty"), ("big.png", f"{2 * W} x {2 * H}"), ("none.png", "not a file")):
        with pytest.raises(InputError) as e:
            object_hint(None, tmp_path / name, frame, tmp_path)
        assert e.value.fix == "mask" and words in str(e.value) and name in str(e.value)
    assert object_hint(None, None, frame, tmp_path) is None


def test_a_sweep_past_a_table_keeps_the_table_and_what_stands_on_it(scene):
    """Cameras passing sideways along the table, looking past the two boxes at its far side: neither box is at the
    centre of half the views, so the object is the table surface with both boxes on it (the volume holds both
    and reaches just below the surface), and it says so."""
    from gscan.geometry.transforms import look_at

    target = box_mesh(TARGET_SIZE, procedural_box_texture(1))
    distractor = box_mesh((0.06, 0.06, 0.14), procedural_box_texture(2), name="distractor")
    T_t = rest_on_table(target)
    T_d = rest_on_table(distractor, None, (0.25, 0.05))
    sc = SynthScene([(target, T_t), (distractor, T_d)], seed=4, table_texture_size=1024)
    poses = [look_at(np.array([x, -0.45, 0.40]), np.array([x, 0.5, 0.0])) for x in np.linspace(-0.25, 0.45, 6)]
    renders = [sc.render(T, INTR, rng=np.random.default_rng(k), noise_params=NOISE) for k, T in enumerate(poses)]
    frames = [RGBDFrame(f"{k:06d}", r.color, r.depth, INTR) for k, r in enumerate(renders)]
    vol = estimate_working_volume(frames, poses)
    assert vol is not None and vol.chosen is not None
    assert vol.chosen.by == "fixation" and "surface" in vol.chosen.reason, vol.chosen
    assert vol.footprint is not None and vol.height_min < 0
    for T in (T_t, T_d):
        assert vol.contains(T[:3, 3][None] + [0, 0, 0.03])[0], (T[:3, 3], vol)


@pytest.mark.slow
def test_scan_with_a_box_keeps_the_object_inside_it(scene, tmp_path):
    """The pipeline end to end: `scan` with `roi` around the distractor in the first frame fuses the distractor
    (0.06 x 0.06 x 0.14 m), not the target the orbit looks at (0.12 x 0.08 x 0.10 m), and says so in its result
    and in the template (`info --json`)."""
    from gscan.scanning.api import scan
    from gscan.scanning.options import ScanOptions
    from gscan.synth.capture import write_capture
    from gscan.template.reports import template_info

    _, _, renders, _ = scene
    cap = write_capture(tmp_path / "cap", renders, INTR, write_masks=False)
    sel = renders[0].labels == 1
    ys, xs = np.nonzero(sel)
    roi = (int(xs.min()), int(ys.min()), int(xs.max() - xs.min()) + 1, int(ys.max() - ys.min()) + 1)
    res = scan(cap, tmp_path / "d.gscan", ScanOptions(roi=roi))
    assert res.object is not None and res.object["by"] == "roi", res.object
    info = template_info(tmp_path / "d.gscan")
    assert info.object == res.object
    assert 0.12 < res.object["size_m"][2] < 0.17 and res.object["size_m"][0] < 0.10, res.object
    assert max(info.summary.extent_m) < 0.19 and sorted(info.summary.extent_m)[1] < 0.10, info.summary.extent_m
