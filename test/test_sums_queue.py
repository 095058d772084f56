"""Frames fed one by one are queued and summed as blocks (:meth:`RelativePoseSums.add_frame`, issue 16).

The live path and the block path share one code path for the sums: :meth:`~jointfit_core.joint_sums.
RelativePoseSums.add_frame` queues a frame and :meth:`~jointfit_core.joint_sums.RelativePoseSums.flush`
sums the queue with ``add_block``. Whatever the flush points (every frame, as a reader asking after each
frame would force, or at most :data:`~jointfit_core.joint_sums.PENDING_MAX` frames apart), the window
must end in the same state, on streams with occlusions, frames a segment cannot be posed in and bad
stamps (lag pairs broken where a frame could not enter), for every kind of window and attachment.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from helpers import SUMS_RTOL, rel_diff
from test_update_many import WINDOWS, _stream

from jointfit_core.estimator import OnlineJoint
from jointfit_core.joint_sums import _LAG, PENDING_MAX


@pytest.mark.parametrize("attachment", ["rigid", "skin"])
@pytest.mark.parametrize("kind", ["ball", "hinge"])
@pytest.mark.parametrize("window", WINDOWS, ids=lambda w: next(iter(w)))
def test_sums_do_not_depend_on_when_the_queue_is_summed(window: dict[str, Any], kind: str, attachment: str) -> None:
    rng = np.random.default_rng(17)
    yp, yc, stamps = _stream(rng, kind, 700)
    every = OnlineJoint(kind, template_frames=20, attachment=attachment, **window)
    lazy = OnlineJoint(kind, template_frames=20, attachment=attachment, **window)
    most = 0
    for k in range(yp.shape[0]):
        every.update(yp[k], yc[k], float(stamps[k]))
        lazy.update(yp[k], yc[k], float(stamps[k]))
        _ = every.statistics.window  # a reader after every frame: blocks of one
        most = max(most, lazy.statistics.n_pending)
        if k == 400:  # a reader in the middle of the stream
            assert lazy.n_window == every.n_window and lazy.statistics.n_pending == 0
    assert 0 < most <= PENDING_MAX  # the queue held frames, and never more than its cap
    a, b = every.statistics.window, lazy.statistics.window
    assert a is not None and b is not None
    assert rel_diff(a.sums, b.sums) < SUMS_RTOL
    assert every.n_window == lazy.n_window and every.dropped == lazy.dropped
    assert b.sums[_LAG] > 0
    if not a.spec.exponential:  # the lag pairs: the same count (chains broken alike), exactly
        assert a.sums[_LAG] == b.sums[_LAG]
        np.testing.assert_array_equal(a.window_stamps(), b.window_stamps())
    ea, eb = every.estimate(), lazy.estimate()
    np.testing.assert_allclose(ea.cov_parent if kind == "ball" else ea.cov_direction_parent,
                               eb.cov_parent if kind == "ball" else eb.cov_direction_parent, rtol=1e-8)
