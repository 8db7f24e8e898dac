"""Hand-computed checks of gscan.evaluate.metrics (ADD/ADD-S/AUC, ATE, VSD, MSSD/MSPD, BOP recall).

Tolerances: every expected value is worked out by hand and gscan computes it in float64 from a few operations,
so the two agree to rounding (~1e-16 relative). `abs=1e-12` on values of order 0.01-100 and pytest.approx's
default (rel 1e-6) leave many orders of magnitude; 1e-9 where an SVD (ATE's alignment), a k-d tree over moved
points or a sum over a few hundred points comes in. VSD errors are ratios of pixel counts, exact up to one
division (atol 0 or 1e-12). Angles come from arccos of a rotation's trace, well conditioned away from 0 and 180
deg (at 30 deg an error e in the cosine moves the angle by 2e rad); at 180 deg one ulp of the trace reads as
1.2e-6 deg, inside approx's 1.8e-4 deg there.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.evaluate.metrics import (
    add,
    adds,
    ar_mspd,
    ar_mssd,
    ate,
    ate_rmse,
    auc,
    average_recall,
    mspd,
    mspd_thresholds,
    mssd,
    mssd_thresholds,
    recall_at,
    rotation_error_deg,
    translation_error,
)
from gscan.geometry.transforms import make_T, rotvec_to_R
from gscan.io.camera import Intrinsics

RZ180 = make_T(rotvec_to_R([0.0, 0.0, np.pi]), np.zeros(3))
RX180 = make_T(rotvec_to_R([np.pi, 0.0, 0.0]), np.zeros(3))


def _box_points(sx: float = 0.2, sy: float = 0.1, sz: float = 0.05, n: int = 5) -> np.ndarray:
    """Surface grid of an axis-aligned box centred at the origin (symmetric under Rz(180))."""
    g = np.linspace(-0.5, 0.5, n)
    X, Y, Z = np.meshgrid(g * sx, g * sy, g * sz, indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    on_surface = np.isclose(np.abs(P) / np.array([sx, sy, sz]), 0.5).any(axis=1)
    return P[on_surface]


def test_rotation_and_translation_error():
    T_gt = make_T(rotvec_to_R([0.1, -0.2, 0.3]), [0.1, 0.2, 0.3])
    dR = rotvec_to_R(np.radians(30.0) * np.array([0.0, 0.6, 0.8]))
    T_est = make_T(dR @ T_gt[:3, :3], T_gt[:3, 3] + [0.03, 0.0, -0.04])
    assert rotation_error_deg(T_est, T_gt) == pytest.approx(30.0, abs=1e-9)
    assert rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]) == pytest.approx(30.0, abs=1e-9)
    assert translation_error(T_est, T_gt) == pytest.approx(0.05, abs=1e-12)
    assert rotation_error_deg(RZ180, np.eye(4)) == pytest.approx(180.0)


def test_auc_hand_computed():
    assert auc(np.zeros(7)) == pytest.approx(100.0)
    assert auc([0.11, 0.5, np.inf, np.nan]) == 0.0
    # n = 4; finite errors 0.02 (acc 1/4), 0.04 (acc 2/4); 0.2 and NaN are failures:
    # area = 0.02 * 0.25 + 0.02 * 0.5 + (0.1 - 0.04) * 0.5 = 0.045 -> 45 % of 0.1
    assert auc([0.04, 0.2, 0.02, np.nan]) == pytest.approx(45.0)
    # exactly at the threshold still counts (toolbox: D(D > 0.1) = inf): the interval
    # (0, 0.1] takes the accuracy of the first of the equal errors, 1/2 -> 50
    assert auc([0.1, 0.1]) == pytest.approx(50.0)
    assert auc([0.1, 0.1000001]) == pytest.approx(50.0)
    # duplicates: [0.05, 0.05]: area = 0.05 * 0.5 + 0.05 * 1.0 = 0.075 -> 75
    assert auc([0.05, 0.05]) == pytest.approx(75.0)
    assert auc([0.01], max_threshold=0.02) == pytest.approx(100.0)
    with pytest.raises(ValueError):
        auc([])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 0.2, allow_nan=False), min_size=1, max_size=30))
def test_auc_equals_exact_integral_plus_toolbox_bias(errors):
    """VOCap = exact area under the empirical accuracy curve + d_max / n (derived in auc's docstring)."""
    e = np.asarray(errors)
    n = len(e)
    ok = e[e <= 0.1]
    exact = np.sum(0.1 - ok) / n
    bias = (ok.max() if ok.size else 0.0) / n
    assert auc(e) == pytest.approx((exact + bias) / 0.1 * 100.0, abs=1e-9)
    assert 0.0 <= auc(e) <= 100.0


def test_add_pure_translation():
    pts = np.random.default_rng(0).normal(size=(200, 3)) * 0.05
    T_gt = make_T(rotvec_to_R([0.3, 0.1, -0.4]), [0.0, 0.1, 0.7])
    t = np.array([0.01, -0.02, 0.02])
    T_est = T_gt.copy()
    T_est[:3, 3] += t
    assert add(pts, T_est, T_gt) == pytest.approx(np.linalg.norm(t), abs=1e-12)
    assert add(pts, T_gt, T_gt) == 0.0
    assert adds(pts, T_gt, T_gt) < 1e-12


def test_adds_symmetric_box():
    pts = _box_points()
    T_gt = make_T(rotvec_to_R([0.2, -0.5, 0.1]), [0.05, -0.02, 0.8])
    T_est = T_gt @ RZ180  # the box turned 180 degrees about its own z (symmetry) axis
    assert adds(pts, T_est, T_gt) < 1e-9
    # every point (x, y, z) -> (-x, -y, z): distance 2 * sqrt(x^2 + y^2)
    expected = np.mean(2 * np.linalg.norm(pts[:, :2], axis=1))
    assert add(pts, T_est, T_gt) == pytest.approx(expected, rel=1e-9)
    assert add(pts, T_est, T_gt) > 0.1
    # and ADD-S is a true nearest-neighbour distance: a shift of 1 mm in z is seen as 1 mm at most
    T_shift = T_gt @ make_T(np.eye(3), [0.0, 0.0, 0.001])
    assert 0.0 < adds(pts, T_shift, T_gt) <= 0.001 + 1e-12


def _random_rigid(rng: np.random.Generator) -> np.ndarray:
    return make_T(rotvec_to_R(rng.normal(size=3)), rng.normal(size=3) * 2.0)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 25))
def test_ate_invariant_to_rigid_motion(seed, n):
    rng = np.random.default_rng(seed)
    gt = [_random_rigid(rng) for _ in range(n)]
    M = _random_rigid(rng)  # the estimate lives in another world frame
    est = [M @ T for T in gt]
    assert ate_rmse(est, gt) < 1e-9


def test_ate_hand_computed():
    # octahedron of positions, estimate scaled outwards by delta: alignment stays identity
    # (C = 2 (1 + delta) I), each error is delta -> ATE = delta
    delta = 0.03
    dirs = np.concatenate([np.eye(3), -np.eye(3)])
    gt = [make_T(np.eye(3), d) for d in dirs]
    est = [make_T(rotvec_to_R([0.0, 0.0, 0.7]), d * (1 + delta)) for d in dirs]  # orientations do not matter
    res = ate(est, gt)
    assert res.rmse == pytest.approx(delta, abs=1e-12)
    assert res.max == pytest.approx(delta, abs=1e-12)
    np.testing.assert_allclose(res.T_gt_est, np.eye(4), atol=1e-12)
    # one pose: always 0; two poses 1.0 m and 1.2 m apart: each end off by 0.1 m
    assert ate_rmse([make_T(np.eye(3), [5.0, 0, 0])], [np.eye(4)]) == 0.0
    two_gt = [np.eye(4), make_T(np.eye(3), [1.0, 0.0, 0.0])]
    two_est = [make_T(np.eye(3), [3.0, 3.0, 3.0]), make_T(np.eye(3), [3.0, 4.2, 3.0])]
    assert ate_rmse(two_est, two_gt) == pytest.approx(0.1, abs=1e-12)
    # a single outlier among 4 collinear-free poses: the alignment spreads it, RMSE below the raw offset
    sq = [make_T(np.eye(3), p) for p in ([0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1])]
    bad = [T.copy() for T in sq]
    bad[3][:3, 3] += [0.0, 0.0, 0.2]
    r = ate_rmse(bad, sq)
    assert 0.0 < r < 0.2 / 2 + 1e-12
    with pytest.raises(ValueError):
        ate(sq, sq[:2])


def test_mssd_mspd_hand_computed():
    pts = np.array([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0], [0.0, 0.05, 0.0]])
    T_gt = make_T(np.eye(3), [0.0, 0.0, 1.0])
    T_est = T_gt @ RZ180  # points -> (-0.1,0,0), (0.1,0,0), (0,-0.05,0): distances 0.2, 0.2, 0.1
    K = np.array([[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 1.0]])
    assert mssd(pts, T_est, T_gt) == pytest.approx(0.2)
    assert mssd(pts, T_est, T_gt, syms=[RZ180]) == pytest.approx(0.0, abs=1e-12)
    assert mssd(pts, T_est, T_gt, syms=[RX180]) == pytest.approx(0.2)  # a symmetry that does not help
    # at z = 1 with f = 100: 0.2 m -> 20 px
    assert mspd(pts, T_est, T_gt, K) == pytest.approx(20.0)
    assert mspd(pts, T_est, T_gt, K, syms=[RX180, RZ180]) == pytest.approx(0.0, abs=1e-9)
    # a lateral shift of 1 cm at 1 m: 1 px everywhere; MSSD 1 cm
    T_shift = make_T(np.eye(3), [0.01, 0.0, 1.0])
    assert mspd(pts, T_shift, T_gt, K) == pytest.approx(1.0)
    assert mssd(pts, T_shift, T_gt) == pytest.approx(0.01)
    # moving to 2 m halves the projections: u 10 -> 5 px is the largest change
    T_far = make_T(np.eye(3), [0.0, 0.0, 2.0])
    intr = Intrinsics(100.0, 100.0, 0.0, 0.0, 640, 480)
    assert mspd(pts, T_far, T_gt, intr) == pytest.approx(5.0)
    assert mssd(pts, T_far, T_gt) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        mspd(pts, make_T(np.eye(3), [0.0, 0.0, -1.0]), T_gt, K)


def test_bop_recall():
    np.testing.assert_allclose(mssd_thresholds(0.2), np.arange(1, 11) * 0.01)
    np.testing.assert_allclose(mspd_thresholds(640), np.arange(1, 11) * 5.0)
    np.testing.assert_allclose(mspd_thresholds(1280), np.arange(1, 11) * 10.0)
    # 0.012 is below 9 of the 10 thresholds (not 0.01); 0.5 below none -> mean (9 * 0.5) / 10
    assert ar_mssd([0.012, 0.5], diameter=0.2) == pytest.approx(0.45)
    # strictly below: an error equal to a threshold fails it
    np.testing.assert_allclose(recall_at([5.0], [5.0, 5.0001]), [0.0, 1.0])
    assert ar_mspd([0.0, np.nan]) == pytest.approx(0.5)
    assert ar_mspd([12.0], image_width=1280) == pytest.approx(0.9)  # thresholds 10..100 px
    assert average_recall([0.0, 0.0], [1.0]) == 1.0
    with pytest.raises(ValueError):
        mssd_thresholds(0.0)


def test_diameter_is_the_largest_pairwise_distance():
    from gscan.evaluate.metrics import diameter

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(700, 3))
    brute = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1)).max()
    assert diameter(pts) == pytest.approx(brute, rel=1e-12)
    box = np.array([[x, y, z] for x in (0, 0.3) for y in (0, 0.2) for z in (0, 0.1)])
    assert diameter(box) == pytest.approx(np.sqrt(0.3 ** 2 + 0.2 ** 2 + 0.1 ** 2))
    flat = np.c_[rng.random((50, 2)), np.zeros(50)]  # coplanar: no 3D hull, still exact
    assert diameter(flat) == pytest.approx(np.sqrt(((flat[:, None] - flat[None]) ** 2).sum(-1)).max())
    assert diameter(pts[:1]) == 0.0


# --------------------------------------------------------------------------------------------------- VSD
# A square plate of half-side 0.1005 m facing a camera with f = 100 px, principal point (49.5, 49.5) in a 100 x 100
# image: at 1.0 m it covers the 20 x 20 pixel centres with |u - 49.5| <= 9.5 (its edge at 10.05 px lies between
# pixel centres), at 1.25 m the centred 16 x 16 (edge at 8.04 px). Every count below follows from that.
VSD_K = np.array([[100.0, 0.0, 49.5], [0.0, 100.0, 49.5], [0.0, 0.0, 1.0]])
HALF = 0.1005


def _plate_depth(z: float) -> np.ndarray:
    """[100 x 100] depth of the plate at distance z along the optical axis, 0 off the plate (analytic)."""
    c = np.abs(np.arange(100) - 49.5) < 100.0 * HALF / z
    return np.where(c[:, None] & c[None, :], z, 0.0)


def test_vsd_of_a_plate_moved_along_the_optical_axis():
    """The estimate 0.25 m behind the truth: its 16 x 16 pixels all lie 0.25 m (x the ray's length, at most
    1.0056 at the 16 x 16's corners) off the truth's, and the truth's other 400 - 256 pixels are not matched."""
    from gscan.evaluate.metrics import vsd

    d_gt, d_est = _plate_depth(1.0), _plate_depth(1.25)
    assert (d_gt > 0).sum() == 400 and (d_est > 0).sum() == 256
    e = vsd(d_gt, d_est, d_gt, VSD_K, taus=[0.1, 0.25, 0.3])
    # tau 0.1 and 0.25 <= every pixel's distance: nothing matches; tau 0.3 > all: the 256 match
    np.testing.assert_allclose(e, [1.0, 1.0, (400 - 256) / 400], rtol=0, atol=1e-12)
    # the exact pose: every visible pixel matches for any tau > 0
    np.testing.assert_allclose(vsd(d_gt, d_gt, d_gt, VSD_K, taus=[1e-6, 0.1]), [0.0, 0.0], atol=0)
    # no model in either pose: the error is 1 (nothing to compare)
    none = np.zeros((100, 100))
    np.testing.assert_allclose(vsd(d_gt, none, none, VSD_K, taus=[0.1]), [1.0], atol=0)


def test_vsd_visibility_rules():
    """BOP19 visibility: an occluder more than delta (15 mm) in front hides the model; a pixel without measured
    depth counts as visible."""
    from gscan.evaluate.metrics import VSD_DELTA_M, vsd

    d_gt, d_est = _plate_depth(1.0), _plate_depth(1.25)
    occluded = d_gt.copy()
    occluded[:, :50] = np.where(d_gt[:, :50] > 0, 0.9, 0.0)  # the plate's left half (columns 40-49) hidden
    # truth visible on its right half (200 px); the estimate's own pixels are all > delta behind the measured
    # surface, so it is visible only where it covers the truth's visible pixels (16 rows x columns 50-57)
    e = vsd(occluded, d_est, d_gt, VSD_K, taus=[0.1, 0.3])
    np.testing.assert_allclose(e, [1.0, (200 - 128) / 200], atol=1e-12)
    assert vsd(occluded, d_gt, d_gt, VSD_K, taus=[0.1])[0] == 0.0  # the exact pose is not blamed for the occluder
    # an occluder just within delta in front does not hide the model
    near = np.where(d_gt > 0, 1.0 - 0.9 * VSD_DELTA_M, 0.0)
    np.testing.assert_allclose(vsd(near, d_est, d_gt, VSD_K, taus=[0.1, 0.3]), [1.0, (400 - 256) / 400], atol=1e-12)
    # no measured depth anywhere: both surfaces count as visible, as with a measured plate
    np.testing.assert_allclose(vsd(np.zeros((100, 100)), d_est, d_gt, VSD_K, taus=[0.1, 0.3]),
                               [1.0, (400 - 256) / 400], atol=1e-12)


def test_vsd_on_rendered_plate_and_recall():
    """The plate ray-cast (geometry.raycast) gives the analytic depth images, with VSD's pixel offset too; BOP19's
    taus scale with the diameter, and AR_VSD averages the recall over its thresholds (strictly below) and the taus."""
    from gscan.evaluate.metrics import VSD_RENDER_PIXEL_OFFSET, VSD_TAU_FRACTIONS, ar_vsd, vsd, vsd_taus
    from gscan.geometry.raycast import MeshRaycaster

    V = np.array([[-HALF, -HALF, 0], [HALF, -HALF, 0], [HALF, HALF, 0], [-HALF, HALF, 0]])
    caster = MeshRaycaster(V, np.array([[0, 1, 2], [0, 2, 3]]))
    cam = Intrinsics(100.0, 100.0, 49.5, 49.5, 100, 100)
    for z in (1.0, 1.25):
        T_obj_cam = make_T(np.eye(3), [0.0, 0.0, -z])  # the camera z metres in front of the plate, facing it
        np.testing.assert_allclose(caster.depth(cam, T_obj_cam), _plate_depth(z), atol=1e-6)  # float32 depth
    # VSD's renders sample pixel (u, v) at (u + 0.5, v + 0.5), as OpenGL does (the BOP toolkit's renderers): at
    # 1 m the plate's edges at 39.45 and 59.55 px take in the 21 columns and rows 39-59
    inside = np.abs(np.arange(100) + VSD_RENDER_PIXEL_OFFSET - 49.5) < 100.0 * HALF
    hit = caster.depth(cam, make_T(np.eye(3), [0.0, 0.0, -1.0]), VSD_RENDER_PIXEL_OFFSET) > 0
    assert hit.sum() == 21 * 21 and (hit == inside[:, None] & inside[None, :]).all()
    diam = 2 * np.sqrt(2) * HALF  # 0.2843 m: the plate's diagonal
    taus = vsd_taus(diam)
    np.testing.assert_allclose(taus, VSD_TAU_FRACTIONS * diam)
    # 5 cm behind: the same 400 pixels (edge at 9.57 px), each 0.05 x its ray's length (<= 1.009) off, so
    # 0.0500-0.0505 m: the taus 0.014, 0.028 and 0.043 m fail every pixel, the seven from 0.057 m on none
    e = vsd(_plate_depth(1.0), _plate_depth(1.05), _plate_depth(1.0), cam, taus)
    np.testing.assert_allclose(e, [1.0] * 3 + [0.0] * 7, atol=0)
    assert ar_vsd([e]) == pytest.approx(0.7)  # an error of 0 is below every threshold, 1 below none
    # 0.36 (the 1.25 m case) is below 3 of the 10 thresholds (0.40, 0.45, 0.50: strictly below)
    assert ar_vsd(np.full((1, 10), 0.36)) == pytest.approx(0.3)
    assert ar_vsd(np.zeros((2, 10))) == 1.0 and ar_vsd(np.full((2, 10), np.inf)) == 0.0
