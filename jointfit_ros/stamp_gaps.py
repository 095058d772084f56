"""Frames that never reached the node: gaps in a regular marker stream's stamps.

Pure Python. A mocap stream has a fixed frame period. When the node cannot
keep up, or the network or the driver loses messages, DDS drops them without
telling anyone (best-effort, keep-last queues), and the outputs simply have
holes. :class:`StampGaps` sees the holes in the stamps: the period is the
median of the recent stamp differences, and a difference of ``k`` periods
(``k >= 2``, rounded) means ``k - 1`` frames missed. Differences longer
than ``max_gap_s`` are a pause (a stopped recording), not missed frames;
stamps that go back (a looped replay, or the return after one stamp that
jumped ahead) take back what the jump before them counted and go on from there.

When most frames are lost (a node that cannot keep up drops two in three and
takes every second or third frame), the median difference is a multiple of the
period, and a 1 kHz stream read as 356 Hz with a fifth of its frames missed
instead of two thirds (measured: the full-body node at 1 kHz). The period is
then the largest ``p`` of which nearly all the differences are whole multiples
(:func:`base_period`): differences of 2 and 3 ms give 1 ms. Stamps with jitter
have no such ``p`` and keep the median, and differences that are all the same
multiple cannot be told from a slower stream (the node's busy share can:
:mod:`jointfit_ros.frame_load`).
"""

from __future__ import annotations

import statistics
from collections import deque

__all__ = ["BASE_SHARE", "BASE_TOLERANCE", "StampGaps", "base_period"]

#: :func:`base_period`: the share of the differences that must be whole multiples of a period shorter
#: than their median, and how close to a whole multiple (in periods) they must be.
BASE_SHARE = 0.9
BASE_TOLERANCE = 0.1
#: Most periods in the smallest usual difference (:func:`base_period`): a node keeping one frame in 16.
_BASE_MAX_K = 16


def base_period(diffs: list[int]) -> int:
    """A regular stream's period (ns) from the differences between the stamps that arrived (ns, all > 0).

    The median difference, unless the differences are whole multiples of a shorter period: then
    the largest ``p = low / k`` (``low`` their 5th percentile, ``k`` = 1 ... 16) of which at least
    :data:`BASE_SHARE` of them are whole multiples within :data:`BASE_TOLERANCE` periods, refined as the
    median of ``d / round(d / p)`` over those, and at least 1/16 of the median (a few differences far
    below the others, two messages close together, give no period). A regular stream with a few holes
    is ``k = 1``.
    """
    d = sorted(diffs)
    median = int(statistics.median(d))
    low = d[len(d) // 20]
    for k in range(1, _BASE_MAX_K + 1):
        p = low / k
        if p * _BASE_MAX_K < median:  # (a period under 1/16 of the median: differences far below the others)
            break
        steps = [x / p for x in d]
        whole = [x / round(r) for x, r in zip(d, steps, strict=True) if r >= 0.5 and abs(r - round(r)) <= BASE_TOLERANCE]
        if len(whole) >= BASE_SHARE * len(d):
            return int(statistics.median(whole))
    return median


class StampGaps:
    """Counts the frames missing between the stamps of a regular stream.

    Parameters
    ----------
    history : int
        Stamp differences the period is the median of (re-taken every ``history`` frames).
    max_gap_s : float
        Longer differences are pauses, not missed frames.

    Attributes
    ----------
    received : int
        Frames seen.
    missed : int
        Frames missing between them (0 until the period is known: after ``history`` frames).
    """

    def __init__(self, history: int = 200, max_gap_s: float = 0.5) -> None:
        self.received = 0
        self.missed = 0
        self._history = history
        self._max_gap_ns = round(max_gap_s * 1e9)
        self._diffs: deque[int] = deque(maxlen=history)
        self._last: int | None = None
        self._period = 0
        self._spacing = 0
        self._until_period = history
        self._last_added = 0  # missed frames counted at the latest difference

    @property
    def period_s(self) -> float:
        """The stream's frame period (s; 0 while unknown): :func:`base_period` of the recent differences."""
        return self._period * 1e-9

    @property
    def spacing_s(self) -> float:
        """The median difference between the stamps that arrived (s; 0 while unknown).

        The period of the frames the joints get: :attr:`period_s` unless most frames are lost.
        """
        return self._spacing * 1e-9

    def add(self, stamp_ns: int) -> None:
        """A frame stamped ``stamp_ns`` (ns) arrived."""
        self.received += 1
        last, self._last = self._last, stamp_ns
        if last is None:
            return
        d = stamp_ns - last
        if d <= 0:  # back: the frame before jumped ahead (a bad stamp, not a hole), or the replay looped
            self.missed -= self._last_added
            self._last_added = 0
            return
        self._diffs.append(d)
        p = self._period
        self._last_added = round(d / p) - 1 if p and 2 * d > 3 * p and d <= self._max_gap_ns else 0
        self.missed += self._last_added
        self._until_period -= 1
        if self._until_period <= 0:
            self._until_period = self._history
            self._spacing = int(statistics.median(self._diffs))
            self._period = base_period(list(self._diffs))
