"""`gscan.io.sequence.spread_indices`: the one helper for the frames or views a stage samples from a sequence."""
from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from gscan.io.sequence import spread_indices


@given(st.integers(0, 500), st.integers(1, 60), st.booleans())
def test_spread_indices_cover_the_sequence_in_order(n, k, nearest):
    """At most k distinct indices of range(n), increasing, the first included and the last too when k > 1; all of
    them when n <= k."""
    got = spread_indices(n, k, nearest)
    assert got == sorted(set(got)) and all(0 <= i < n for i in got)
    assert len(got) <= min(n, k)
    if n:
        assert got[0] == 0 and (k == 1 or got[-1] == n - 1)
    if n <= k:
        assert got == list(range(n))


@given(st.integers(1, 500), st.integers(1, 60))
def test_spread_indices_round_down_or_to_the_nearest(n, k):
    """Rounded down, the indices are linspace's truncated; to the nearest, rounded half to even (as the stages that
    sampled so wrote it each)."""
    x = np.linspace(0, n - 1, min(k, n))
    assert spread_indices(n, k) == sorted({int(v) for v in x})
    assert spread_indices(n, k, nearest=True) == sorted({int(round(v)) for v in x})
