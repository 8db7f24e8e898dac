"""The kernels over the retrieval matrix (gscan.estimate.similarity) give exactly what the plain numpy
computation gives: the estimator's GMatch candidates are those `extract_candidates` gives on the explicitly
built group distance block (same pairs, same order, same distances; ties, coincident keypoint groups, values
at the threshold, both orders, both kinds of retrieval matrix), and the best offered column of each row is
np.argmax's (first on ties)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.estimate.hypotheses import QueryKeypoints
from gscan.estimate.similarity import (
    TemplateGroups,
    _unit_distance,
    _unit_threshold,
    best_columns,
    neighbourhood_candidates,
    neighbourhoods_candidates,
)
from gscan.estimate.verify import count_unique_rows
from gscan.matching.gmatch import extract_candidates


def _groups(rng: np.random.Generator, n: int, max_size: int) -> tuple[np.ndarray, np.ndarray]:
    """A random grouping of n items, as coincident_groups returns it: (order [n], starts [G])."""
    sizes = []
    while sum(sizes) < n:
        sizes.append(int(min(rng.integers(1, max_size + 1), n - sum(sizes))))
    perm = rng.permutation(n)
    return perm.astype(np.int64), np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64)


def _block(S: np.ndarray, unit: bool, q: tuple[np.ndarray, np.ndarray], cols: np.ndarray,
           t: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The [R x G] group distance block, built the plain way: each group pair's best member value, then its
    distance (the estimator's formula for unit descriptors)."""
    def members(order, starts, k):
        return order[starts[k]:(starts[k + 1] if k + 1 < len(starts) else len(order))]

    out = np.empty((len(t[1]), len(q[1])), np.float32)
    for r in range(len(t[1])):
        for g in range(len(q[1])):
            v = S[np.ix_(members(*q, g), cols[members(*t, r)])]
            out[r, g] = v.max() if unit else v.min()
    return np.sqrt(np.maximum(2.0 - 2.0 * out, 0.0)) if unit else out


def _check(S: np.ndarray, unit: bool, q, cols, t, eps_f: float, order: str, capacity: int = 1 << 16) -> int:
    want = extract_candidates(_block(S, unit, q, cols, t), eps_f, order)
    got = neighbourhood_candidates(S, unit, *q, TemplateGroups(cols, *t), eps_f, order, capacity=capacity)
    np.testing.assert_array_equal(got.src, want.src)
    np.testing.assert_array_equal(got.tgt, want.tgt)
    np.testing.assert_array_equal(got.dist, want.dist)  # (the sign of a zero within a group is either member's)
    return len(want.src)


@given(seed=st.integers(0, 10_000), unit=st.booleans(), order=st.sampled_from(["ratio", "distance"]),
       eps_f=st.sampled_from([0.3, 0.5, 0.6, 0.7]))
@settings(max_examples=60, deadline=None)
def test_candidates_equal_extract_candidates_on_the_group_block(seed, unit, order, eps_f):
    rng = np.random.default_rng(seed)
    M, N = int(rng.integers(1, 30)), int(rng.integers(1, 60))
    if unit:  # cosine similarities of non-negative unit vectors, some repeated (ties)
        d = rng.random((M + N, 16)) ** 4
        d[rng.random(M + N) < 0.2] = d[0]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        S = (d[:M] @ d[M:].T).astype(np.float32)
    else:  # distances on a coarse grid (ties), some -0.0
        S = (rng.integers(0, 12, (M, N)) / 10.0).astype(np.float32)
        S[rng.random(S.shape) < 0.05] = -0.0
    n_cols = int(rng.integers(1, N + 1))
    cols = rng.choice(N, n_cols, replace=False).astype(np.int64)  # the neighbourhood's template columns
    _check(S, unit, _groups(rng, M, 3), cols, _groups(rng, n_cols, 3), eps_f, order)


@given(seed=st.integers(0, 10_000), unit=st.booleans())
@settings(max_examples=30, deadline=None)
def test_several_neighbourhoods_in_one_pass_equal_one_by_one(seed, unit):
    rng = np.random.default_rng(seed)
    M, N = int(rng.integers(1, 25)), int(rng.integers(2, 50))
    S = rng.random((M, N)).astype(np.float32) if unit else (rng.integers(0, 12, (M, N)) / 10.0).astype(np.float32)
    q = _groups(rng, M, 3)
    tgs = []
    for _ in range(int(rng.integers(1, 4))):
        cols = rng.choice(N, int(rng.integers(0, N + 1)), replace=False).astype(np.int64)  # maybe none
        tgs.append(TemplateGroups(cols, *(_groups(rng, len(cols), 3) if len(cols) else (cols, cols))))
    together = neighbourhoods_candidates(S, unit, *q, tgs, 0.6, "ratio", capacity=int(rng.integers(1, 50)))
    for tg, got in zip(tgs, together, strict=True):
        want = neighbourhood_candidates(S, unit, *q, tg, 0.6, "ratio")
        for a, b in zip((got.src, got.tgt, got.dist), (want.src, want.tgt, want.dist), strict=True):
            np.testing.assert_array_equal(a, b)


def test_candidates_at_the_threshold_and_beyond_the_first_buffer():
    """Similarities on both sides of the unit threshold, ties in every row, and more candidates than the
    kernel's first buffer holds."""
    eps = np.float32(0.6)
    t = _unit_threshold(eps)
    below, above = t, np.nextafter(t, np.float32(2.0))
    S = np.full((6, 8), below, np.float32)
    S[::2, 1::2] = above
    S[5, 7] = np.float32(1.0)
    q, cols, tg = (np.arange(6), np.arange(6)), np.arange(8), (np.arange(8), np.arange(8))
    n = _check(S, True, q, cols, tg, float(eps), "ratio")
    assert n == 3 * 4 + 1  # `above` and 1.0 are candidates, `below` is not
    assert _check(S, True, q, cols, tg, float(eps), "ratio", capacity=5) == n  # the kernel runs again with room


@pytest.mark.parametrize("eps", [0.05, 0.1, 0.3, 0.5, 0.6, 0.7, 1.0, 1.4])
def test_unit_threshold_separates_the_distances(eps):
    e = np.float32(eps)
    t = _unit_threshold(e)
    assert _unit_distance(t) >= e > _unit_distance(np.nextafter(t, np.float32(2.0)))


@given(seed=st.integers(0, 10_000), sign=st.sampled_from([1.0, -1.0]))
@settings(max_examples=60, deadline=None)
def test_best_columns_is_argmax_of_the_block(seed, sign):
    rng = np.random.default_rng(seed)
    S = (rng.integers(0, 6, (int(rng.integers(1, 20)), int(rng.integers(1, 40)))) / 5.0).astype(np.float32)  # ties
    rows = rng.integers(0, len(S), int(rng.integers(0, 25)))
    cols = rng.choice(S.shape[1], int(rng.integers(1, S.shape[1] + 1)), replace=False)
    block = (S if sign > 0 else -S)[np.ix_(rows, cols)]
    j, v = best_columns(S, rows, cols, sign)
    np.testing.assert_array_equal(j, np.argmax(block, axis=1))
    np.testing.assert_array_equal(v, block[np.arange(len(rows)), np.argmax(block, axis=1)])
    assert v.dtype == np.float32


@given(seed=st.integers(0, 10_000), spread=st.sampled_from([2, 50, 2**40]))
@settings(max_examples=40, deadline=None)
def test_count_unique_rows_is_numpys(seed, spread):
    rng = np.random.default_rng(seed)
    keys = rng.integers(-spread, spread, (int(rng.integers(0, 60)), 3))
    if len(keys) > 4:
        keys[: len(keys) // 3] = keys[-(len(keys) // 3):]  # repeated rows
    assert count_unique_rows(keys) == len(np.unique(keys, axis=0))


@given(seed=st.integers(0, 10_000), unit=st.booleans())
@settings(max_examples=30, deadline=None)
def test_a_subset_read_through_its_rows_equals_the_copied_rows(seed, unit):
    """The instance search's later searches read their keypoints' rows in the frame's whole retrieval matrix
    (`Retrieval.rows`): candidates, best columns and `QueryKeypoints.similarity` equal those of the rows copied out
    (S[keep])."""
    rng = np.random.default_rng(seed)
    M, N = int(rng.integers(2, 30)), int(rng.integers(2, 50))
    S = rng.random((M, N)).astype(np.float32) if unit else (rng.integers(0, 12, (M, N)) / 10.0).astype(np.float32)
    rows = np.flatnonzero(rng.random(M) < 0.6)
    if len(rows) == 0:
        rows = np.array([0])
    sub = S[rows]
    q_order, q_starts = _groups(rng, len(rows), 3)
    cols = rng.choice(N, int(rng.integers(1, N + 1)), replace=False).astype(np.int64)
    tg = TemplateGroups(cols, *_groups(rng, len(cols), 3))
    got = neighbourhood_candidates(S, unit, rows[q_order], q_starts, tg, 0.6, "ratio")
    want = neighbourhood_candidates(sub, unit, q_order, q_starts, tg, 0.6, "ratio")
    for a, b in zip((got.src, got.tgt, got.dist), (want.src, want.tgt, want.dist), strict=True):
        np.testing.assert_array_equal(a, b)
    on = rng.integers(0, len(rows), int(rng.integers(0, 20)))
    for a, b in zip(best_columns(S, rows[on], cols), best_columns(sub, on, cols), strict=True):
        np.testing.assert_array_equal(a, b)
    qk = QueryKeypoints(None, S, *(np.zeros(0, np.int64),) * 4, rows=rows)  # type: ignore[arg-type]
    np.testing.assert_array_equal(qk.similarity(cols), sub[:, cols])  # what a `Matcher` reads


def test_a_subset_read_without_its_row_map_is_refused():
    """A keypoint subset's similarity rows live in the whole frame's matrix: reading it without the row map
    (row i taken for keypoint i) would give another keypoint's support, so it raises."""
    from gscan.estimate.verify import keypoint_support

    S = np.zeros((5, 4), np.float32)  # 5 rows, 3 query keypoints
    with pytest.raises(ValueError, match="sim_rows"):
        keypoint_support(np.eye(4), np.zeros((4, 3)), np.arange(4), S, np.arange(4), np.zeros((3, 3)), np.arange(3),
                         np.zeros((10, 3)), np.zeros((8, 8)), None, 0.01, 0.5, 0.01)  # type: ignore[arg-type]
