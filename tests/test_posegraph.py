"""Pose graph: drift removal on a synthetic ring, rejection of wrong edges, parts and thin evidence, loop
candidates."""
from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.geometry.transforms import inv_T, look_at, make_T, pose_error, rotvec_to_R, transform_points
from gscan.registration.posegraph import (
    GraphEdge,
    LoopParams,
    PoseGraphParams,
    bow_vectors,
    bridges,
    edge_chi2,
    edge_residual,
    information_from_points,
    optimize_pose_graph,
    select_loop_candidates,
    spanning_poses,
)

SIGMA = 0.002  # m, per-axis noise of the synthetic matched points


def ring_poses(n: int = 12, radius: float = 0.4, height: float = 0.3) -> list[np.ndarray]:
    """T_world_cam of n cameras on a ring, all looking at the origin."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        out.append(look_at(np.array([radius * np.cos(a), radius * np.sin(a), height]), np.zeros(3)))
    return out


def perturb(T: np.ndarray, rng: np.random.Generator, rot_deg: float, trans_m: float) -> np.ndarray:
    dR = rotvec_to_R(rng.normal(size=3) * np.radians(rot_deg))
    return make_T(dR, rng.normal(size=3) * trans_m) @ T


def points_info(n: int, rng: np.random.Generator, depth: float = 0.5) -> np.ndarray:
    """Information of a pose from n matched points spread over an object at `depth` in the source camera."""
    pts = np.array([0.0, 0.0, depth]) + rng.uniform(-0.1, 0.1, (n, 3))
    return information_from_points(pts, np.full(n, SIGMA))


def edge(gt: list[np.ndarray], i: int, j: int, rng: np.random.Generator, n: int, rot_deg: float = 0.05,
         trans_m: float = 0.0005, strong: bool = True, bias: np.ndarray | None = None) -> GraphEdge:
    T = perturb(inv_T(gt[j]) @ gt[i], rng, rot_deg, trans_m)
    if bias is not None:
        T = bias @ T
    return GraphEdge(i, j, T, points_info(n, rng), strong=strong, weight=n)


def ate(T_est: list[np.ndarray | None], T_gt: list[np.ndarray], ref: int = 0) -> float:
    """RMSE of camera-centre errors after anchoring both trajectories at node `ref`."""
    errs = [np.linalg.norm((inv_T(T_est[ref]) @ Te)[:3, 3] - (inv_T(T_gt[ref]) @ Tg)[:3, 3])
            for Te, Tg in zip(T_est, T_gt, strict=True) if Te is not None]
    return float(np.sqrt(np.mean(np.square(errs))))


def make_ring(seed: int = 0, n: int = 12, n_wrong: int = 3) -> tuple[list[np.ndarray], list[GraphEdge], int]:
    """Biased odometry (it drifts), right loop closures, `n_wrong` wrong ones (weaker, 25 deg / 8 cm off)."""
    rng = np.random.default_rng(seed)
    gt = ring_poses(n)
    bias = make_T(rotvec_to_R(np.radians([0.0, 0.3, 0.1])), [0.002, 0.0, 0.001])
    edges = [edge(gt, i, i + 1, rng, 200, bias=bias) for i in range(n - 1)]
    edges += [edge(gt, i, j, rng, 100) for i, j in [(0, 11), (0, 3), (3, 6), (6, 9), (9, 0), (2, 10), (1, 5), (4, 8)]]
    edges += [edge(gt, i, j, rng, 40, 25.0, 0.08) for i, j in [(2, 7), (5, 11), (1, 8)][:n_wrong]]
    return gt, edges, len(edges) - n_wrong


def test_ring_removes_drift_and_rejects_wrong_edges():
    gt, edges, first_wrong = make_ring()
    init = spanning_poses(12, list(edges[:11]))  # the odometry chain alone: it drifts
    before = ate(init, gt)
    res = optimize_pose_graph(12, edges, init)
    after = ate(res.T_world_node, gt)
    assert before > 0.01 and after < before / 3
    assert res.unregistered == [] and res.parts == []
    for k, rep in enumerate(res.edges):
        if k >= first_wrong:
            assert not rep.accepted and rep.reason.startswith("inconsistent"), f"wrong edge {rep.src}->{rep.tgt}"
        else:
            assert rep.accepted, f"good edge {rep.src}->{rep.tgt} rejected: {rep.reason}"
    np.testing.assert_allclose(res.T_world_node[0], init[0], atol=1e-9)  # the reference keeps its pose
    for i in range(12):
        deg, m = pose_error(res.T_ref_node(i), inv_T(gt[0]) @ gt[i])
        assert deg < 1.0 and m < 0.01


def test_a_strong_wrong_cluster_does_not_drag_the_right_edges_out():
    """Four wrong edges that agree with each other (one node seen flipped 180 degrees) against right edges:
    the re-weighted start keeps the poses where the right edges put them, and only the wrong ones go."""
    rng = np.random.default_rng(2)
    gt = ring_poses(8)
    flip = make_T(rotvec_to_R([0.0, 0.0, np.pi]), [0.0, 0.0, 0.0])
    gt_flipped = list(gt)
    gt_flipped[4] = gt[4] @ flip
    edges = [edge(gt, i, i + 1, rng, 300) for i in range(7)] + [edge(gt, 0, 7, rng, 300), edge(gt, 2, 6, rng, 150)]
    n_right = len(edges)
    edges += [edge(gt_flipped, i, 4, rng, 40) for i in (1, 2, 6, 7)]  # node 4 seen flipped: they agree
    res = optimize_pose_graph(8, edges, spanning_poses(8, edges))
    assert [r.accepted for r in res.edges] == [True] * n_right + [False] * 4
    assert res.registered == list(range(8))


def test_parts_and_thin_evidence():
    """Two clusters joined by one edge: a weak bridge is cut (both parts reported, the larger registered, no
    pose for the smaller); a strong one keeps them together. An isolated node gets no pose either."""
    rng = np.random.default_rng(3)
    gt = ring_poses(10)
    a = [edge(gt, i, j, rng, 100) for i, j in [(0, 1), (1, 2), (2, 3), (0, 2), (1, 3), (3, 4), (2, 4)]]
    b = [edge(gt, i, j, rng, 100) for i, j in [(6, 7), (7, 8), (6, 8)]]
    for strong, registered in ((False, [0, 1, 2, 3, 4]), (True, [0, 1, 2, 3, 4, 6, 7, 8])):
        link = edge(gt, 4, 6, rng, 8, strong=strong)
        res = optimize_pose_graph(10, a + [link] + b, spanning_poses(10, a + [link] + b))
        assert res.registered == registered
        assert res.edges[len(a)].accepted == strong
        if not strong:
            assert res.edges[len(a)].reason.startswith("the only link")
            assert res.parts == [[6, 7, 8]] and "separate part of 3 frames" in res.node_reasons[6]
            assert all(not r.accepted for r in res.edges[len(a) + 1:])
        else:
            assert res.parts == []
        assert res.T_world_node[5] is None and res.T_world_node[9] is None  # no edge at all


def test_a_node_held_by_one_of_two_disagreeing_edges_is_left_out():
    rng = np.random.default_rng(5)
    gt = ring_poses(6) + [look_at(np.array([0.0, 0.5, 0.5]), np.zeros(3))]
    edges = [edge(gt, i, j, rng, 100) for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (0, 3)]]
    edges += [edge(gt, 1, 6, rng, 50, 40.0, 0.2), edge(gt, 4, 6, rng, 50, 40.0, 0.2)]
    res = optimize_pose_graph(7, edges, spanning_poses(7, edges))
    reps6 = [r for r in res.edges if 6 in (r.src, r.tgt)]
    assert all(not r.accepted for r in reps6)
    assert any(r.reason.startswith("the only edge left") for r in reps6)
    assert res.registered == list(range(6))


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 8), st.lists(st.tuples(st.integers(0, 7), st.integers(0, 7)), max_size=12))
def test_bridges_match_brute_force(n, pairs):
    pairs = [(a % n, b % n) for a, b in pairs if a % n != b % n]

    def n_components(es):
        parent = list(range(n))

        def find(x):
            while parent[x] != x:
                x = parent[x]
            return x
        for a, b in es:
            parent[find(a)] = find(b)
        return len({find(x) for x in range(n)})

    base = n_components(pairs)
    brute = {k for k in range(len(pairs)) if n_components(pairs[:k] + pairs[k + 1:]) > base}
    assert bridges(n, pairs) == brute


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_chi2_is_the_points_misfit_in_the_source_frame(seed):
    """For a small residual motion, e^T I e equals the sum of the squared misfits of the source points over
    their variance (Gauss-Newton's cost), with I from the SOURCE points: the frame open3d's residual is in."""
    rng = np.random.default_rng(seed)
    pts_s = np.array([0.0, 0.0, 0.6]) + rng.uniform(-0.2, 0.2, (50, 3))
    X = make_T(rotvec_to_R(rng.normal(size=3) * 0.3), rng.normal(size=3) * 0.2)  # measured T_tgt_src
    delta = make_T(rotvec_to_R(rng.normal(size=3) * 1e-4), rng.normal(size=3) * 1e-4)
    T_world_src = make_T(rotvec_to_R(rng.normal(size=3)), rng.normal(size=3))
    T_world_tgt = T_world_src @ delta @ inv_T(X)  # the node poses see the source moved by delta
    e = GraphEdge(0, 1, X, information_from_points(pts_s, np.full(50, SIGMA)))
    cost = np.sum(np.square(transform_points(delta, pts_s) - pts_s)) / SIGMA ** 2
    assert abs(edge_chi2(T_world_src, T_world_tgt, e) - cost) < 1e-3 * cost
    deg, m = edge_residual(T_world_src, T_world_tgt, X)
    assert deg < 0.05 and m < 1e-3


def test_deterministic():
    gt, edges, _ = make_ring(seed=3)
    init = spanning_poses(12, edges)
    a = optimize_pose_graph(12, edges, init)
    b = optimize_pose_graph(12, edges, init)
    for Ta, Tb in zip(a.T_world_node, b.T_world_node, strict=True):
        np.testing.assert_array_equal(Ta, Tb)
    assert [(r.accepted, r.reason) for r in a.edges] == [(r.accepted, r.reason) for r in b.edges]


def test_params_validated():
    import pytest

    for bad in ({"alpha": 0.0}, {"alpha": 1.0}, {"max_rounds": 0}):
        with pytest.raises(ValueError):
            PoseGraphParams(**bad)
    assert list(itertools.islice(bridges(3, [(0, 1), (1, 2), (2, 0)]), 1)) == []


def test_residual_convention_matches_open3d_edge_semantics():
    """Edge (i, j, T_j_i): T_j_i maps frame-i points into frame j, like registration_icp(source=i, target=j)."""
    gt = ring_poses(4)
    T_1_0 = inv_T(gt[1]) @ gt[0]
    p0 = np.array([0.01, 0.02, 0.3])
    # a point moved through the relative transform: float64 rounding of O(1) products
    np.testing.assert_allclose(gt[1][:3, :3] @ (T_1_0[:3, :3] @ p0 + T_1_0[:3, 3]) + gt[1][:3, 3],
                               gt[0][:3, :3] @ p0 + gt[0][:3, 3], atol=1e-12)
    assert edge_residual(gt[0], gt[1], T_1_0) == (0.0, 0.0) or max(edge_residual(gt[0], gt[1], T_1_0)) < 1e-9
    deg, m = edge_residual(gt[0], gt[1], inv_T(T_1_0))
    assert deg > 1.0


@settings(deadline=None, max_examples=15)
@given(st.integers(0, 10_000))
def test_information_from_points_matches_open3d(seed):
    """Unweighted, it is open3d's get_information_matrix_from_point_clouds on the same points; weighted, each
    point counts 1 / sigma^2."""
    import open3d as o3d

    p = np.random.default_rng(seed).normal(size=(50, 3))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    ref = np.asarray(o3d.pipelines.registration.get_information_matrix_from_point_clouds(pc, pc, 1e-3, np.eye(4)))
    np.testing.assert_allclose(information_from_points(p), ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(information_from_points(p, np.full(50, 0.5)), 4.0 * ref, rtol=1e-9, atol=1e-9)


def test_loop_candidates_overlap_bounded_deterministic():
    gt = ring_poses(12)
    params = LoopParams(max_per_node=2, min_index_gap=2, max_angle_deg=70.0, max_baseline=1.0)
    cands = select_loop_candidates(gt, None, existing=[(0, 11)], params=params)
    assert cands, "ring views overlap with their neighbours two steps away"
    counts = np.zeros(12, dtype=int)
    for c in cands:
        assert c.i < c.j and c.j - c.i >= 2 and (c.i, c.j) != (0, 11)
        # the loop-candidate rule's own bounds: at most 70 deg and 0.5 m apart (the default depth, 0.5 m)
        assert c.angle_deg <= 70.0 and c.distance_m <= 0.5 and c.reason == "overlap"
        counts[[c.i, c.j]] += 1
    assert counts.max() <= 2
    # opposite views (180 deg apart) never qualify by geometry
    assert all(abs(c.i - c.j) != 6 for c in cands)
    again = select_loop_candidates(gt, None, existing=[(0, 11)], params=params)
    assert [(c.i, c.j, c.score) for c in cands] == [(c.i, c.j, c.score) for c in again]


def test_loop_candidates_overlap_scales_with_the_depth_the_views_look_at():
    """A ring of views around an object 1.5 m away overlaps as the same ring 0.5 m away does: its camera centres
    are three times farther apart, and so is the depth the views look at. Given 0.5 m depths, the far ring's
    neighbours (0.78 m apart) do not qualify."""
    params = LoopParams(max_per_node=2, min_index_gap=2)
    near = ring_poses(10, radius=0.5, height=0.3)
    far = ring_poses(10, radius=1.5, height=0.9)
    depth = float(np.hypot(0.5, 0.3))
    a = select_loop_candidates(near, None, params=params, depths=[depth] * 10)
    b = select_loop_candidates(far, None, params=params, depths=[3 * depth] * 10)
    assert a and [(c.i, c.j) for c in a] == [(c.i, c.j) for c in b]
    np.testing.assert_allclose([c.score for c in a], [c.score for c in b], atol=1e-12)
    assert not select_loop_candidates(far, None, params=params, depths=[depth] * 10)


def test_loop_candidates_appearance():
    """Frames 0 and 7 share a descriptor cluster nobody else has: appearance proposes the pair."""
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(10, 32)).astype(np.float32) * 5
    desc = []
    for k in range(10):
        words = [k % 5, (k + 1) % 5] if k not in (0, 7) else [8, 9]
        d = np.concatenate([centres[w] + rng.normal(size=(40, 32)).astype(np.float32) * 0.1 for w in words])
        desc.append(d)
    far = [make_T(np.eye(3), [10.0 * k, 0, 0]) for k in range(10)]  # no geometric overlap at all
    H = bow_vectors(desc, vocabulary_size=16, seed=0)
    assert H.shape == (10, 16)
    # L2-normalised float32 histograms: float32 rounding (6e-8) over 16 bins
    np.testing.assert_allclose(np.linalg.norm(H, axis=1), 1.0, atol=1e-5)
    cands = select_loop_candidates(far, desc, params=LoopParams(vocabulary_size=16, appearance_top_k=1,
                                                                min_similarity=0.9))
    pairs = {(c.i, c.j) for c in cands}
    assert (0, 7) in pairs
    assert all(c.reason == "appearance" for c in cands)
    # ORB-like binary descriptors are accepted too
    Hb = bow_vectors([rng.integers(0, 256, size=(30, 32), dtype=np.uint8) for _ in range(4)], 8)
    assert Hb.shape == (4, 8) and np.all(np.isfinite(Hb))


def test_subtle_wrong_closure_rejected():
    """A loop closure off by 12 deg about the optical axis (weakly constrained direction) is rejected."""
    gt, edges, _ = make_ring(seed=2, n_wrong=0)
    rng = np.random.default_rng(9)
    edges.append(GraphEdge(2, 7, make_T(rotvec_to_R(np.radians([0, 0, 12.0])), [0, 0, 0]) @ inv_T(gt[7]) @ gt[2],
                           points_info(100, rng), weight=100))
    res = optimize_pose_graph(12, edges, spanning_poses(12, edges[:11]))
    rejected = [(r.src, r.tgt) for r in res.edges if not r.accepted]
    assert rejected == [(2, 7)], rejected
    assert res.edges[-1].residual_deg > 5.0
    assert ate(res.T_world_node, gt) < 0.01


def test_trivial_graphs():
    res = optimize_pose_graph(1, [], [np.eye(4)])
    assert res.registered == [0] and res.edges == []
    res = optimize_pose_graph(2, [], [np.eye(4), None])
    assert res.registered == [0] and res.unregistered == [1]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_information_moves_between_frames_by_the_adjoint(seed):
    """The information of a pose from matched points, given in the target frame, turned into the source frame's
    (`in_source_frame`), is the information from the same points in the source frame."""
    from gscan.registration.dense import in_source_frame

    rng = np.random.default_rng(seed)
    pts_s = rng.normal(size=(30, 3))
    T = make_T(rotvec_to_R(rng.normal(size=3)), rng.normal(size=3))
    info_t = information_from_points(transform_points(T, pts_s))
    np.testing.assert_allclose(in_source_frame(info_t, T), information_from_points(pts_s), rtol=1e-7, atol=1e-7)


@settings(deadline=None, max_examples=25)
@given(st.integers(0, 10_000), st.sampled_from([None, 0.0, 1e-7, np.pi, np.pi - 1e-9]))
def test_a_stack_of_edges_gives_each_edge_its_own_chi2(seed, angle):
    """The graph's stacked chi^2 (rotation vectors, inverses and products over all edges at once) gives each edge
    the bits `edge_chi2` gives it alone, and rotation vectors those of scipy's to 1e-9, at angles near 0 and 180
    deg (angle: every edge's residual rotation, None: random)."""
    from scipy.spatial.transform import Rotation

    from gscan.registration.posegraph import _Graph, _rotvecs

    rng = np.random.default_rng(seed)
    n = 6
    poses = [make_T(rotvec_to_R(rng.normal(size=3)), rng.normal(size=3)) for _ in range(n)]
    edges = []
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (0, 3)]:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        D = make_T(rotvec_to_R(axis * (rng.uniform(0, 3) if angle is None else angle)), rng.normal(size=3) * 0.01)
        edges.append(GraphEdge(i, j, inv_T(poses[j]) @ poses[i] @ inv_T(D), points_info(30, rng),
                               depth=rng.uniform(0.3, 2.0)))
    g = _Graph(n, edges, poses, PoseGraphParams())
    for floor in (0.0, 0.01):
        g.set_floor(floor)
        got = g.chi2s(list(range(len(edges))))
        for k, ed in enumerate(edges):
            one = _Graph(n, [ed], poses, PoseGraphParams())
            one.set_floor(floor)
            assert got[k] == one.chi2(0)
            if floor == 0.0:
                assert got[k] == edge_chi2(poses[ed.src], poses[ed.tgt], ed)
    R = np.array([rotvec_to_R(rng.normal(size=3)) for _ in range(5)] + [np.eye(3)])
    ref = Rotation.from_matrix(R).as_rotvec()
    np.testing.assert_allclose(_rotvecs(R), ref, atol=1e-9)
    half = np.array([rotvec_to_R(np.array([0.0, 0.0, np.pi])),
                     rotvec_to_R(np.array([1.0, 1.0, 0.0]) / np.sqrt(2) * np.pi)])
    got = _rotvecs(half)
    assert np.allclose(np.linalg.norm(got, axis=1), np.pi)
    for r, Rk in zip(got, half, strict=True):
        np.testing.assert_allclose(rotvec_to_R(r), Rk, atol=1e-9)
