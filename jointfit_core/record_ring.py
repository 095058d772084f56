"""The ring buffer of a sliding window: one row and one stamp per frame in the window.

A frame or a time window of :class:`~jointfit_core.stats.SlidingSums`
subtracts the frames that leave it from its sums, so it keeps each frame's
row (the raw record, or its contribution when that never changes) until the
frame leaves. :class:`RecordRing` keeps them addressed by absolute frame
index (frame ``i`` in slot ``i % capacity``): a frame window's ring has the
window's length; a time window's starts small and doubles when full, up to a
limit beyond which its oldest frames leave early.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["RecordRing"]

FloatArray = NDArray[np.float64]


class RecordRing:
    """Rows and stamps of a window's frames, from the oldest ``lo`` to the newest ``hi - 1`` (absolute indices).

    Parameters
    ----------
    capacity : int
        Slots to begin with (a frame window's length).
    width : int
        Length of a row.
    max_frames : int
        Most slots the ring grows to (:meth:`horizon_lo`).

    Attributes
    ----------
    rows : ndarray, shape (capacity, width)
        Frame ``i``'s row in slot ``i % capacity``.
    stamps : ndarray, shape (capacity,)
        Its stamp (s; NaN when it had none).
    lo, hi : int
        Absolute index of the oldest frame in the window, and one past the newest.
    max_frames : int
        As given.
    """

    def __init__(self, capacity: int, width: int, max_frames: int) -> None:
        self.width = width
        self.max_frames = max_frames
        self.rows = np.empty((capacity, width))
        self.stamps = np.empty(capacity)
        self.clear()

    def clear(self) -> None:
        """Empty the window (the slots and their capacity stay)."""
        self.lo = 0
        self.hi = 0

    @property
    def capacity(self) -> int:
        """Number of slots."""
        return int(self.rows.shape[0])

    def slots(self, start: int, stop: int) -> list[int]:
        """Slots of the frames ``start`` to ``stop - 1`` (absolute indices)."""
        cap = self.capacity
        return [i % cap for i in range(start, stop)]

    def subtract_rows(self, target: FloatArray, slots: list[int]) -> None:
        """Subtract the rows in ``slots`` from ``target`` (L,), in place: one row, or their sum.

        (That order of the additions is the one :class:`~jointfit_core.ring_replay.RingBlockReplay`
        replays bit for bit.)
        """
        if len(slots) == 1:
            target -= self.rows[slots[0]]
        elif slots:
            target -= self.rows[slots].sum(axis=0)

    def window_rows(self) -> FloatArray:
        """Copy of the rows in the window, oldest first, shape (n, width)."""
        idx = np.arange(self.lo, self.hi) % max(self.capacity, 1)
        return self.rows[idx].copy()

    def window_stamps(self) -> FloatArray:
        """Copy of the stamps in the window, oldest first (s; NaN when not stamped), shape (n,)."""
        idx = np.arange(self.lo, self.hi) % max(self.capacity, 1)
        return self.stamps[idx].copy()

    def stamp_segments(self) -> list[FloatArray]:
        """The window's stamps as (at most two) contiguous pieces of the ring, oldest first (views, s)."""
        cap = self.capacity
        if self.hi <= self.lo or cap == 0:
            return []
        a, b = self.lo % cap, self.hi % cap
        if a < b:
            return [self.stamps[a:b]]
        return [self.stamps[a:], self.stamps[:b]]

    def horizon_lo(self, stamp: float, seconds: float) -> int:
        """Oldest frame a time window of ``seconds`` keeps once a frame stamped ``stamp`` (s) is added.

        The frames stamped at or before ``stamp - seconds`` leave. When the
        frames kept and the new one do not fit, the ring doubles (up to
        ``max_frames`` slots); at that limit the oldest frames leave early.
        """
        lo, hi = self.lo, self.hi
        cap = self.capacity
        horizon = stamp - seconds
        new_lo = lo
        while new_lo < hi and self.stamps[new_lo % cap] <= horizon:
            new_lo += 1
        if hi - new_lo >= cap:
            if cap < self.max_frames:
                self._grow()
            else:
                new_lo = hi - cap + 1
        return new_lo

    def _grow(self) -> None:
        """Double the slots (at most ``max_frames``), the window's frames moved to their new slots."""
        cap = self.capacity
        new_cap = min(2 * cap, self.max_frames)
        idx = np.arange(self.lo, self.hi) % cap
        rows = np.empty((new_cap, self.width))
        stamps = np.empty(new_cap)
        rows[np.arange(self.lo, self.hi) % new_cap] = self.rows[idx]
        stamps[np.arange(self.lo, self.hi) % new_cap] = self.stamps[idx]
        self.rows, self.stamps = rows, stamps

    def append(self, row: FloatArray, stamp: float | None, new_lo: int) -> None:
        """Store the newest frame's row (R,) (a copy) and stamp (s or None), and move the oldest to ``new_lo``."""
        slot = self.hi % self.capacity
        self.rows[slot] = row
        self.stamps[slot] = np.nan if stamp is None else float(stamp)
        self.lo = new_lo
        self.hi += 1
