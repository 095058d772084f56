"""jointfit_ros.stamp_gaps: frames that never arrived, from the gaps in a regular stream's stamps."""

from __future__ import annotations

import numpy as np

from jointfit_ros.stamp_gaps import StampGaps

T0 = 1_000_000_000_000


def _feed(stamps_ns: np.ndarray) -> StampGaps:
    gaps = StampGaps()
    for s in stamps_ns.tolist():
        gaps.add(int(s))
    return gaps


def test_every_tenth_frame_lost_at_1000_hz_is_counted() -> None:
    k = np.arange(5000)
    kept = k[k % 10 != 3]
    gaps = _feed(T0 + kept * 1_000_000)
    assert gaps.period_s == 1e-3
    # counted once the period is known (after 200 frames): ~9/10 of the 500 holes
    assert 440 <= gaps.missed <= 500 and gaps.received == kept.size


def test_jitter_pauses_loops_and_one_bad_stamp_are_not_missed_frames() -> None:
    rng = np.random.default_rng(0)
    regular = T0 + np.arange(3000) * 5_000_000 + rng.integers(-1_000_000, 1_000_000, 3000)  # 200 Hz, +-1 ms jitter
    assert _feed(regular).missed == 0
    paused = np.concatenate([regular[:1500], regular[1500:] + 2_000_000_000])  # a 2 s pause (a stopped replay)
    assert _feed(paused).missed == 0
    looped = np.concatenate([regular, regular])  # a replay looping to its start
    assert _feed(looped).missed == 0
    bad = regular.copy()
    bad[1000] += 100_000_000  # one frame stamped 0.1 s ahead
    assert _feed(bad).missed == 0
    holes = np.delete(regular, [1000, 1001, 1002, 2000])
    assert _feed(holes).missed == 4
