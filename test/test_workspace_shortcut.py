"""The absurd-marker test's shortcut for compact segments (:meth:`MarkerScreen.compact`) changes no verdict.

With the shortcut disabled (``compact_starts`` None) every frame takes the segment-by-segment
test; single frames and blocks, clean, with absurd, missing and infinite markers, must come out
the same (the frames, the counters, the message).
"""

from __future__ import annotations

import numpy as np

from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_ros.params import node_config
from jointfit_ros.runner import JointRunner
from jointfit_ros.skeleton_params import skeleton_parameters


def test_compact_shortcut_gives_the_segment_by_segment_verdicts() -> None:
    sk = make_skeleton("full", seed=0)
    cfg = node_config(skeleton_parameters(sk, sk.joints[:1]))
    t = np.arange(400) / 100.0
    frames = skeleton_frames(sk, t, np.random.default_rng(0), 0.0005, 0.02)
    fast, slow = JointRunner(cfg.joints[0], cfg), JointRunner(cfg.joints[0], cfg)
    for k in range(150):
        fast.markers_frame(round(t[k] * 1e9), frames[k])
        slow.markers_frame(round(t[k] * 1e9), frames[k])
    assert fast.estimator.length_scale > 0.0  # templates built: the shortcut applies
    slow.screen.compact_starts = None
    rng = np.random.default_rng(1)
    rows = fast.screen.cluster_rows
    shortcuts = 0
    for k in range(150, 400):
        frame = frames[k].copy()
        kind = rng.integers(5)
        row = rows[rng.integers(rows.size)]
        if kind == 1:
            frame[row] += 1e3  # absurd
        elif kind == 2:
            frame[row, int(rng.integers(3))] = np.inf
        elif kind == 3:
            frame[fast.parent_rows] = np.nan  # a segment all missing
        elif kind == 4:
            frame[row] = 1e300
        shortcuts += fast.screen.compact(frame, 20.0 * fast.estimator.length_scale)
        a, b = fast._in_workspace(frame), slow._in_workspace(frame)
        np.testing.assert_array_equal(a, b)
        assert fast.counters == slow.counters and fast.last_error == slow.last_error
    block = frames[150:200].copy()
    block[3, rows[0]] += 1e3
    block[7, fast.child_rows] = np.nan
    np.testing.assert_array_equal(fast._in_workspace(block), slow._in_workspace(block))
    np.testing.assert_array_equal(fast._in_workspace(block[:0]), slow._in_workspace(block[:0]))
    assert fast.counters == slow.counters
    assert 0 < shortcuts < 250  # both ways taken
