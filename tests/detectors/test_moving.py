"""MovingWindow: streaming moving sums equal direct sums whatever the block cuts."""

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from imufdi_cli.detectors.moving import MovingWindow


@settings(max_examples=40, deadline=None)
@given(
    length=st.integers(1, 12),
    cuts=st.lists(st.integers(0, 60), max_size=5),
)
def test_moving_window_matches_direct_sums_across_block_boundaries(length, cuts):
    values = np.random.default_rng(length).standard_normal((60, 2))
    window = MovingWindow(length, 2)
    edges = [0, *sorted(cuts), 60]
    sums, counts = zip(*(window.push(values[a:b]) for a, b in itertools.pairwise(edges)))
    sums_all, counts_all = np.concatenate(sums), np.concatenate(counts)
    expected = np.array([values[max(0, i - length + 1) : i + 1].sum(axis=0) for i in range(60)])
    assert_allclose(sums_all, expected, atol=1e-12)
    assert_allclose(counts_all, np.minimum(np.arange(1, 61), length))
