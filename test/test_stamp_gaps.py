"""jointfit_ros.stamp_gaps: frames that never arrived, from the gaps in a regular stream's stamps."""

from __future__ import annotations

from collections import deque

import numpy as np

from jointfit_ros.stamp_gaps import StampGaps, base_period

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
    jittered = _feed(regular)
    assert jittered.missed == 0 and abs(jittered.period_s - 5e-3) < 0.3e-3
    paused = np.concatenate([regular[:1500], regular[1500:] + 2_000_000_000])  # a 2 s pause (a stopped replay)
    assert _feed(paused).missed == 0
    looped = np.concatenate([regular, regular])  # a replay looping to its start
    assert _feed(looped).missed == 0
    bad = regular.copy()
    bad[1000] += 100_000_000  # one frame stamped 0.1 s ahead
    assert _feed(bad).missed == 0
    holes = np.delete(regular, [1000, 1001, 1002, 2000])
    assert _feed(holes).missed == 4


def _overloaded_node(service_s: float, rate: float, seconds: float, seed: int) -> list[int]:
    """The stamps a node gets when each frame takes it ``service_s`` (+-10 %) and its queue keeps the last 10 (DDS keep-last).

    Continuous time: the node takes the oldest queued frame as soon as it is free.
    """
    rng = np.random.default_rng(seed)
    period = 1.0 / rate
    queue: deque[int] = deque(maxlen=10)
    taken: list[int] = []
    free_at = 0.0
    for k in range(round(rate * seconds)):
        now = k * period
        while queue and free_at <= now:  # frames taken between the arrivals
            taken.append(queue.popleft())
            free_at += service_s * rng.uniform(0.9, 1.1)
        queue.append(k)
        if free_at <= now:  # idle: the new frame at once
            taken.append(queue.popleft())
            free_at = now + service_s * rng.uniform(0.9, 1.1)
    return [T0 + round(k * period * 1e9) for k in taken]


def test_a_node_that_takes_one_frame_in_three_reads_the_streams_rate_and_its_losses() -> None:
    """Measured on the full-body node at 1 kHz (2.8 ms a frame): before, the input status read a 356 Hz stream and
    a fifth of its frames missed; the stamps that arrive differ by 2 and 3 ms, whose base is the 1 ms period."""
    for service in (0.0028, 0.0045, 0.0095):
        stamps = _overloaded_node(service, 1000.0, 10.0, 1)
        gaps = _feed(np.array(stamps))
        assert gaps.period_s == 1e-3, (service, gaps.period_s)
        assert gaps.spacing_s > 2e-3  # the frames the joints get
        # every frame lost is counted once the period is known (from the 200th difference on)
        lost = (stamps[-1] - stamps[200]) // 1_000_000 + 1 - (len(stamps) - 200)
        assert gaps.missed == lost, (service, gaps.missed, lost)
        assert gaps.missed > 0.6 * (stamps[-1] - stamps[0]) // 1_000_000  # (most frames are lost)


def test_the_base_period_needs_nearly_all_differences_to_be_whole_multiples() -> None:
    assert base_period([2_000_000, 3_000_000] * 50) == 1_000_000
    assert base_period([3_000_000] * 100) == 3_000_000  # all one multiple: a 333 Hz stream as far as stamps tell
    assert base_period([1_000_000] * 90 + [2_000_000] * 10) == 1_000_000  # the usual: the median
    # differences far below the others (two messages close together) are no multiple of anything
    assert base_period([1, 5, 10_000] + [10_000_000] * 97) == 10_000_000
    assert base_period([1] * 10 + [10_000_000] * 90) == 10_000_000
    rng = np.random.default_rng(3)
    assert base_period(rng.integers(2_000_000, 8_000_000, 200).tolist()) > 2_000_000  # no structure: no base
