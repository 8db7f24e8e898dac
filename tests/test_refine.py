"""ICP's normal equations (gscan.estimate.refine): the kernel's 6 x 6 system is the least-squares system of the
point-to-plane residuals and the anchor pairs, written out in numpy."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.estimate.refine import normal_equations
from gscan.geometry.transforms import rotvec_to_R


@given(seed=st.integers(0, 10_000), n_anchors=st.integers(0, 6), weight=st.sampled_from([0.0, 0.1, 1.0]))
@settings(max_examples=60, deadline=None)
def test_normal_equations_are_the_least_squares_system(seed, n_anchors, weight):
    rng = np.random.default_rng(seed)
    N, M = 40, 30
    p = rng.normal(0.0, 0.1, (N, 3)) + [0.0, 0.0, 0.6]
    tgt = rng.normal(0.0, 0.1, (M, 3)) + [0.0, 0.0, 0.6]
    nrm = rng.normal(size=(N, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    R = rotvec_to_R(rng.normal(0.0, 0.5, 3))
    j = np.where(rng.random(N) < 0.7, rng.integers(0, M, N), -1)
    anc_p, anc_q = rng.normal(0.0, 0.1, (n_anchors, 3)), rng.normal(0.0, 0.1, (n_anchors, 3))
    H, g = np.empty((6, 6)), np.empty(6)
    pairs = normal_equations(p, j, tgt, nrm, R, anc_p, anc_q, weight, H, g)

    ok = j >= 0
    P, Q, Nn = p[ok], tgt[j[ok]], nrm[ok] @ R.T
    A = np.hstack([np.cross(P, Nn), Nn])  # d(residual) / d(rotation vector, translation)
    r = np.einsum("ij,ij->i", P - Q, Nn)
    H_ref, g_ref = A.T @ A, A.T @ r
    for x, e in zip(anc_p, anc_p - anc_q, strict=True):  # omega x p + t: J = [-[p]x, I]
        J = np.hstack([-np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]]), np.eye(3)])
        H_ref += weight * J.T @ J
        g_ref += weight * J.T @ e
    assert pairs == ok.sum()
    np.testing.assert_allclose(H, H_ref, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(g, g_ref, rtol=1e-10, atol=1e-14)
