"""Point-set helpers of pose estimation (gscan.geometry.pointset): exact on constructed inputs, deterministic."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.geometry.icp import icp_point_to_plane
from gscan.geometry.pointset import coincident_groups, pca_normals, voxel_down_indices, voxel_mean
from gscan.geometry.transforms import make_T, pose_error, rotvec_to_R, transform_points


def _box_surface(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n points on the surface of a 10 x 6 x 4 cm box 0.6 m in front of the camera, with their face normals."""
    half = np.array([0.05, 0.03, 0.02])
    axis = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    p = rng.uniform(-half, half, (n, 3))
    p[np.arange(n), axis] = sign * half[axis]
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = sign
    return p + [0.0, 0.0, 0.6], normals


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_icp_point_to_plane_recovers_a_small_motion(seed):
    rng = np.random.default_rng(seed)
    src, normals = _box_surface(3000, rng)
    R, c = rotvec_to_R(rng.normal(0, np.radians(2), 3)), np.array([0.0, 0.0, 0.6])
    T = make_T(R, c - R @ c + rng.normal(0, 0.003, 3))  # a few degrees about the box centre, a few mm
    tgt = transform_points(T, _box_surface(3000, rng)[0])  # other samples of the same surface
    T_est, fitness = icp_point_to_plane(src, normals, tgt, np.eye(4), max_dist=0.015, iterations=30)
    deg, m = pose_error(T_est, T)
    assert deg < 0.3 and m < 0.002 and fitness > 0.9  # 300 seeds: <= 0.13 deg, <= 1.4 mm (two samplings)
    T_again, _ = icp_point_to_plane(src, normals, tgt, np.eye(4), max_dist=0.015, iterations=30)
    np.testing.assert_array_equal(T_est, T_again)  # deterministic


def test_icp_point_to_plane_without_enough_points_keeps_the_start():
    T0 = make_T(rotvec_to_R([0.1, 0, 0]), [0, 0, 0.01])
    T, fitness = icp_point_to_plane(np.zeros((5, 3)), np.zeros((5, 3)), np.zeros((50, 3)), T0, 0.01)
    np.testing.assert_array_equal(T, T0)
    assert fitness == 0.0


def test_pca_normals_of_box_faces():
    rng = np.random.default_rng(1)
    pts, normals = _box_surface(4000, rng)
    est = pca_normals(pts, k=8)
    face = np.abs(np.einsum("ij,ij->i", est, normals))
    assert np.median(face) > 0.99  # unoriented: |cos| to the true face normal
    np.testing.assert_allclose(np.linalg.norm(est, axis=1), 1.0, atol=1e-9)  # unit normals: float64 normalisation


def test_coincident_groups_and_voxels():
    pts = np.array([[0.0, 0, 0], [1, 1, 1], [0, 0, 0.00001], [2, 2, 2], [1, 1, 1]])
    order, starts = coincident_groups(pts)
    groups = [order[a:b].tolist() for a, b in zip(starts, list(starts[1:]) + [len(order)], strict=True)]
    assert groups == [[0, 2], [1, 4], [3]]  # first-occurrence order, members in input order, 0.1 mm tolerance
    assert coincident_groups(np.zeros((0, 3)))[0].size == 0
    grid = np.array([[0.001, 0, 0], [0.003, 0, 0], [0.011, 0, 0], [0.0, 0.02, 0]])
    # voxel means of exact values: float64 rounding (assert_allclose's rtol 1e-7)
    np.testing.assert_allclose(voxel_mean(grid, 0.01), [[0.002, 0, 0], [0.0, 0.02, 0], [0.011, 0, 0]])
    np.testing.assert_array_equal(voxel_down_indices(grid, 0.01), [0, 2, 3])
    np.testing.assert_array_equal(voxel_down_indices(grid, 0.0), np.arange(4))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.01, 0.5, 1e7]))
def test_voxels_and_groups_equal_their_definition(seed, scale):
    """Voxel means (rows ordered by voxel key, per-voxel sums in input order), one index per voxel and the
    coincident groups, against a plain per-point loop: bit-identical, also for coordinates whose voxel keys do
    not fit the integer code (scale 1e7)."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    pts = (rng.random((n, 3)) - 0.4) * scale
    pts[rng.random(n) < 0.3] = pts[0]  # repeated points
    rows = np.hstack([pts, rng.random((n, 2))])  # xyz and two per-point values
    voxel = scale / 20
    sums: dict[tuple, list] = {}
    for r in rows:
        key = tuple(np.floor(r[:3] / voxel).astype(np.int64))
        acc = sums.setdefault(key, [np.zeros(rows.shape[1]), 0])
        acc[0] = acc[0] + r
        acc[1] += 1
    want = np.array([sums[k][0] / sums[k][1] for k in sorted(sums)])
    np.testing.assert_array_equal(voxel_mean(rows, voxel), want)
    first: dict[tuple, int] = {}
    for i, p in enumerate(pts):
        first.setdefault(tuple(np.floor(p / voxel).astype(np.int64)), i)
    np.testing.assert_array_equal(voxel_down_indices(pts, voxel), sorted(first.values()))
    groups: dict[tuple, list] = {}
    for i, p in enumerate(pts):
        groups.setdefault(tuple(np.rint(p * 1e4).astype(np.int64)), []).append(i)
    order, starts = coincident_groups(pts)
    got = [order[a:b].tolist() for a, b in zip(starts, list(starts[1:]) + [n], strict=True)]
    assert got == list(groups.values())


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.002, 0.005, 0.03]), st.booleans())
def test_nearest_grid_equals_brute_force(seed, radius, coarse):
    """The grid's nearest point within the radius is the brute-force one (squared distances summed as
    (dx^2 + dy^2) + dz^2, strictly below radius^2; ties to the lower index), also for queries outside the
    points' bounds and with points on a coarse lattice (many exact ties)."""
    from gscan.geometry.grid_kernel import NearestGrid

    rng = np.random.default_rng(seed)
    P = rng.random((int(rng.integers(1, 400)), 3)) * 0.1 + [0.0, 0.0, 0.5]
    Q = rng.random((int(rng.integers(1, 300)), 3)) * 0.14 + [-0.02, -0.02, 0.48]
    if coarse:
        P, Q = np.round(P / radius) * radius, np.round(Q / radius * 2) * radius / 2
    Q[: len(Q) // 3] = P[rng.integers(0, len(P), len(Q) // 3)]  # exact hits
    grid = NearestGrid.build(P, radius)
    assert grid is not None
    found, nearest = grid.query(Q)
    D = Q[:, None, :] - P[None, :, :]
    d2 = (D[..., 0] * D[..., 0] + D[..., 1] * D[..., 1]) + D[..., 2] * D[..., 2]
    want = np.argmin(d2, axis=1)  # first on ties
    ok = d2[np.arange(len(Q)), want] < radius * radius
    np.testing.assert_array_equal(found, ok)
    np.testing.assert_array_equal(nearest, np.where(ok, want, -1))
    assert ok.any()


def test_nearest_grid_refuses_points_spread_too_wide():
    from gscan.geometry.grid_kernel import NearestGrid

    assert NearestGrid.build(np.array([[0.0, 0, 0], [100.0, 100, 100]]), 0.001) is None
    one = NearestGrid.build(np.array([[0.0, 0, 1]]), 0.01)
    assert one is not None
    found, nearest = one.query(np.array([[0.0, 0, 1.005], [0.0, 0, 1.02], [1e9, -1e9, 0]]))
    assert found.tolist() == [True, False, False] and nearest.tolist() == [0, -1, -1]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_plane_kernel_counts_the_heights(seed, per_point):
    """The RANSAC scoring kernel counts inliers (|h| < d) and points behind (h < -d) of the heights
    h = n . p + offset, and its inlier mask is the plane's: checked against the heights from a matrix product,
    away from the tolerance (the kernel's fused multiply-adds may round the last bit differently)."""
    from gscan.geometry.plane_kernel import plane_counts, plane_inliers

    rng = np.random.default_rng(seed)
    S = rng.normal(0.0, 0.2, (int(rng.integers(1, 500)), 3)) + [0.0, 0.0, 1.0]
    S[: len(S) // 2, 2] = 1.0 + rng.normal(0.0, 0.002, len(S) // 2)  # half on a plane z = 1
    normals = rng.normal(size=(int(rng.integers(1, 40)), 3))
    normals[0] = [0.0, 0.0, -1.0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.normal(0.0, 0.5, len(normals))
    offsets[0] = 1.0
    d = 0.004 + 0.004 * rng.random(len(S)) if per_point else np.full(len(S), 0.005)
    h = S @ normals.T + offsets
    clear = np.abs(np.abs(h) - d[:, None]) > 1e-12
    inl, behind = plane_counts(S, normals, offsets, d)
    assert np.all(np.abs(inl - (np.abs(h) < d[:, None]).sum(0)) <= (~clear).sum(0))
    assert np.all(np.abs(behind - (h < -d[:, None]).sum(0)) <= (~clear).sum(0))
    for j in range(len(normals)):
        mask = plane_inliers(S, normals, offsets, j, d)
        assert mask.sum() == inl[j]
        np.testing.assert_array_equal(mask[clear[:, j]], (np.abs(h[:, j]) < d)[clear[:, j]])
    assert inl[0] >= len(S) // 3  # the plane z = 1 holds most of its half


def test_ransac_plane_same_with_and_without_the_fma_kernel(monkeypatch):
    """ransac_plane scores with the kernel where the CPU has fused multiply-adds, with a matrix product
    elsewhere: the same plane and inliers on a table with boxes on it."""
    import gscan.geometry.plane_kernel as kernel
    from gscan.geometry.plane import ransac_plane

    rng = np.random.default_rng(5)
    table = np.c_[rng.uniform(-0.5, 0.5, (3000, 2)), rng.normal(0.0, 0.001, 3000)]
    boxes = rng.uniform([-0.1, -0.1, -0.15], [0.1, 0.1, -0.02], (800, 3))  # towards the camera
    S = np.vstack([table, boxes]) + [0.0, 0.0, 1.0]
    runs = []
    for fma in (True, False):
        monkeypatch.setattr(kernel, "HAS_FMA", fma)
        runs.append(ransac_plane(S, 150, np.random.default_rng(0), 0.004, np.zeros(3), max_behind=0.05))
    (p1, m1), (p2, m2) = runs
    np.testing.assert_array_equal(p1.normal, p2.normal)
    assert p1.offset == p2.offset
    np.testing.assert_array_equal(m1, m2)
    assert abs(p1.normal[2]) > 0.99 and m1[:3000].mean() > 0.9 and m1[3000:].mean() < 0.1
