""":meth:`LagHistory.contributions` overwrites the whole of its output, whatever the buffer held.

The estimator sums a queue of live frames as a block into a fresh, uninitialised array
(:meth:`~jointfit_core.joint_sums.RelativePoseSums.flush`), so every entry of a row must be
written: the usual frame's pairs (every lag paired), the frames with some lags unpaired (zeros
there) and the frame after a restart (no pair at all). Blocks of any size, into buffers full of
garbage, must equal one clean pass.
"""

from __future__ import annotations

import itertools

import numpy as np

from jointfit_core.serial import N_TIME_LAG_SUMS, LagHistory


def test_contributions_into_a_dirty_buffer_equal_a_clean_pass() -> None:
    rng = np.random.default_rng(7)
    n = 1500
    times = np.cumsum(rng.uniform(0.005, 0.04, n))
    times[700:] += 4.0  # a gap longer than every lag: frames with some lags unpaired, then none
    times[1200:] -= 50.0  # a restart: the next frame has no pair at all
    z = rng.normal(size=(n, 3, 4))
    want = np.zeros((n, N_TIME_LAG_SUMS))
    LagHistory().contributions(times, z, want)
    assert not want[1200, 2::30].any()  # the restart: no pair
    cuts = np.unique(np.concatenate([[0, n], rng.integers(1, n, 200)]))  # blocks of 1 to ~40 frames
    history = LagHistory()
    every = 0
    for a, b in itertools.pairwise(cuts):
        buffer = rng.normal(size=(b - a, N_TIME_LAG_SUMS))  # what a reused or uninitialised buffer may hold
        buffer[rng.random(buffer.shape) < 0.3] = np.nan
        history.contributions(times[a:b], z[a:b], buffer)
        np.testing.assert_array_equal(buffer, want[a:b])
        every += int(buffer[:, 2::30].all(axis=1).sum())
    assert 0 < every < n  # frames with every lag paired, and frames without
