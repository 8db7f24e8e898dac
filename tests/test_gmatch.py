"""GMatch matcher: unit tests of delta / g / flip-over / Step, synthetic robustness, determinism.

Synthetic generator (`_problem`, seeded): n_in source keypoints uniform in a 0.30 x 0.24 x 0.10 m
box 0.7 m in front of the camera (a visible object surface region), mapped to the target by a rigid
motion (rotation of 5-30 deg about a random axis, translation up to 5 cm) plus N(0, 1 mm) noise;
n_out extra outlier keypoints on each side. The descriptor distance matrix is built directly:
true pairs and `n_false` wrong candidates per source keypoint are below eps_f = 1, every other pair is 2.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.geometry.kabsch import kabsch
from gscan.geometry.transforms import make_T, pose_error, rotvec_to_R, transform_points
from gscan.matching.gmatch import (
    Candidates,
    GMatchParams,
    default_eps_f,
    extract_candidates,
    gmatch,
    search_candidates,
    step,
)
from gscan.matching.kernel import flips, keep_consistent

Z = np.array([0.0, 0.0, 1.0])


def _motion(rng: np.random.Generator, max_deg: float = 30.0) -> np.ndarray:
    ax = rng.normal(size=3)
    ax /= np.linalg.norm(ax)
    ang = np.radians(rng.uniform(5.0, max_deg))
    c = np.array([0.0, 0.0, 0.7])
    R = rotvec_to_R(ax * ang)
    return make_T(R, c - R @ c + rng.uniform(-0.05, 0.05, 3))


def _box(rng, n):
    return np.array([0.0, 0.0, 0.7]) + rng.uniform([-0.15, -0.12, -0.05], [0.15, 0.12, 0.05], (n, 3))


def _problem(seed: int, n_in: int = 40, n_out: int = 20, n_false: int = 4, true_lo: float = 0.0,
             true_hi: float = 0.6, false_lo: float = 0.0, false_hi: float = 1.0):
    """Returns (pts_s [Ns x 3], pts_t [Nt x 3], dist [Ns x Nt], T_t_s, gt {src: tgt})."""
    rng = np.random.default_rng(seed)
    T = _motion(rng)
    ns = nt = n_in + n_out
    ps = _box(rng, ns)
    perm = rng.permutation(nt)
    pt = np.empty((nt, 3))
    pt[perm[:n_in]] = transform_points(T, ps[:n_in]) + rng.normal(0, 0.001, (n_in, 3))
    pt[perm[n_in:]] = transform_points(T, _box(rng, n_out))
    dist = np.full((ns, nt), 2.0, np.float32)
    dist[np.arange(n_in), perm[:n_in]] = rng.uniform(true_lo, true_hi, n_in)
    for i in range(ns):
        wrong = rng.choice(nt, n_false, replace=False)
        wrong = wrong[wrong != (perm[i] if i < n_in else -1)]
        dist[i, wrong] = rng.uniform(false_lo, false_hi, len(wrong))
    return ps, pt, dist, T, {i: int(perm[i]) for i in range(n_in)}


def _ok(res, ps, pt, T, max_deg=1.0, max_m=0.005) -> bool:
    if len(res.matches) < 3:
        return False
    T_est = kabsch(ps[res.matches[:, 0]], pt[res.matches[:, 1]])
    deg, m = pose_error(T_est, T)
    return deg < max_deg and m < max_m


# ---------------------------------------------------------------------------------------------- units


def _cands(pairs):
    p = np.asarray(pairs, dtype=np.int32)
    return p[:, 0].copy(), p[:, 1].copy()


def _members(ps, pt, pairs, cf=None):
    """Member set (F, I, G) of the kernel for candidate pairs [(i, j)] with zero running cost."""
    p = np.asarray(pairs)
    F = np.vstack([ps[p[:, 0]].T, pt[p[:, 1]].T, np.ones(len(p)) if cf is None else cf])
    I = np.vstack([np.arange(len(p)), p[:, 0], p[:, 1]]).astype(np.int32)
    return np.ascontiguousarray(F), I, np.zeros(len(p))


def _keep(F, I, G, k_m, eps, eta):
    """(kept candidate indices, their g, argmin position) of keep_consistent, written to fresh arrays."""
    n = F.shape[1]
    Fo, Io, Go = np.empty_like(F), np.empty_like(I), np.empty_like(G)
    w, arg, _ = keep_consistent(F, I, G, n, Fo, Io, Go, k_m, eps, eta, np.empty(n), np.empty(n, bool))
    return list(Io[0, :w]), Go[:w], arg


def test_keep_consistent_delta_is_the_relative_error_with_a_hard_margin():
    ps = np.array([[0, 0, 1.0], [0.1, 0, 1.0], [0.3, 0, 1.0]])
    pt = np.array([[0, 0, 1.0], [0.104, 0, 1.0], [0.32, 0, 1.0]])
    F, I, G = _members(ps, pt, [(0, 0), (1, 1), (2, 2), (0, 1)])
    # |0.1 - 0.104| = 4 mm < eta = 1 cm -> 0.004 / 0.1; |0.3 - 0.32| = 2 cm >= eta -> never consistent;
    # a pair sharing a keypoint with the anchor is never combined; the anchor itself is not kept
    kept, g, arg = _keep(F, I, G, 0, 0.08, 0.01)
    # a relative distance error of hand-built points: float64 rounding of O(0.1) values
    assert kept == [1] and g == pytest.approx([0.04], abs=1e-9) and arg == 0
    kept, g, _ = _keep(F, I, G, 0, 0.08, 0.03)  # eta 3 cm: 2 cm / 0.3 m passes
    assert kept == [1, 2] and g == pytest.approx([0.04, 0.02 / 0.3], abs=1e-9)  # 2 cm / 0.3 m: float64 rounding
    assert _keep(F, I, G, 0, 0.03, 0.03)[0] == []  # both relative errors above eps
    # the depth factor scales the margin: a 2 cm error passes eta 1 cm at factor 2.5
    F2, I2, G2 = _members(ps, pt, [(0, 0), (1, 1), (2, 2), (0, 1)], cf=np.array([1.0, 1.0, 2.5, 1.0]))
    assert _keep(F2, I2, G2, 0, 0.08, 0.01)[0] == [1, 2]
    # g is the running max: a member's earlier cost is kept when larger; argmin picks the smaller g
    G2[1] = 0.07
    kept, g, arg = _keep(F2, I2, G2, 0, 0.08, 0.01)
    assert g == pytest.approx([0.07, 0.02 / 0.3], abs=1e-9) and arg == 1  # as above: float64 rounding


def test_flip_test_mirror_and_collinear():
    a, b, c = [0.0, 0, 1], [0.1, 0, 1], [0, 0.1, 1]
    ps = np.array([a, b, c])
    mirror = np.array([[0.0, 0, 1], [-0.1, 0, 1], [0, 0.1, 1]])  # x -> -x: seen from the other side
    rot = transform_points(make_T(rotvec_to_R([0, 0, 0.7]), [0.02, 0, 0.1]), ps)  # in-plane rotation
    args = (Z, Z, 0.8, 0.1)
    assert flips(ps, mirror, 0, 1, 2, 0, 1, 2, *args)
    assert not flips(ps, rot, 0, 1, 2, 0, 1, 2, *args)
    # near-collinear triples are not decided
    col = np.array([[0.0, 0, 1], [0.1, 0, 1], [0.2, 0.001, 1]])
    col_m = col * np.array([-1, 1, 1])
    assert not flips(col, col_m, 0, 1, 2, 0, 1, 2, *args)
    # a triangle seen edge-on (normal perpendicular to view) is below the flip margin
    edge = np.array([[0.0, 0, 1], [0.1, 0, 1], [0, 0.0, 1.1]])
    tilt = transform_points(make_T(rotvec_to_R([0.2, 0, 0]), [0, 0, 0]), edge)
    assert not flips(edge, tilt, 0, 1, 2, 0, 1, 2, *args)


def test_step_hand_made():
    # square source; target = source shifted. Matches (0,0), (1,1). Candidates for point 2:
    # its true partner (cost ~0), a mirrored partner (flip-over), a far one (g > eps_c).
    ps = np.array([[0, 0, 1.0], [0.1, 0, 1.0], [0.1, 0.1, 1.0], [0.0, 0.1, 1.0]])
    pt = np.vstack([ps + [0.05, 0, 0], [[0.15, -0.1, 1.0], [0.5, 0.5, 1.0]]])  # 4: mirror of 2, 5: far
    pt[3, 1] += 0.002  # (3, 3) is consistent with cost 0.02
    cand = Candidates(*_cands([(2, 5), (2, 4), (2, 2), (3, 3)]), np.array([0.1, 0.2, 0.3, 0.4], np.float32))
    p = GMatchParams(eta_depth=False)
    m = np.array([[0, 0], [1, 1]])
    assert step(ps, pt, cand, m, p) == 2  # (2,2): cost 0 beats (3,3) at 0.02
    # without the true partner the mirror is rejected by the flip test, (3,3) is taken
    cand2 = Candidates(*_cands([(2, 5), (2, 4), (3, 3)]), np.array([0.1, 0.2, 0.4], np.float32))
    assert step(ps, pt, cand2, m, p) == 2
    # the distance-only constraint accepts the mirror (equal distances)
    assert step(ps, pt, cand2, m, GMatchParams(eta_depth=False, constraint="distance")) == 1
    # nothing consistent -> None
    cand3 = Candidates(*_cands([(2, 5), (0, 3)]), np.array([0.1, 0.2], np.float32))
    assert step(ps, pt, cand3, m, p) is None


@pytest.mark.parametrize("constraint", ["flip", "triple", "distance"])
@pytest.mark.parametrize("order,eta_depth", [("distance", False), ("ratio", True)])
def test_kernel_growth_equals_repeated_step(constraint, order, eta_depth):
    """With a single hypothesis (T = K2 = K3 = 1) the kernel's greedy growth is Algorithm 1 repeated."""
    checked = grown = 0
    for seed in range(30):
        ps, pt, dist, T, gt = _problem(seed, n_in=30, n_out=10, n_false=6)
        params = GMatchParams(T=1, K2=1, K3=1, L=12, eta_depth=eta_depth, constraint=constraint, order=order)
        cand = extract_candidates(dist, 1.0, order)
        res = search_candidates(ps, pt, cand, params)
        if len(res.hyp_start) == 0:  # the single seed had no valid triangle
            continue
        checked += 1
        m = res.hyp_start[0]
        while len(m) < params.L:
            k = step(ps, pt, cand, m, params)
            if k is None:
                break
            m = np.vstack([m, [[cand.src[k], cand.tgt[k]]]])
        np.testing.assert_array_equal(res.matches, m)
        grown += len(m) > 3
    assert checked >= 8 and grown >= 3  # not vacuous: several single hypotheses grew


def test_extract_candidates_order_and_threshold():
    d = np.array([[0.5, 0.1, 0.9], [0.1, 0.95, 0.3]], np.float32)
    c = extract_candidates(d, 0.6, "distance")
    assert list(zip(c.src, c.tgt, strict=True)) == [(0, 1), (1, 0), (1, 2), (0, 0)]  # ties by row-major index
    assert np.all(np.diff(c.dist) >= 0)


def test_extract_candidates_ratio_order_puts_distinctive_pairs_first():
    # row 0: a repeated pattern (0.10 vs 0.11: ratio 0.91); row 1: one clear match (0.2 vs 0.9: ratio 0.22)
    d = np.array([[0.10, 0.11, 0.9], [0.2, 0.9, 0.95]], np.float32)
    by_dist = extract_candidates(d, 0.5, "distance")
    by_ratio = extract_candidates(d, 0.5, "ratio")
    assert list(zip(by_dist.src, by_dist.tgt, strict=True)) == [(0, 0), (0, 1), (1, 0)]
    assert list(zip(by_ratio.src, by_ratio.tgt, strict=True)) == [(1, 0), (0, 0), (0, 1)]
    np.testing.assert_array_equal(by_ratio.dist, np.float32([0.2, 0.10, 0.11]))  # distances travel along
    one = extract_candidates(d[:, :1], 0.5, "ratio")  # a single target: rows keyed by d / eps_f
    assert list(zip(one.src, one.tgt, strict=True)) == [(0, 0), (1, 0)]
    with pytest.raises(ValueError):
        extract_candidates(d, 0.5, "nope")


@given(seed=st.integers(0, 10_000), levels=st.integers(2, 50), negative=st.booleans())
@settings(max_examples=60, deadline=None)
def test_extract_candidates_matches_stable_argsort(seed, levels, negative):
    """The packed-key sort gives the order of a stable argsort (many ties, -0.0, negative values)."""
    rng = np.random.default_rng(seed)
    d = (rng.integers(0, levels, (int(rng.integers(1, 40)), int(rng.integers(1, 40)))) / levels).astype(np.float32)
    d[rng.random(d.shape) < 0.05] = -0.0
    if negative:
        d -= 0.1
    c = extract_candidates(d, 0.6, "distance")
    flat = np.flatnonzero(d < 0.6)
    order = np.argsort(d.reshape(-1)[flat], kind="stable")
    np.testing.assert_array_equal(c.src, flat[order] // d.shape[1])
    np.testing.assert_array_equal(c.tgt, flat[order] % d.shape[1])
    np.testing.assert_array_equal(c.dist, d.reshape(-1)[flat[order]])


def test_inputs_validated():
    with pytest.raises(ValueError):
        gmatch(np.zeros((3, 2)), np.zeros((3, 3)), np.zeros((3, 3)), 1.0)
    with pytest.raises(ValueError):
        gmatch(np.zeros((3, 3)), np.zeros((4, 3)), np.zeros((3, 3)), 1.0)
    with pytest.raises(ValueError):
        GMatchParams(constraint="nope")
    with pytest.raises(ValueError):
        GMatchParams(eps_c=1.0)  # a relative distance error: (0, 1)
    with pytest.raises(ValueError):
        default_eps_f("akaze")
    empty = gmatch(np.zeros((3, 3)), np.zeros((3, 3)), np.full((3, 3), 5.0), 1.0)
    assert empty.matches.shape == (0, 2) and empty.cost == 1.0


# ------------------------------------------------------------------------------------------ synthetic


def _rate(make, params, n=100, **kw):
    good = 0
    for seed in range(n):
        ps, pt, dist, T, _ = make(seed)
        res = gmatch(ps, pt, dist, 1.0, params)
        good += _ok(res, ps, pt, T, **kw)
    return good / n


@pytest.mark.parametrize("constraint", ["flip", "triple"])
def test_outliers_90_percent(constraint):
    # 40 true pairs among 40 + 20 keypoints per side, 6 wrong candidates per source keypoint whose
    # descriptor distances overlap the true ones: 40 / 400 candidates are right (90 % outliers).
    def make(seed):
        return _problem(1000 + seed, n_in=40, n_out=20, n_false=6)
    assert _rate(make, GMatchParams(constraint=constraint)) >= 0.9


def test_repetitive_descriptors():
    # "visual words": every source keypoint has 7 equally similar candidates (at most one right):
    # 40 right among 340 candidates, and descriptor order carries no information.
    def make(seed):
        return _problem(2000 + seed, n_in=40, n_out=10, n_false=6, true_lo=0.2, true_hi=0.5,
                        false_lo=0.2, false_hi=0.5)
    assert _rate(make, GMatchParams()) >= 0.9


def _mirror_problem(seed: int, thickness: float):
    """Target holds the true image of the source and a left-right mirrored copy (x -> -x, shifted)
    whose descriptors are closer and whose points are noise-free, so pairwise distances alone prefer
    the mirror. `thickness` (m) of the layout along the view axis: ~0 is a printed face of a box seen
    from the front (the mirror is then a rigid 180 deg turn of the plane, seen from behind: only the
    flip-over test can reject it); 0.1 m is a 3D layout (the triple product rejects the mirror)."""
    rng = np.random.default_rng(3000 + seed)
    n = 40
    T = _motion(rng, max_deg=20.0)
    ps = np.array([0.0, 0.0, 0.7]) + rng.uniform([-0.15, -0.12, -thickness / 2], [0.15, 0.12, thickness / 2], (n, 3))
    true_t = transform_points(T, ps) + rng.normal(0, 0.001, (n, 3))
    mir = ps * np.array([-1.0, 1.0, 1.0]) + np.array([0.4, 0.0, 0.0])
    pt = np.vstack([true_t, mir])
    dist = np.full((n, 2 * n), 2.0, np.float32)
    dist[np.arange(n), np.arange(n)] = rng.uniform(0.0, 0.6, n)
    dist[np.arange(n), n + np.arange(n)] = rng.uniform(0.0, 0.3, n)
    return ps, pt, dist, T, None


def test_mirrored_planar_layout_resolved_by_flip_over():
    def make(seed):
        return _mirror_problem(seed, thickness=0.002)
    assert _rate(make, GMatchParams(constraint="flip")) >= 0.9
    assert _rate(make, GMatchParams(constraint="distance"), n=20) <= 0.1  # the same inputs defeat distances alone


def test_mirrored_3d_layout_resolved_by_triple_product():
    def make(seed):
        return _mirror_problem(seed, thickness=0.1)
    assert _rate(make, GMatchParams(constraint="triple")) >= 0.9
    # distances alone cannot tell a mirror image: the ablation fails nearly every mirrored problem
    assert _rate(make, GMatchParams(constraint="distance"), n=20) <= 0.1


@pytest.mark.parametrize("tilt_deg", [0.0, 45.0, 60.0, 75.0])
def test_plane_seen_from_behind(tilt_deg):
    """A textured plane turned 180 deg about an axis in the plane keeps every pairwise distance (a rigid
    motion) but shows its back to the camera. The flip-over test rejects it up to ~66 deg of tilt from the
    view, where |z_s| + |z_t| passes the 0.8 margin (before, the start triangle was flip-tested at another
    corner than its degeneracy test and a face-on plane kept 14 matches); beyond, only the paper's plain
    sign test (flip_margin 0) rejects it."""
    rng = np.random.default_rng(0)
    t = np.radians(tilt_deg)
    u, v = np.array([0.0, 1.0, 0.0]), np.array([np.cos(t), 0.0, -np.sin(t)])  # plane normal (sin t, 0, cos t)
    c = np.array([0.0, 0.0, 0.6])
    ab = rng.uniform(-0.1, 0.1, (30, 2))
    ps = c + ab[:, :1] * u + ab[:, 1:] * v
    pt = (ps - c) @ np.diag([-1.0, 1.0, -1.0]).T + c  # 180 deg about u through c
    dist = np.full((30, 30), 1.0, np.float32)
    dist[np.arange(30), np.arange(30)] = 0.1
    assert len(gmatch(ps, pt, dist, 0.5, GMatchParams(constraint="distance")).matches) == 24  # congruent
    for order in ("ratio", "distance"):
        n = len(gmatch(ps, pt, dist, 0.5, GMatchParams(order=order)).matches)
        assert n == (24 if tilt_deg > 66 else 0), n
        assert len(gmatch(ps, pt, dist, 0.5, GMatchParams(order=order, flip_margin=0.0)).matches) == 0


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), constraint=st.sampled_from(["flip", "triple", "distance"]))
def test_deterministic_and_consistent(seed, constraint):
    ps, pt, dist, T, _ = _problem(seed, n_in=25, n_out=25, n_false=6)
    p = GMatchParams(constraint=constraint)
    a = gmatch(ps, pt, dist, 1.0, p)
    b = gmatch(ps.copy(), pt.copy(), dist.copy(), 1.0, p)
    np.testing.assert_array_equal(a.matches, b.matches)
    assert a.cost == b.cost
    # one-to-one, below the thresholds, list cost = max pairwise delta
    assert len(np.unique(a.matches[:, 0])) == len(a.matches) == len(np.unique(a.matches[:, 1]))
    # candidate pairs only: their descriptor distance is below the threshold (1.0 here)
    assert np.all(dist[a.matches[:, 0], a.matches[:, 1]] < 1.0)
    if len(a.matches) >= 2:
        ls = np.linalg.norm(ps[a.matches[:, 0], None] - ps[None, a.matches[:, 0]], axis=-1)
        lt = np.linalg.norm(pt[a.matches[:, 1], None] - pt[None, a.matches[:, 1]], axis=-1)
        iu = np.triu_indices(len(a.matches), 1)
        worst = (np.abs(ls - lt)[iu] / ls[iu]).max()
        # the list's cost is its largest pairwise delta, computed again here in float64 (1e-9: rounding of O(0.1)
        # ratios)
        assert worst <= a.cost + 1e-9 <= p.eps_c + 1e-9
        if constraint != "triple":  # triple adds the off-plane term to the cost
            # the same delta recomputed from float32 points: float32 rounding (6e-8 relative) of distances, 1e-6 allows
            # it
            assert worst == pytest.approx(a.cost, abs=1e-6)
    assert len(a.matches) <= p.L


def test_trace_holds_each_hypothesis_list():
    """Every hypothesis' list starts with its 3-pair start, has its recorded length, is one-to-one and within
    eps_c; the winner is the first longest, cheapest list that was not pruned."""
    ps, pt, dist, T, _ = _problem(5, n_in=30, n_out=30, n_false=6)
    p = GMatchParams()
    res = gmatch(ps, pt, dist, 1.0, p)
    tr = res.trace
    assert len(tr) > 10 and len({t.length for t in tr}) > 1  # not vacuous: lists of several lengths
    for t in tr:
        assert t.matches.shape == (t.length, 2)
        np.testing.assert_array_equal(t.matches[:3], t.start)
        assert len(np.unique(t.matches[:, 0])) == t.length == len(np.unique(t.matches[:, 1]))
        ls = np.linalg.norm(ps[t.matches[:, 0], None] - ps[None, t.matches[:, 0]], axis=-1)
        lt = np.linalg.norm(pt[t.matches[:, 1], None] - pt[None, t.matches[:, 1]], axis=-1)
        iu = np.triu_indices(t.length, 1)
        # every hypothesis's cost bounds its own pairwise deltas (float64 recomputation; 1e-9 for rounding)
        assert (np.abs(ls - lt)[iu] / ls[iu]).max() <= t.cost + 1e-9
    done = [t for t in tr if not t.pruned]
    win = min(done, key=lambda t: (-t.length, t.cost))
    np.testing.assert_array_equal(win.matches, res.matches)
