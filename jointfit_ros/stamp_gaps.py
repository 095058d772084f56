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
"""

from __future__ import annotations

import statistics
from collections import deque

__all__ = ["StampGaps"]


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
        self._until_period = history
        self._last_added = 0  # missed frames counted at the latest difference

    @property
    def period_s(self) -> float:
        """The stream's frame period (s; 0 while unknown)."""
        return self._period * 1e-9

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
            self._period = int(statistics.median(self._diffs))
