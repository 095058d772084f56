""":meth:`LagHistory.contribution_one` writes the whole of a reused buffer (the estimator's, per frame).

It writes the usual frame's pairs in place (every lag paired) and clears the buffer otherwise: a
buffer holding the previous frame's numbers (or garbage) ends up as the block path's row.
"""

from __future__ import annotations

import numpy as np

from jointfit_core.serial import N_TIME_LAG_SUMS, LagHistory


def test_contribution_one_into_a_reused_buffer_equals_the_block_path() -> None:
    rng = np.random.default_rng(7)
    n = 1500
    times = np.cumsum(rng.uniform(0.005, 0.04, n))
    times[700:] += 4.0  # a gap longer than every lag: frames with some lags unpaired, then none
    times[1200:] -= 50.0  # a restart: the next frame has no pair at all
    z = rng.normal(size=(n, 3, 4))
    want = np.zeros((n, N_TIME_LAG_SUMS))
    LagHistory().contributions(times[:1200], z[:1200], want[:1200])
    LagHistory().contributions(times[1200:], z[1200:], want[1200:])
    history = LagHistory()
    buffer = np.full(N_TIME_LAG_SUMS, np.nan)
    every = 0
    for k in range(n):
        buffer[rng.random(N_TIME_LAG_SUMS) < 0.5] = rng.normal()  # what a reused buffer may hold
        if k == 1200:
            history.clear()
        history.contribution_one(float(times[k]), z[k], buffer)
        np.testing.assert_array_equal(buffer, want[k])
        every += bool(buffer[2::30].all())
    assert 0 < every < n  # both the in-place and the clearing path were taken
