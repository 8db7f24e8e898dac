"""Pairwise registration (gscan.registration.pairwise) on rendered view pairs and on real RGB-D frames."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gscan.features import FeatureParams, Features, extract_features
from gscan.geometry.transforms import (
    inv_T,
    look_at,
    make_T,
    pose_error,
    rotation_angle_deg,
    rotvec_to_R,
    transform_points,
)
from gscan.io.camera import Intrinsics, RGBDFrame
from gscan.matching.gmatch import GMatchResult
from gscan.registration.noise import DepthNoise
from gscan.registration.pairwise import (
    METHODS,
    GuidedPool,
    PairResult,
    RegisterParams,
    frame_cloud,
    lists_to_verify,
    pose_by_support,
    register_features,
    relative_pose,
)

N_MESHES = 10
AZIMUTHS = (0.0, 15.0, 30.0, 45.0)  # 4 views per mesh -> pairs at 15, 30 and 45 deg: 6 per mesh, 60 in all


def _render_views(mesh_dir: Path, seed: int, azimuths=AZIMUTHS, table_kind: str = "newspaper"
                  ) -> list[tuple[RGBDFrame, np.ndarray]]:
    """(frame, T_world_cam) per azimuth: the mesh rests on a textured table, camera at 40/45 deg elevation
    looking at its centre from gscan.synth's default distance, 640x480 with noisy depth."""
    from gscan.synth import DEFAULT_INTRINSICS, SynthScene, default_distance, load_textured_mesh, rest_on_table

    mesh = load_textured_mesh(mesh_dir / "model_0.obj")
    T_world_obj = rest_on_table(mesh)
    c = transform_points(T_world_obj, mesh.center[None])[0]
    scene = SynthScene([(mesh, T_world_obj)], table=True, seed=seed, table_kind=table_kind)
    r = default_distance(mesh)
    out = []
    for k, az in enumerate(azimuths):
        el, a = np.radians(40.0 + 5.0 * (k % 2)), np.radians(az)
        T = look_at(c + r * np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)]), c)
        f = scene.render(T, DEFAULT_INTRINSICS, rng=np.random.default_rng([seed, k]))
        out.append((RGBDFrame(f"{mesh_dir.name}_{k}", f.color, f.depth, DEFAULT_INTRINSICS, f.mask, None), T))
    return out


@pytest.fixture(scope="module")
def rendered(meshes_dir):
    """[(views, features)] for the first N_MESHES shared meshes."""
    dirs = sorted(p for p in meshes_dir.iterdir() if (p / "model_0.obj").is_file())[:N_MESHES]
    assert len(dirs) == N_MESHES, f"need {N_MESHES} meshes in {meshes_dir}"
    out = []
    for i, d in enumerate(dirs):
        views = _render_views(d, seed=i)
        fp = FeatureParams(kind="rootsift", max_keypoints=1000)  # keeps the 60 whole-frame pairs fast
        out.append((views, [extract_features(v[0], fp) for v in views]))
    return out


def test_rendered_pairs_whole_frame(rendered):
    errs = []
    for views, feats in rendered:
        for i in range(len(views)):
            for j in range(i + 1, len(views)):
                T_gt = relative_pose(views[i][1], views[j][1])
                gap = rotation_angle_deg(T_gt[:3, :3])
                assert 10.0 < gap < 50.0  # the rendered views' ring: neighbours 20-40 deg apart (the pairs tested)
                r = register_features(feats[i], feats[j], RegisterParams(icp=False))
                errs.append(pose_error(r.T_tgt_src, T_gt) if r.T_tgt_src is not None else (np.inf, np.inf))
    errs = np.array(errs)
    assert len(errs) >= 60
    good = (errs[:, 0] < 3.0) & (errs[:, 1] < 0.01)
    assert good.mean() >= 0.9, f"{good.sum()} / {len(good)} pairs within 3 deg / 1 cm"


def test_icp_refinement_and_rules(rendered):
    views, feats = rendered[0]
    T_gt = relative_pose(views[0][1], views[1][1])
    cs, ct = frame_cloud(views[0][0], 4), frame_cloud(views[1][0], 4)
    r = register_features(feats[0], feats[1], RegisterParams(icp=True), clouds=(cs, ct))
    assert r.accepted and r.reason is None and r.fitness is not None and r.fitness >= 0.3
    deg, m = pose_error(r.T_tgt_src, T_gt)
    # ICP on noisy rendered depth: 0.29 deg / 1.8 mm measured; 1 deg / 5 mm catch a wrong or skipped refinement
    assert deg < 1.0 and m < 0.005
    # a target cloud that does not overlap: ICP finds no support -> rejected, match pose kept
    far = register_features(feats[0], feats[1], RegisterParams(icp=True), clouds=(cs, ct + [1.0, 0.0, 0.0]))
    assert not far.accepted and far.reason.startswith("icp fitness")
    # the match pose returned as is (no arithmetic): rtol 1e-7 is exactness
    np.testing.assert_allclose(far.T_tgt_src, far.T_match)
    # without clouds: accepted on the matches alone, rmse = Kabsch residual
    nc = register_features(feats[0], feats[1], RegisterParams(icp=True))
    # Kabsch residual over GMatch's list on rendered keypoints: 1.1 mm measured; 1 cm is the rule's own bound
    assert nc.accepted and nc.fitness is None and nc.rmse < 0.01


def test_rejection_rules():
    rng = np.random.default_rng(0)
    n = 300
    pts = np.array([0.0, 0.0, 0.6]) + rng.uniform(-0.2, 0.2, (n, 3))
    desc = rng.random((n, 128)).astype(np.float32)
    desc[:, 64:] = 0.0
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)

    def feats(p, d):
        return Features(np.zeros((len(p), 2), np.float32), p.astype(np.float32), d, "rootsift",
                        np.ones(len(p), np.float32))

    # unrelated descriptors (disjoint support: RootSIFT distance sqrt(2)) -> no candidate at all
    other = np.roll(desc, 64, axis=1)
    r = register_features(feats(pts, desc), feats(pts, other), RegisterParams(icp=False))
    assert not r.accepted and r.reason.startswith("too few matches")
    # identical keypoints under a known motion -> accepted, exact pose
    T = make_T(rotvec_to_R([0.1, -0.2, 0.05]), [0.02, 0.01, -0.03])
    r = register_features(feats(pts, desc), feats(transform_points(T, pts), desc), RegisterParams(icp=False))
    assert isinstance(r, PairResult) and r.accepted and r.n_matches == 24
    deg, m = pose_error(r.T_tgt_src, T)
    # keypoints are stored as float32 (6e-8 m rounding at 0.6 m): the pose is exact to ~1e-7; 0.01 deg (arccos
    # resolution 1.2e-6 deg) and 0.1 mm leave orders of magnitude
    assert deg < 0.01 and m < 1e-4
    # target points 6 mm noisy per axis, and a noise model that says so (s = 6 mm): accepted, the inliers'
    # RMS residual about sqrt(2.9) = 1.7 sigmas (chi, 3 axes, truncated at the 3.4 sigma gate)
    noisy = transform_points(T, pts) + rng.normal(0, 0.006, (n, 3))
    matched = DepthNoise(0.006 ** 2 / 2, 0.0, 0.0)
    r = register_features(feats(pts, desc), feats(noisy, desc), RegisterParams(noise=matched))
    assert r.accepted and 1.3 < r.rms_sigma < 2.1
    deg, m = pose_error(r.T_tgt_src, T)
    assert deg < 0.5 and m < 0.003  # ~300 inliers of 6 mm noise: the pose to a fraction of that
    # the same with a residual rule below what that noise gives: rule 2 fires
    r = register_features(feats(pts, desc), feats(noisy, desc), RegisterParams(noise=matched, max_rms=1.0))
    assert not r.accepted and r.reason.startswith("keypoint residual")
    with pytest.raises(ValueError):
        RegisterParams(method="magic")
    assert set(METHODS) == {"gmatch", "ratio", "mutual", "ransac", "lo-ransac", "fgr"}


def _padded(lists: list[list[tuple[int, int]]], L: int = 6) -> np.ndarray:
    out = np.full((len(lists), L, 2), -1, np.int32)
    for h, m in enumerate(lists):
        out[h, : len(m)] = m
    return out


def test_lists_to_verify_order_dedupe_and_min_len():
    a = [(0, 0), (1, 1), (2, 2), (3, 3), (4, 4)]
    b = [(5, 5), (6, 6), (7, 7), (8, 8)]
    c = [(9, 9), (6, 6), (7, 7), (8, 8)]
    hyps = [a, b, b[::-1], [(0, 1), (1, 2), (2, 3)], a, c]  # b reversed: the same pairs; one list of 3
    res = GMatchResult(np.array(a, np.int32), 0.05, hyp_start=_padded(hyps)[:, :3],
                       hyp_length=np.array([len(m) for m in hyps]),
                       hyp_cost=np.array([0.05, 0.03, 0.02, 0.0, 0.05, 0.03]),
                       hyp_pruned=np.zeros(len(hyps), bool), hyp_matches=_padded(hyps))
    lists, costs = lists_to_verify(res, 16, 4)
    # the winner, then by length, cost, search order: b reversed (0.02) before b (its duplicate) and c (0.03)
    assert [m.tolist() for m in lists] == [[list(p) for p in x] for x in (a, b[::-1], c)]
    assert costs == [0.05, 0.02, 0.03]
    assert len(lists_to_verify(res, 1, 4)[0]) == 2 and len(lists_to_verify(res, 0, 4)[0]) == 1
    assert len(lists_to_verify(res, 16, 5)[0]) == 1  # nothing else has 5 pairs
    assert len(lists_to_verify(res, 16, 3)[0]) == 4  # the 3-pair list joins


def test_pose_by_support_replaces_a_weakly_supported_winner():
    """GMatch's pick: 5 pairs consistent under a wrong motion, nothing else agrees with it. A 4-pair list under
    the true motion, with which n_true candidate pairs agree in all: it wins only with >= 1.5 x the support."""
    rng = np.random.default_rng(0)
    T, W = make_T(rotvec_to_R([0.2, -0.1, 0.3]), [0.03, 0.0, 0.01]), make_T(rotvec_to_R([0.0, 1.2, 0.0]), [0.1, 0, 0])
    ps = np.array([0.0, 0.0, 0.6]) + rng.uniform(-0.1, 0.1, (20, 3))
    pt = transform_points(T, ps)
    pt[15:] = transform_points(W, ps[15:])  # pairs (15..19): the wrong motion's
    wrong = np.stack([np.arange(15, 20)] * 2, 1).astype(np.int32)
    true4 = np.stack([np.arange(4)] * 2, 1).astype(np.int32)
    for n_true, chosen in ((12, 1), (7, 0)):  # 12 >= 1.5 x 5 replaces the pick; 7 < 7.5 does not
        idx = np.r_[np.arange(n_true), np.arange(15, 20)].astype(np.int32)
        dist = np.ones((20, 20))
        dist[idx, idx] = 0.0  # the pool: these pairs alone
        pool = GuidedPool(pt, dist, 0.5)
        k, T_est, kept, refined = pose_by_support(ps, pt, pool, pool, [wrong, true4], RegisterParams())
        assert k == chosen
        # exact float64 pairs: the pose is the motion to rounding (~1e-15 on its entries). Compared as matrices:
        # pose_error's angle comes from arccos((trace - 1) / 2), where one ulp of the trace near 3 already reads as
        # 1.2e-6 deg (1e-6 deg failed on an AMD CPU at 1.7e-6, two ulps)
        assert np.abs(T_est - (W, T)[chosen]).max() < 1e-12
        assert len(refined) == (5, n_true)[chosen] and len(kept) == (5, 4)[chosen]
    with pytest.raises(ValueError):
        pose_by_support(ps, pt, pool, pool, [], RegisterParams())


def test_support_counts_look_alike_pairs_but_inliers_stay_candidates():
    """The support check counts pairs up to support_eps_scale x eps_f: the true 4-pair list has 4 candidate pairs
    (distance 0.1) and 8 more seen less alike (0.8, beyond eps_f 0.6), so it outsupports the wrong 5-pair pick
    (12 >= 1.5 x 5) only with the looser bound; its refined inliers are still the 4 candidate pairs."""
    rng = np.random.default_rng(1)
    T, W = make_T(rotvec_to_R([0.1, 0.2, -0.3]), [0.02, 0.01, 0.0]), make_T(rotvec_to_R([1.0, 0.0, 0.2]), [0, 0.1, 0])
    ps = np.array([0.0, 0.0, 0.6]) + rng.uniform(-0.1, 0.1, (20, 3))
    pt = transform_points(T, ps)
    pt[15:] = transform_points(W, ps[15:])
    dist = np.ones((20, 20))
    dist[np.arange(4), np.arange(4)] = 0.1
    dist[np.arange(4, 12), np.arange(4, 12)] = 0.8
    dist[np.arange(15, 20), np.arange(15, 20)] = 0.1
    wrong = np.stack([np.arange(15, 20)] * 2, 1).astype(np.int32)
    true4 = np.stack([np.arange(4)] * 2, 1).astype(np.int32)
    strict, loose = GuidedPool(pt, dist, 0.6), GuidedPool(pt, dist, 0.9)
    assert pose_by_support(ps, pt, strict, strict, [wrong, true4], RegisterParams())[0] == 0
    k, T_est, kept, refined = pose_by_support(ps, pt, loose, strict, [wrong, true4], RegisterParams())
    # exact float64 pairs: far above arccos's 1.2e-6 deg resolution near 0 and any rounding of the refit
    assert k == 1 and pose_error(T_est, T)[0] < 1e-4
    np.testing.assert_array_equal(np.sort(refined, axis=0), true4)  # (in residual order)


@pytest.mark.parametrize("lookup", ["rows", "tree", "auto"])
@pytest.mark.parametrize("seed", range(4))
def test_the_pool_lookup_is_a_ball_query_filtered_by_descriptors(seed, lookup):
    """GuidedPool.near, by either lookup, returns what a k-d tree ball query over the target points, then the
    descriptor filter, returns, in the same order: per-point and shared radii, float32 and float64 distances, empty
    rows, and points exactly at the radius (kept: the test is <=, exact here in binary fractions)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    ns, nt = int(rng.integers(1, 60)), int(rng.integers(1, 80))
    pt = np.round(rng.uniform(-1, 1, (nt, 3)) * 8) / 8  # eighths: many exact distances
    q = np.round(rng.uniform(-1, 1, (ns, 3)) * 8) / 8
    dist = rng.uniform(0, 1, (ns, nt)).astype(np.float32 if seed % 2 else np.float64)
    dist[rng.uniform(size=ns) < 0.2] = 2.0  # rows with no pair under eps
    eps = 0.7 + 1e-9  # between two float32 values: compared in dist's type, as numpy does
    dist.flat[::7] = dist.dtype.type(eps)  # in float32, not under eps
    tree = cKDTree(pt)
    for tau in (0.5, np.round(rng.uniform(0.1, 1.2, ns) * 8) / 8):
        hits = tree.query_ball_point(q, tau, return_sorted=True)
        ii = np.repeat(np.arange(ns), [len(h) for h in hits])
        jj = np.array([j for h in hits for j in h], np.int64)
        ok = dist[ii, jj] < eps
        got = GuidedPool(pt, dist, eps, lookup).near(q, tau)
        np.testing.assert_array_equal(got[0], ii[ok])
        np.testing.assert_array_equal(got[1], jj[ok])
    # a 3-4-5 triangle in eighths: exactly at the radius, kept
    edge = GuidedPool(np.array([[0.375, 0.5, 0.0]]), np.zeros((1, 1), np.float32), eps, lookup).near(np.zeros((1, 3)),
                                                                                                     0.625)
    assert [list(a) for a in edge] == [[0], [0]]
    empty = GuidedPool(np.zeros((0, 3)), np.zeros((ns, 0)), eps, lookup).near(q, 0.5)
    assert len(empty[0]) == len(empty[1]) == 0


def test_support_check_fixes_a_rendered_pair(meshes_dir):
    """Object pixels only, a 60 deg view change of the fondant box on the wood table: GMatch's longest list is
    wrong (158 deg off), another hypothesis list has 1.5 x its support and is right. The pose choice is what is
    tested: the right list's 8 pairs on one face pin the pose to 2.8 deg / 2 cm only, so the edge is rejected
    as weak geometry (the pose is 3 deg / 2.5 cm off: a wrong pose by the rendered benchmark's bound)."""
    from gscan.features import descriptor_distances
    from gscan.geometry.kabsch import kabsch_trimmed
    from gscan.matching.gmatch import gmatch
    from gscan.registration.pairwise import refine_pose

    d = meshes_dir / "ReadytoUse_Rolled_Fondant_Pure_White_24_oz_box"
    views = _render_views(d, seed=16, azimuths=(0.0, 60.0), table_kind="wood")
    fs, ft = [extract_features(v[0], FeatureParams(kind="rootsift"), mask=v[0].mask) for v in views]
    T_gt = relative_pose(views[0][1], views[1][1])
    dist = descriptor_distances(fs.descriptors, ft.descriptors, fs.kind)
    res = gmatch(fs.points, ft.points, dist, 0.6)
    r = register_features(fs, ft, RegisterParams(icp=False))
    deg, m = pose_error(r.T_tgt_src, T_gt)
    assert deg < 5.0 and m < 0.05  # the right list (GMatch's own is 158 deg off); a short one: a few cm
    # the result is a runner-up list of the trace, reported consistently
    assert not np.array_equal(r.matches, res.matches) and r.n_matches == len(r.matches)
    assert any(np.array_equal(r.matches, t.matches) and r.cost == t.cost for t in res.trace)
    assert r.reason.startswith("weak geometry")
    # verify = 0: GMatch's own list, posed by kabsch_trimmed then refined, as before the support check
    r0 = register_features(fs, ft, RegisterParams(icp=False, verify=0))
    np.testing.assert_array_equal(r0.matches, res.matches)
    ps, pt = fs.points.astype(np.float64), ft.points.astype(np.float64)
    p = RegisterParams()
    src, dst = ps[res.matches[:, 0]], pt[res.matches[:, 1]]
    T0, _ = kabsch_trimmed(src, dst, p.trim_gate * p.noise.pair_sigma(src[:, 2], dst[:, 2]))
    pool = GuidedPool(pt, dist, p.support_eps_scale * 0.6)  # refined on look-alike pairs too
    T0, inl0 = refine_pose(ps, pt, pool, T0, p.refine_gates, p.noise, len(res.matches))
    np.testing.assert_allclose(r0.T_tgt_src, T0, atol=1e-12)
    assert pose_error(r0.T_tgt_src, T_gt)[0] > 90.0  # the paper's pick alone is wrong here


# ---------------------------------------------------------------------------------------------- real


def _trajectory(path: Path) -> list[np.ndarray]:
    """Open3D trajectory.log: per frame a header line then 4 rows of T_world_cam."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    return [np.array([[float(x) for x in lines[k + 1 + r].split()] for r in range(4)]) for k in range(0, len(lines), 5)]


def test_real_open3d_sequence_all_pairs(real_dir):
    from gscan.io import load_frame

    d = real_dir / "open3d_rgbd" / "RGBD"
    intr = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    colors, depths = sorted((d / "color").iterdir()), sorted((d / "depth").iterdir())
    Ts = _trajectory(d / "trajectory.log")
    assert len(colors) == len(depths) == len(Ts) == 5
    frames = [load_frame(c, dp, intr, depth_scale=0.001) for c, dp in zip(colors, depths, strict=True)]
    feats = [extract_features(f) for f in frames]
    for i in range(5):
        for j in range(i + 1, 5):
            T_gt = relative_pose(Ts[i], Ts[j])
            r = register_features(feats[i], feats[j], RegisterParams(icp=False))
            assert r.accepted, (i, j, r.reason)
            deg, m = pose_error(r.T_tgt_src, T_gt)
            motion_deg, motion_m = pose_error(np.eye(4), T_gt)
            # real frames 0.7-3 deg / 2-10 cm apart: registered within 0.11 deg / 5 mm of trajectory.log (measured)
            assert deg < 1.0 and m < 0.02, (i, j, deg, m)
            # and always closer to the truth than no motion at all
            assert deg < 0.5 * motion_deg and m < 0.5 * motion_m, (i, j, deg, m, motion_deg, motion_m)
    # inv_T(T) @ T of one pose: float64 rounding (np.allclose's atol 1e-8)
    assert np.allclose(inv_T(Ts[0]) @ Ts[0], np.eye(4))
