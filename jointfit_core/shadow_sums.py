"""The drift control of a ring window's sums: a second copy, rebuilt from the ring one frame per push.

A window's sums are updated by adding the newest frame and subtracting the
ones that leave; repeated, that accumulates rounding error without bound,
and sums about a reference point far from the data lose digits by
cancellation. :class:`ShadowSums` is a second copy of the sums that a ring
window (:class:`~jointfit_core.ring_sums.RingWindowSums`) rebuilds from its
ring, one frame per push, about a fresh reference point, while it adds and
subtracts the same new and leaving frames as the live sums. Once it has
covered the window it replaces the live sums and a new rebuild starts, so
the sums in use always come from at most about two window lengths of
add/subtract steps, and every push does the same, constant amount of work.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .record_ring import RecordRing

__all__ = ["ShadowSums"]

FloatArray = NDArray[np.float64]


class ShadowSums:
    """The window's sums being rebuilt from the ring, about their own reference point.

    Parameters
    ----------
    n_sums : int
        Length L of the sums.

    Attributes
    ----------
    sums : ndarray, shape (L,)
        The rebuilt frames' sums, and those of the frames pushed since the rebuild began.
    ref : ndarray, shape (3,)
        Their reference point.
    active : bool
        Whether a rebuild is under way.
    next : int
        Absolute index of the next frame of the ring it rebuilds.
    end : int
        One past the last frame it rebuilds (the frames from ``end`` on were pushed into it).
    """

    def __init__(self, n_sums: int) -> None:
        self.n_sums = n_sums
        self.clear()

    def clear(self) -> None:
        """No rebuild."""
        self.sums = np.zeros(self.n_sums)
        self.ref = np.zeros(3)
        self.active = False
        self.next = 0
        self.end = 0

    def start(self, ref: FloatArray, lo: int, hi: int) -> None:
        """Begin rebuilding the frames ``lo`` to ``hi - 1`` (absolute indices) about ``ref`` (3,)."""
        self.ref = ref
        self.sums = np.zeros(self.n_sums)
        self.next = lo
        self.end = hi
        self.active = True

    @property
    def complete(self) -> bool:
        """Whether the rebuild has covered its frames (its sums can replace the live ones)."""
        return self.active and self.next >= self.end

    def held(self, lo: int, new_lo: int, cap: int) -> list[int]:
        """Ring slots (capacity ``cap``) of the leaving frames ``lo`` to ``new_lo - 1`` that the sums hold.

        Those are the rebuilt ones (below :attr:`next`) and the ones pushed since the rebuild
        began (from :attr:`end` on; a time window can drop those too when stamps jump).
        """
        return [i % cap for i in range(lo, new_lo) if i < self.next or i >= self.end]

    def advance(self, new_lo: int, cap: int) -> list[int]:
        """The ring slot (capacity ``cap``) of the frame to rebuild at this push, or none; skips frames below ``new_lo``."""
        self.next = max(self.next, new_lo)
        if self.next < self.end:
            slot = self.next % cap
            self.next += 1
            return [slot]
        return []

    def push_stored(self, c_new: FloatArray, ring: RecordRing, lo: int, new_lo: int) -> None:
        """One push into a ring of stored contributions: add ``c_new`` (L,), subtract the leaving frames held, rebuild one.

        ``lo``, ``new_lo``: the window's oldest frame before and after the push (absolute
        indices; the ring not yet holding the new frame).
        """
        self.sums += c_new
        ring.subtract_rows(self.sums, self.held(lo, new_lo, ring.capacity))
        for slot in self.advance(new_lo, ring.capacity):
            self.sums += ring.rows[slot]
