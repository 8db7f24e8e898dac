"""gscan.io.camera (pinhole model, back-projection, keypoint lifting, intrinsics files) and
gscan.geometry.transforms (SE(3) helpers, Kabsch, look_at)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.errors import InputError
from gscan.geometry.kabsch import kabsch, kabsch_trimmed, leave_one_out_residuals
from gscan.geometry.transforms import inv_T, look_at, make_T, pose_error, rotvec_to_R, transform_points
from gscan.io.camera import (
    DepthCamera,
    Intrinsics,
    RGBDFrame,
    backproject,
    backproject_pixels,
    lift_keypoints,
    load_depth_camera,
    load_intrinsics,
    pixel_rays,
    point_cloud,
    project,
)

finite = {"allow_nan": False, "allow_infinity": False}


@pytest.fixture(scope="module")
def o3d_root(real_dir: Path) -> Path:
    root = real_dir / "open3d_rgbd"
    if not (root / "camera_primesense.json").is_file():
        pytest.fail(f"Open3D RGB-D test frames missing under {root}")
    return root


# ---------------------------------------------------------------- back-projection vs open3d

@pytest.mark.parametrize("idx", [0, 3])
def test_backproject_matches_open3d(o3d_root, idx):
    import open3d as o3d

    intr = load_intrinsics(o3d_root / "camera_primesense.json")
    depth_mm = cv2.imread(str(o3d_root / "RGBD" / "depth" / f"{idx:05d}.png"), cv2.IMREAD_UNCHANGED)
    assert depth_mm.dtype == np.uint16 and depth_mm.shape == (intr.height, intr.width)
    o3d_intr = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    pc = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.geometry.Image(depth_mm), o3d_intr, np.eye(4), depth_scale=1000.0, depth_trunc=1e6, stride=1,
        project_valid_depth_only=True)
    ref = np.asarray(pc.points)
    depth = depth_mm.astype(np.float32) / 1000.0
    ours = backproject(depth, intr)[depth > 0]  # row-major valid pixels, same order as open3d
    assert len(ref) == len(ours) > 100000
    # float32 depth and rays: relative rounding 6e-8 at ~3 m depth is 2e-7 m; 1e-5 m leaves 50x
    assert np.abs(ours - ref).max() < 1e-5
    frame = RGBDFrame("f", np.zeros((*depth.shape, 3), np.uint8), depth, intr)
    pts, cols = point_cloud(frame)
    np.testing.assert_array_equal(pts, ours)
    assert cols.shape == pts.shape
    pts2, _ = point_cloud(frame, stride=2)
    np.testing.assert_array_equal(pts2, backproject(depth, intr)[::2, ::2][depth[::2, ::2] > 0])


def test_pixel_rays_convention():
    intr = Intrinsics(100.0, 200.0, 1.5, 0.5, 4, 2)
    r = pixel_rays(intr)
    assert r.shape == (2, 4, 3)
    np.testing.assert_allclose(r[0, 0], [-1.5 / 100, -0.5 / 200, 1.0])  # centre of the top-left pixel is (0, 0)
    # exact binary fractions except /100 and /200, within assert_allclose's rtol 1e-7
    np.testing.assert_allclose(r[1, 3], [1.5 / 100, 0.5 / 200, 1.0])


# ---------------------------------------------------------------- round trips

intrinsics_st = st.builds(
    Intrinsics, st.floats(50.0, 2000.0), st.floats(50.0, 2000.0), st.floats(0.0, 1000.0), st.floats(0.0, 1000.0),
    st.integers(16, 2000), st.integers(16, 2000))


@settings(max_examples=60, deadline=None)
@given(intrinsics_st, st.integers(0, 2**32 - 1))
def test_project_backproject_round_trip(intr, seed):
    rng = np.random.default_rng(seed)
    px = rng.uniform([0, 0], [intr.width, intr.height], size=(50, 2))
    z = rng.uniform(0.1, 10.0, size=50)
    P = backproject_pixels(px, z, intr)
    # z copied through one product and division by 1 (rtol 1e-7 covers float64 rounding)
    np.testing.assert_allclose(P[:, 2], z)
    # project(backproject(px)) in float64: ~1e-13 px of rounding at 10 m; 1e-8 px leaves 1e5x
    np.testing.assert_allclose(project(P, intr), px, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(intrinsics_st, st.sampled_from([0.25, 0.5, 2.0, 4.0]))
def test_intrinsics_scaled_round_trip(intr, s):
    back = intr.scaled(s).scaled(1.0 / s)
    for a in ("fx", "fy", "cx", "cy"):
        # scaling by s then 1/s: two float64 roundings, ~1e-16 relative
        assert getattr(back, a) == pytest.approx(getattr(intr, a), rel=1e-12, abs=1e-9)
    # pixel-centre convention: the point at a scaled pixel centre projects to the matching location
    sc = intr.scaled(s)
    P = backproject_pixels(np.array([[3.0, 7.0]]), np.array([2.0]), intr)
    # float64 products of numbers below 1e3: rounding ~1e-13 px
    np.testing.assert_allclose(project(P, sc), [[(3.0 + 0.5) * s - 0.5, (7.0 + 0.5) * s - 0.5]], atol=1e-9)
    if (intr.width * s).is_integer() and (intr.height * s).is_integer():
        assert (back.width, back.height) == (intr.width, intr.height)
    assert Intrinsics.from_dict(intr.to_dict()) == intr
    assert Intrinsics.from_matrix(intr.K, intr.width, intr.height) == intr


def test_intrinsics_validation():
    with pytest.raises(ValueError):
        Intrinsics(-1.0, 1.0, 0.0, 0.0, 10, 10)
    with pytest.raises(ValueError):
        Intrinsics(1.0, 1.0, float("nan"), 0.0, 10, 10)
    with pytest.raises(ValueError):
        Intrinsics(1.0, 1.0, 0.0, 0.0, 0, 10)


# ---------------------------------------------------------------- geometry

def _rigid(rng: np.random.Generator) -> np.ndarray:
    return make_T(rotvec_to_R(rng.normal(size=3) * rng.uniform(0, 3)), rng.normal(size=3))


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_inv_T_and_kabsch_exact(seed):
    rng = np.random.default_rng(seed)
    T = _rigid(rng)
    # 4x4 products of O(1) entries: float64 rounding ~1e-16; 1e-12 leaves 1e4x
    np.testing.assert_allclose(inv_T(T) @ T, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(T @ inv_T(T), np.eye(4), atol=1e-12)
    src = rng.normal(size=(int(rng.integers(3, 60)), 3))
    dst = transform_points(T, src)
    T_est = kabsch(src, dst)
    # Kabsch by SVD on exact data: rounding grows with the points' conditioning (>= 3 random points), ~1e-13; 1e-9
    # leaves room for any BLAS or LAPACK
    np.testing.assert_allclose(T_est, T, atol=1e-9)
    # det of a float64 rotation: ~1e-15 off 1; approx's default rel 1e-6
    assert np.linalg.det(T_est[:3, :3]) == pytest.approx(1.0)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 4))
def test_kabsch_trimmed_drops_a_minority_of_gross_outliers(seed, n_out):
    """0.1 m-scale points, 1 mm noise, n_out pairs moved 5-40 cm: the pose is the inliers' Kabsch."""
    rng = np.random.default_rng(seed)
    T = _rigid(rng)
    src = rng.uniform(-0.1, 0.1, size=(24, 3))
    dst = transform_points(T, src) + rng.normal(0, 0.001, size=src.shape)
    bad = rng.choice(24, n_out, replace=False)
    away = rng.normal(size=(n_out, 3))
    dst[bad] += away / np.linalg.norm(away, axis=1, keepdims=True) * rng.uniform(0.05, 0.4, (n_out, 1))
    T_est, keep = kabsch_trimmed(src, dst, 0.008)
    assert not keep[bad].any() and keep.sum() >= 24 - n_out - 1
    # the same Kabsch on the same kept points: equal up to the order of float64 sums (~1e-15)
    np.testing.assert_allclose(T_est, kabsch(src[keep], dst[keep]), atol=1e-12)
    deg, m = pose_error(T_est, T)
    # 1 mm noise on 24 points 0.2 m across: the fit is good to ~0.1 deg / 0.5 mm; 1 deg / 3 mm catch a wrong trim
    assert deg < 1.0 and m < 0.003
    if n_out == 0:  # nothing trimmed: plain Kabsch
        assert keep.all()


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_kabsch_trimmed_catches_a_high_leverage_pair(seed):
    """23 pairs in a 3 cm patch plus one 20 cm away and 14 mm off: it tilts plain Kabsch by degrees
    while fitting within a few mm itself; the leave-one-out pass drops it."""
    rng = np.random.default_rng(seed)
    T = _rigid(rng)
    src = np.vstack([rng.uniform(-0.015, 0.015, size=(23, 3)), [[0.2, 0.0, 0.0]]])
    dst = transform_points(T, src) + rng.normal(0, 0.0001, size=src.shape)
    dst[23] += 0.014 * np.array([0.0, 0.0, 1.0]) @ T[:3, :3].T
    T_est, keep = kabsch_trimmed(src, dst, 0.008)
    assert not keep[23] and keep[:23].sum() >= 22
    # the same Kabsch on the same kept points: equal up to the order of float64 sums (~1e-15)
    np.testing.assert_allclose(T_est, kabsch(src[keep], dst[keep]), atol=1e-12)
    assert pose_error(T_est, T)[0] < pose_error(kabsch(src, dst), T)[0] / 2


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(4, 30))
def test_leave_one_out_residuals_equal_n_separate_fits(seed, n):
    """The batched leave-one-out residuals equal N separate Kabsch fits, reflection-prone layouts included."""
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * [0.1, 0.1, rng.choice([0.1, 1e-4])]  # sometimes near-planar
    dst = transform_points(_rigid(rng), src) + rng.normal(0, rng.choice([0.001, 0.1]), size=src.shape)
    dst[: n // 3] = dst[: n // 3] * [1.0, 1.0, -1.0]  # a mirrored part: some fits need the reflection guard
    ref = [np.linalg.norm(transform_points(kabsch(np.delete(src, k, 0), np.delete(dst, k, 0)), src[k][None])[0]
                          - dst[k]) for k in range(n)]
    # each residual from its own SVD on the same data: float64 rounding amplified by conditioning, ~1e-12
    np.testing.assert_allclose(leave_one_out_residuals(src, dst), ref, atol=1e-9)
    with pytest.raises(ValueError):  # fewer than 4 pairs leaves fits of fewer than 3
        leave_one_out_residuals(src[:3], dst[:3])


def test_kabsch_trimmed_keeps_only_a_consistent_subset_when_no_majority_agrees():
    rng = np.random.default_rng(3)
    src = rng.uniform(-0.1, 0.1, size=(10, 3))
    dst = rng.uniform(-0.1, 0.1, size=(10, 3))  # unrelated: no consistent majority
    T_est, keep = kabsch_trimmed(src, dst, 0.008)
    assert keep.sum() == 3  # the winning triple alone: too few for registration's rule 1
    # the same Kabsch on the same kept points: equal up to the order of float64 sums (~1e-15)
    np.testing.assert_allclose(T_est, kabsch(src[keep], dst[keep]), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_kabsch_trimmed_survives_a_distant_pair_far_off(seed):
    """A whole-frame list as on a rendered pair (plain table, 60 deg): 14 pairs on the object (a 30 x 16 x 8 cm
    box 1 m away, 1.5 mm noise) and one on the background 0.8-1 m from them, 25-40 cm off. That pair drags
    plain Kabsch so far that true pairs have the largest residuals: dropping the worst first ran down to the
    floor and fell back to all pairs (19 deg on the rendered pair); the triple consensus keeps the 14."""
    rng = np.random.default_rng(seed)
    T = _rigid(rng)
    src = rng.uniform([-0.15, -0.08, 0.96], [0.15, 0.08, 1.04], size=(15, 3))
    far = rng.normal(size=3)
    src[10] = src.mean(0) + far / np.linalg.norm(far) * rng.uniform(0.8, 1.0)
    dst = transform_points(T, src) + rng.normal(0, 0.0015, size=src.shape)
    away = rng.normal(size=3)
    dst[10] += away / np.linalg.norm(away) * rng.uniform(0.25, 0.4)
    T_est, keep = kabsch_trimmed(src, dst, 0.008)
    assert not keep[10] and keep.sum() >= 13
    deg, m = pose_error(T_est, T)
    assert deg < 2.0 and m < 0.03  # m: at the camera origin, 1 m from the points


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(4, 32), st.integers(1, 3))
def test_consensus_kernel_poses_a_clean_triple_exactly(seed, n, n_out):
    """Noise-free pairs under a rigid motion plus n_out pairs moved 5-40 cm: the best triple is a triple of
    inliers and its triad pose is the motion itself."""
    from gscan.geometry.consensus_kernel import best_triple

    rng = np.random.default_rng(seed)
    T = _rigid(rng)
    src = rng.uniform(-0.1, 0.1, size=(n, 3))
    dst = transform_points(T, src)
    bad = rng.choice(n, min(n_out, n - 3), replace=False)
    away = rng.normal(size=(len(bad), 3))
    dst[bad] += away / np.linalg.norm(away, axis=1, keepdims=True) * rng.uniform(0.05, 0.4, (len(bad), 1))
    i, j, k, T_tri = best_triple(src, dst, n, np.full(n, 0.008), 0.1)
    assert not {i, j, k} & set(bad.tolist())
    # a pose from three exact points: an SVD of a 3-point cross-covariance, ~1e-12; 1e-9 leaves 1000x
    np.testing.assert_allclose(T_tri, T, atol=1e-9)


def test_kabsch_trimmed_with_only_collinear_triples_is_plain_kabsch():
    rng = np.random.default_rng(5)
    # four pairs on a line (too few for the leave-one-out step): every triple is degenerate, one pair is off
    src = np.outer(np.linspace(0.0, 0.2, 4), [1.0, 0.5, 0.2])
    dst = transform_points(_rigid(rng), src)
    dst[2] += 0.1
    T_est, keep = kabsch_trimmed(src, dst, 0.008)
    assert keep.all()
    # the same Kabsch on the same points: equal up to the order of float64 sums (~1e-15)
    np.testing.assert_allclose(T_est, kabsch(src, dst), atol=1e-12)


def test_kabsch_trimmed_on_the_rendered_whole_frame_list():
    """GMatch's 15-pair list on a rendered pair (Diet Pepsi, plain table, start azimuth 270, 60 deg; mm,
    rounded): pair 10 lies on the background, 36 cm off; the others within 7 mm. Worst-first trimming
    gave 19 deg (all pairs, after hitting the floor)."""
    src = np.array([[85, -25, 976], [148, -10, 964], [-21, -11, 962], [176, -22, 976], [-90, -67, 1021],
                    [179, 74, 1030], [-86, -53, 1005], [-16, 40, 1000], [185, -24, 980], [115, -84, 1045],
                    [-743, -253, 1456], [132, -22, 975], [51, 40, 998], [70, -16, 965], [142, -22, 975]]) / 1e3
    dst = np.array([[9, 10, 933], [24, 53, 888], [-61, -42, 997], [52, 63, 873], [-27, -110, 1070],
                    [35, 152, 934], [-42, -100, 1060], [-62, 13, 1033], [60, 67, 870], [106, -3, 950],
                    [388, -461, 1703], [29, 37, 903], [-28, 51, 989], [-12, 12, 936], [35, 44, 898]]) / 1e3
    T_gt = np.array([[0.5, -0.55667, 0.663414, -0.695759], [0.55667, 0.793412, 0.246202, -0.258206],
                     [-0.663414, 0.246202, 0.706588, 0.307717], [0.0, 0.0, 0.0, 1.0]])
    T_est, keep = kabsch_trimmed(src, dst, 0.008)
    assert not keep[10] and keep.sum() >= 13
    deg, m = pose_error(T_est, T_gt)
    # the 14 true pairs lie within 7 mm of the true motion, so their fit is within tenths of a degree and a few
    # millimetres; 0.5 deg / 1 cm catch a wrong trim (19 deg before)
    assert deg < 0.5 and m < 0.01


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_kabsch_never_returns_a_reflection(seed):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(20, 3))
    dst = transform_points(_rigid(rng), src * np.array([-1.0, 1.0, 1.0]))  # mirrored copy
    R = kabsch(src, dst)[:3, :3]
    # an SVD's rotation is orthonormal to float64 rounding (~1e-15); 1e-9 for any LAPACK
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-5, 5, **finite), min_size=3, max_size=3),
       st.lists(st.floats(-5, 5, **finite), min_size=3, max_size=3))
def test_look_at_is_a_proper_rotation_looking_at_the_target(eye, target):
    eye, target = np.array(eye), np.array(target)
    if np.linalg.norm(target - eye) < 1e-3:
        return
    T = look_at(eye, target)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, 3], eye)  # eye copied into the translation: exact up to rtol 1e-7
    p_cam = transform_points(inv_T(T), target[None])[0]  # the target sits on the optical axis, in front
    # distances of O(1) in float64: approx's default rel 1e-6 is far above their rounding
    assert p_cam[2] == pytest.approx(np.linalg.norm(target - eye))
    # on the axis up to float64 rounding of the rotation (~1e-15 of the distance)
    np.testing.assert_allclose(p_cam[:2], 0.0, atol=1e-9)
    assert R[:, 1] @ np.array([0.0, 0.0, 1.0]) <= 1e-9  # image y (down) never points up in the world


def test_look_at_horizontal_has_world_up_as_image_up():
    T = look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(T[:3, 1], [0.0, 0.0, -1.0], atol=1e-12)  # y down
    np.testing.assert_allclose(T[:3, 0], [0.0, -1.0, 0.0], atol=1e-12)  # x right


# ---------------------------------------------------------------- lift_keypoints

INTR = Intrinsics(500.0, 500.0, 31.5, 23.5, 64, 48)


def test_lift_rejects_invalid_depth():
    depth = np.full((48, 64), 1.5, np.float32)
    depth[:, 32:] = 0.0
    px = np.array([[10.0, 20.0], [50.0, 20.0], [31.0, 20.0], [33.0, 20.0], [30.0, 10.0]])
    pts, ok = lift_keypoints(px, depth, INTR, window=2)
    # u=31: 3 of 5 columns valid (60 %) -> kept; u=33: 1 of 5 -> rejected
    np.testing.assert_array_equal(ok, [True, False, True, False, True])
    np.testing.assert_allclose(pts[ok][:, 2], 1.5)  # depth 1.5 copied from a float32 image in which 1.5 is exact
    np.testing.assert_array_equal(pts[~ok], 0.0)
    # the same backprojection of the same depth: equal to float64 rounding (rtol 1e-7)
    np.testing.assert_allclose(pts[ok], backproject_pixels(px[ok], np.full(3, 1.5), INTR))
    _, ok = lift_keypoints(np.zeros((0, 2)), depth, INTR)
    assert ok.shape == (0,)


def test_lift_rejects_pixels_outside_the_image_and_nan():
    depth = np.full((48, 64), 1.0, np.float32)
    px = np.array([[-5.0, 10.0], [70.0, 10.0], [10.0, 48.0], [np.nan, 3.0], [0.0, 0.0], [63.4, 47.4]])
    _, ok = lift_keypoints(px, depth, INTR, window=1, min_valid_frac=0.4)
    np.testing.assert_array_equal(ok, [False, False, False, False, True, True])


def test_lift_rejects_depth_discontinuities():
    depth = np.full((48, 64), 1.0, np.float32)
    depth[:, 32:] = 1.3  # a step of 30 cm between columns 31 and 32
    u = np.arange(20.0, 45.0)
    px = np.stack([u, np.full_like(u, 24.0)], 1)
    pts, ok = lift_keypoints(px, depth, INTR, window=2)
    straddles = (u + 2 >= 32) & (u - 2 <= 31)
    np.testing.assert_array_equal(ok, ~straddles)
    # float32 depths 1.0 and 1.3 (1.3 is rounded to 6e-8 relative): rtol 1e-6 = 16 float32 ulps
    np.testing.assert_allclose(pts[ok][:, 2], np.where(u[ok] < 32, 1.0, 1.3), rtol=1e-6)
    # a gentle slant (1 mm per pixel) is not a discontinuity
    slant = (1.0 + 0.001 * np.arange(64, dtype=np.float32))[None, :].repeat(48, 0)
    pts, ok = lift_keypoints(px, slant, INTR, window=2)
    assert ok.all()
    np.testing.assert_allclose(pts[:, 2], 1.0 + 0.001 * u, rtol=1e-6)  # median of a linear window = centre


def test_lift_takes_the_median_despite_corrupted_pixels():
    depth = np.full((48, 64), 0.8, np.float32)
    v, u = 20, 30
    depth[v - 2, u - 2] = 5.0  # two far spikes
    depth[v + 1, u + 2] = 4.0
    depth[v + 2, u] = 0.3  # one near spike
    depth[v - 1, u - 1:u + 2] = 0.0  # three holes
    pts, ok = lift_keypoints(np.array([[u, v]], float), depth, INTR, window=2)
    assert ok[0]
    # a median of float32 0.8 values: 0.8 to float32 rounding (1e-8), within approx's rel 1e-6
    assert pts[0, 2] == pytest.approx(0.8)
    # many spikes: the window straddles two surfaces and is rejected rather than guessed
    depth[v - 2:v + 3, u + 1:u + 3] = 3.0
    _, ok = lift_keypoints(np.array([[u, v]], float), depth, INTR, window=2)
    assert not ok[0]


@given(seed=st.integers(0, 10_000), r=st.integers(0, 3))
@settings(max_examples=60, deadline=None)
def test_lift_window_statistics_are_numpys_percentiles(seed, r):
    """The lift's window statistics (median, 10th and 90th percentiles of the valid depths around a pixel, and
    their count) are numpy's linear percentiles of those depths, windows at the image border and with ties
    included."""
    from gscan.io.lift_kernel import window_stats

    rng = np.random.default_rng(seed)
    H, W = rng.integers(1, 12, 2)
    depth = rng.uniform(0.3, 2.0, (H, W)).astype(np.float32)
    if seed % 2:
        depth = np.round(depth, 1)  # ties
    depth[rng.random((H, W)) < rng.uniform(0.0, 0.8)] = 0.0
    u, v = rng.integers(0, W, 40), rng.integers(0, H, 40)
    med, lo, hi = np.empty(40), np.empty(40), np.empty(40)
    count = np.empty(40, np.int64)
    window_stats(depth, u, v, r, med, lo, hi, count)
    for k in range(40):
        win = depth[max(0, v[k] - r):v[k] + r + 1, max(0, u[k] - r):u[k] + r + 1].astype(np.float64)
        vals = win[win > 0]
        assert count[k] == len(vals)
        if len(vals) == 0:
            assert np.isnan(med[k]) and np.isnan(lo[k]) and np.isnan(hi[k])
        else:
            np.testing.assert_allclose([med[k], lo[k], hi[k]], np.percentile(vals, [50, 10, 90]), rtol=1e-12)


def test_lift_on_real_depth_equals_window_median(o3d_root):
    intr = load_intrinsics(o3d_root / "camera_primesense.json")
    depth = cv2.imread(str(o3d_root / "RGBD" / "depth" / "00001.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000
    rng = np.random.default_rng(0)
    px = rng.uniform([3, 3], [intr.width - 4, intr.height - 4], size=(400, 2))
    pts, ok = lift_keypoints(px, depth, intr, window=2)
    assert 100 < ok.sum() < 400
    for i in np.flatnonzero(ok):
        u, v = np.rint(px[i]).astype(int)
        win = depth[v - 2:v + 3, u - 2:u + 3]
        # the median itself, read back through float32 (6e-8 m at 1 m); abs 1e-6 m leaves 16x
        assert pts[i, 2] == pytest.approx(np.median(win[win > 0]), abs=1e-6)
    # project(lift(px)) at the keypoint's own pixel: float32 depth cancels in x/z, float64 rounding ~1e-12 px
    np.testing.assert_allclose(project(pts[ok], intr), px[ok], atol=1e-6)


# ---------------------------------------------------------------- load_intrinsics

def test_load_intrinsics_open3d_json(o3d_root):
    intr = load_intrinsics(o3d_root / "camera_primesense.json")
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (525.0, 525.0, 319.5, 239.5, 640, 480)
    with pytest.raises(InputError, match="camera_primesense.json"):
        load_intrinsics(o3d_root / "camera_primesense.json", width=320, height=240)


def test_load_intrinsics_cam_k_txt_and_bop(tmp_path):
    p = tmp_path / "cam_K.txt"
    p.write_text("600.5 0 320.25\n0 601 239.75\n0 0 1\n")
    intr = load_intrinsics(p, 640, 480)
    # parsed decimal text: 600.5, 320.25 and 239.75 are exact in binary
    np.testing.assert_allclose(intr.K, [[600.5, 0, 320.25], [0, 601, 239.75], [0, 0, 1]])
    assert (intr.width, intr.height) == (640, 480)
    with pytest.raises(InputError, match="no image size"):
        load_intrinsics(p)
    b = tmp_path / "camera.json"
    b.write_text(json.dumps({"cam_K": [572.4, 0.0, 325.3, 0.0, 573.6, 242.0, 0.0, 0.0, 1.0], "depth_scale": 0.1}))
    intr = load_intrinsics(b, 640, 480)
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == (572.4, 573.6, 325.3, 242.0)
    b.write_text(json.dumps({"fx": 500.0, "fy": 501.0, "cx": 300.0, "cy": 200.0, "width": 600, "height": 400}))
    intr = load_intrinsics(b)
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (500.0, 501.0, 300.0, 200.0, 600, 400)


@pytest.mark.parametrize("name,text", [
    ("cam_K.txt", "600 0 320\n0 600 240\n"),  # 2 rows
    ("cam_K.txt", "600 0 320\n0 600\n0 0 1\n"),  # ragged
    ("cam_K.txt", "600 0 320\n0 abc 240\n0 0 1\n"),  # not a number
    ("cam_K.txt", "nan 0 320\n0 600 240\n0 0 1\n"),  # NaN
    ("cam_K.txt", "-600 0 320\n0 600 240\n0 0 1\n"),  # negative focal length
    ("cam_K.txt", "600 0 -320\n0 600 240\n0 0 1\n"),  # negative principal point
    ("cam_K.txt", "600 5 320\n0 600 240\n0 0 1\n"),  # skew: not representable
    ("cam_K.txt", "600 0 320\n0 600 240\n0 0 2\n"),  # not normalised
    ("cam_K.txt", ""),
    ("camera.json", "{\"cam_K\": [1, 2, 3]}"),
    ("camera.json", "{\"fx\": 500, \"fy\": NaN, \"cx\": 1, \"cy\": 1, \"width\": 10, \"height\": 10}"),
    ("camera.json", "{\"intrinsic_matrix\": [525, 0, 0, 0, 525, 0, 319.5, 239.5, 1], \"width\": -640, "
                    "\"height\": 480}"),
    ("camera.json", "{\"something\": 1}"),
    ("camera.json", "{not json"),
    ("camera.json", "[1, 2, 3]"),
])
def test_load_intrinsics_rejects_malformed(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(InputError) as ei:
        load_intrinsics(p, 640, 480)
    assert ei.value.path == p and name in str(ei.value) and "\n" not in str(ei.value)


def test_load_intrinsics_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_intrinsics(tmp_path / "nope.txt", 640, 480)


DEPTH_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


def _T_color_depth() -> np.ndarray:
    return make_T(rotvec_to_R(np.array([0.0, 0.03, 0.01])), np.array([-0.025, 0.001, 0.002]))


def test_load_depth_camera_from_a_cam_k_txt_an_open3d_json_and_pose_files(tmp_path):
    """load_depth_camera: a cam_K.txt fits depth images of any size, an Open3D JSON its own size alone; the pose
    as 4x4 text or JSON (default the colour camera's centre and axes). The value is its numbers, not its files."""
    np.savetxt(tmp_path / "depth_K.txt", DEPTH_K)
    T = _T_color_depth()
    np.savetxt(tmp_path / "T.txt", T)
    (tmp_path / "T.json").write_text(json.dumps({"T": T.tolist()}))
    cam = load_depth_camera(tmp_path / "depth_K.txt")
    assert cam.size is None and np.array_equal(cam.K, DEPTH_K) and np.array_equal(cam.T_color_depth, np.eye(4))
    assert cam.source == tmp_path / "depth_K.txt"
    with pytest.raises(ValueError, match="any size"):
        _ = cam.intrinsics
    assert cam.for_size(640, 480) == Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    assert cam.for_size(320, 240) == Intrinsics(585.0, 585.0, 320.0, 240.0, 320, 240)
    with pytest.raises(ValueError, match="principal point"):
        cam.for_size(100, 100)
    for pose in ("T.txt", "T.json"):
        np.testing.assert_allclose(load_depth_camera(tmp_path / "depth_K.txt", tmp_path / pose).T_color_depth, T,
                                   atol=1e-12)
    o3d = {"width": 640, "height": 480, "intrinsic_matrix": DEPTH_K.T.flatten().tolist()}
    (tmp_path / "depth_K.json").write_text(json.dumps(o3d))
    js = load_depth_camera(tmp_path / "depth_K.json", tmp_path / "T.json")
    assert js.size == (640, 480) and js.intrinsics == Intrinsics.from_matrix(DEPTH_K, 640, 480)
    with pytest.raises(ValueError, match="depth is 320x240 but the depth camera's intrinsics are for 640x480"):
        js.for_size(320, 240)
    assert DepthCamera.from_dict(json.loads(json.dumps(js.to_dict()))) == js
    assert DepthCamera.from_dict(json.loads(json.dumps(cam.to_dict()))) == cam
    assert js != cam and js == DepthCamera(Intrinsics.from_matrix(DEPTH_K, 640, 480), js.T_color_depth)
    assert cam.sized(640, 480) == DepthCamera(Intrinsics.from_matrix(DEPTH_K, 640, 480))
    with pytest.raises(AttributeError):
        cam.size = (1, 1)  # type: ignore[misc]
    assert not cam.K.flags.writeable and not cam.T_color_depth.flags.writeable


@pytest.mark.parametrize("files, named, why", [
    ({"K.txt": "585 0 320\n0 585\n"}, "K.txt", "malformed cam_K.txt"),
    ({"K.txt": "585 0.5 320\n0 585 240\n0 0 1\n"}, "K.txt", "not a pinhole"),
    ({"K.json": "{not json"}, "K.json", "malformed intrinsics JSON"),
    ({"K.json": json.dumps({"fx": 585, "fy": 585, "cx": 5000, "cy": 240, "width": 640, "height": 480})}, "K.json",
     "principal point"),
    ({}, "K.txt", "not found"),
    ({"T.txt": "1 0 0 0\n0 2 0 0\n0 0 1 0\n0 0 0 1\n"}, "T.txt", "not a rigid transform"),
    ({"T.txt": "1 2 3\n"}, "T.txt", "malformed pose file"),
    ({"T.json": json.dumps({"R": 1})}, "T.json", "expected"),
    ({"T.json": json.dumps({"T": (2 * np.eye(4)).tolist()})}, "T.json", "not a rigid transform"),
])
def test_load_depth_camera_names_the_bad_file(tmp_path, files, named, why):
    np.savetxt(tmp_path / "good_K.txt", DEPTH_K)
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    K = tmp_path / (named if named.startswith("K") else "good_K.txt")
    pose = tmp_path / named if named.startswith("T") else None
    with pytest.raises(InputError, match=why) as e:
        load_depth_camera(K, pose)
    assert e.value.path == tmp_path / named


def test_depth_camera_refuses_what_is_not_a_camera():
    with pytest.raises(ValueError, match="rigid"):
        DepthCamera(DEPTH_K, 2 * np.eye(4))
    with pytest.raises(ValueError, match="4x4"):
        DepthCamera(DEPTH_K, np.eye(3))
    with pytest.raises(ValueError, match="3x3"):
        DepthCamera(np.eye(2))
    with pytest.raises(ValueError, match="pinhole"):
        DepthCamera(np.array([[585.0, 0, 320], [0, 585, 240], [0, 0, 2]]))


def test_rgbd_frame_size_checks():
    with pytest.raises(InputError):
        RGBDFrame("x", np.zeros((48, 64, 3), np.uint8), np.zeros((48, 63), np.float32), INTR)
    with pytest.raises(InputError):
        RGBDFrame("x", np.zeros((24, 32, 3), np.uint8), np.zeros((24, 32), np.float32), INTR)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 300), st.booleans())
def test_kabsch_kernel_against_the_quaternion_solution(seed, n, weighted):
    """The numba Kabsch (weights, the reflection guard, the similarity's scale) against Horn's closed form: the
    rotation is the top eigenvector of the 4 x 4 quaternion matrix of the weighted cross-covariance, the scale
    the ratio of the rotated cross-covariance to the source's spread (numpy, an independent formulation)."""
    from gscan.geometry.kabsch import umeyama

    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * rng.uniform(0.01, 1.0, 3)
    scale = rng.uniform(0.5, 2.0)
    dst = scale * transform_points(_rigid(rng), src) + rng.normal(0, 0.01, size=src.shape)
    w = rng.uniform(0.1, 10.0, n) if weighted else np.ones(n)
    ws = w / w.sum()
    xs, xd = src - ws @ src, dst - ws @ dst
    S = (xs * ws[:, None]).T @ xd  # S[a, b] = sum w x_a y_b
    N = np.array([[S[0, 0] + S[1, 1] + S[2, 2], S[1, 2] - S[2, 1], S[2, 0] - S[0, 2], S[0, 1] - S[1, 0]],
                  [S[1, 2] - S[2, 1], S[0, 0] - S[1, 1] - S[2, 2], S[0, 1] + S[1, 0], S[2, 0] + S[0, 2]],
                  [S[2, 0] - S[0, 2], S[0, 1] + S[1, 0], -S[0, 0] + S[1, 1] - S[2, 2], S[1, 2] + S[2, 1]],
                  [S[0, 1] - S[1, 0], S[2, 0] + S[0, 2], S[1, 2] + S[2, 1], -S[0, 0] - S[1, 1] + S[2, 2]]])
    evals, evecs = np.linalg.eigh(N)
    q0, qx, qy, qz = evecs[:, -1]
    R = np.array([[q0 * q0 + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - q0 * qz), 2 * (qx * qz + q0 * qy)],
                  [2 * (qy * qx + q0 * qz), q0 * q0 - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - q0 * qx)],
                  [2 * (qz * qx - q0 * qy), 2 * (qz * qy + q0 * qx), q0 * q0 - qx * qx - qy * qy + qz * qz]])
    s = np.trace(R @ S) / np.sum(ws * (xs ** 2).sum(1))
    for with_scale, k in ((False, 1.0), (True, s)):
        T = umeyama(src, dst, w if weighted else None, with_scale=with_scale)
        # the same least-squares optimum by two formulations: float64 rounding amplified by the eigen-gap, ~1e-12
        np.testing.assert_allclose(T[:3, :3], k * R, atol=1e-8)
        np.testing.assert_allclose(T[:3, 3], ws @ dst - k * R @ (ws @ src), atol=1e-8)


def test_the_kabsch_kernels_load_from_numba_s_cache_in_a_new_process(tmp_path):
    """Each kernel compiled into numba's cache by one process is loaded and run by the next (a recursive kernel
    crashed there: numba's cache cannot hold one), with the results the first process got."""
    import subprocess
    import sys

    script = ("import numpy as np, sys\n"
              "from gscan.geometry.kabsch import kabsch, kabsch_trimmed, leave_one_out_residuals, umeyama\n"
              "rng = np.random.default_rng(0)\n"
              "src = rng.normal(size=(300, 3)); dst = src + 0.01 * rng.normal(size=(300, 3)); dst[:5] += 1.0\n"
              "out = [kabsch(src, dst, rng.uniform(1, 2, 300)), umeyama(src, 2 * dst, with_scale=True),\n"
              "       leave_one_out_residuals(src[:20], dst[:20]), *kabsch_trimmed(src[:40], dst[:40], 0.03)]\n"
              "np.save(sys.argv[1], np.concatenate([np.ravel(a).astype(float) for a in out]))\n")
    runs = [subprocess.run([sys.executable, "-c", script, str(tmp_path / f"{k}.npy")], capture_output=True,
                           text=True, timeout=300) for k in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    np.testing.assert_array_equal(np.load(tmp_path / "0.npy"), np.load(tmp_path / "1.npy"))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 5000))
def test_the_kernels_pairwise_sum_is_a_sum(seed, n):
    """The kernels' pairwise sum (numpy's summation order, without recursion) against math.fsum's exact one."""
    import math

    from gscan.geometry.kabsch_kernel import _pairwise_sum

    a = np.random.default_rng(seed).uniform(0.0, 1.0, n)
    assert abs(_pairwise_sum(a) - math.fsum(a)) <= 1e-13 * max(1.0, math.fsum(a))
