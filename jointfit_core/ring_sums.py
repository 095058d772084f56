"""A frame or time window's sums: the newest frame added, the leaving ones subtracted from a ring.

:class:`RingWindowSums` is the part of :class:`~jointfit_core.stats.SlidingSums`
for windows of a number of frames or of seconds. The rows of the frames in the
window stay in a :class:`~jointfit_core.record_ring.RecordRing` so that
leaving frames can be subtracted; a :class:`~jointfit_core.shadow_sums.ShadowSums`
rebuilt from it bounds the drift of the add/subtract steps. With a reference
point the ring keeps the raw records, and each push computes the contributions
of the new frame, of the leaving frames and of one frame of the rebuild in a
single vectorised call; without one the contributions never change, so the
ring keeps them and they are added and subtracted without recomputing (and a
block of them is replayed exactly: :class:`~jointfit_core.ring_replay.RingBlockReplay`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .record_ring import RecordRing
from .ring_replay import RingBlockReplay
from .shadow_sums import ShadowSums
from .window_spec import WindowSpec

if TYPE_CHECKING:
    from .stats import ContribFn, RefFn

__all__ = ["RingWindowSums"]

FloatArray = NDArray[np.float64]


class RingWindowSums:
    """Sums of per-frame contributions over a frame or a time window, with the ring of its frames.

    Parameters
    ----------
    spec : WindowSpec
        A frame or a time window (not exponential forgetting).
    record_size : int
        Length R of a frame's record.
    n_sums : int
        Length L of a contribution.
    contrib : callable or None
        ``contrib(records (m, R), refs (m, 3)) -> (m, L)``, or None: the records are the
        contributions (see :class:`~jointfit_core.stats.SlidingSums`).
    ref_of : callable or None
        ``ref_of(sums (L,), ref (3,)) -> (3,) or None``: the reference point of each rebuild;
        None: no reference point (the ring then keeps the contributions).
    max_frames : int
        Most frames a time window's ring holds.

    Attributes
    ----------
    sums : ndarray, shape (L,)
        The window's sums.
    ref : ndarray, shape (3,)
        Their reference point.
    ring : RecordRing
        The frames in the window: their records, or their contributions (:attr:`store_contrib`).
    shadow : ShadowSums
        The drift control's rebuild.
    store_contrib : bool
        Whether the ring keeps contributions (no reference point) rather than records.
    """

    def __init__(
        self,
        spec: WindowSpec,
        record_size: int,
        n_sums: int,
        contrib: ContribFn | None,
        ref_of: RefFn | None,
        max_frames: int,
    ) -> None:
        self.spec = spec
        self.record_size = record_size
        self.n_sums = n_sums
        self._contrib = contrib
        self._ref_of = ref_of
        # Without a reference point the contributions never change, so the ring keeps them
        # (leaving frames are subtracted without recomputing); otherwise it keeps the records.
        self.store_contrib = ref_of is None
        cap = spec.frames if spec.frames is not None else min(64, max_frames)
        self.ring = RecordRing(cap, n_sums if self.store_contrib else record_size, max_frames)
        self.shadow = ShadowSums(n_sums)
        self.clear()

    def clear(self) -> None:
        """Forget every frame."""
        self.ref = np.zeros(3)
        self.sums = np.zeros(self.n_sums)
        self.ring.clear()
        self.shadow.clear()

    def push(self, record: FloatArray, stamp: float | None) -> None:
        """Add one frame's record (R,) and subtract the frames that leave (``stamp`` in s: required by time windows)."""
        ring = self.ring
        lo = ring.lo
        new_lo = lo
        if self.spec.frames is not None:
            if ring.hi - lo >= self.spec.frames:
                new_lo = lo + 1
        else:
            new_lo = ring.horizon_lo(float(stamp), float(self.spec.seconds))  # type: ignore[arg-type]
        cap = ring.capacity
        leaving = ring.slots(lo, new_lo)
        if self.store_contrib:
            c_new = record if self._contrib is None else self._contrib(record[None, :], self.ref[None, :])[0]
            self._push_contrib(c_new, stamp, leaving, new_lo)
            return

        # One block of rows: new and leaving frames about the live reference, then the
        # shadow's rows (new, leaving frames it already holds, one rebuilt frame) about its own.
        shadow = self.shadow
        inside: list[int] = []
        chunk: list[int] = []
        if shadow.active:
            inside = shadow.held(lo, new_lo, cap)
            chunk = shadow.advance(new_lo, cap)
        n_live = 1 + len(leaving)
        n_rows = n_live + ((1 + len(inside) + len(chunk)) if shadow.active else 0)
        block = np.empty((n_rows, self.record_size))
        refs = np.empty((n_rows, 3))
        block[0] = record
        block[1:n_live] = ring.rows[leaving]
        refs[:n_live] = self.ref
        signs = np.ones(n_rows)
        signs[1:n_live] = -1.0
        if shadow.active:
            block[n_live] = record
            block[n_live + 1 : n_live + 1 + len(inside)] = ring.rows[inside]
            block[n_rows - len(chunk) :] = ring.rows[chunk]
            refs[n_live:] = shadow.ref
            signs[n_live + 1 : n_live + 1 + len(inside)] = -1.0
        assert self._contrib is not None  # records with a reference point always have a contribution function
        c = self._contrib(block, refs)
        self.sums += signs[:n_live] @ c[:n_live]
        if shadow.active:
            shadow.sums += signs[n_live:] @ c[n_live:]
        ring.append(record, stamp, new_lo)
        self._renew_shadow(take_ref=True)

    def _push_contrib(self, c_new: FloatArray, stamp: float | None, leaving: list[int], new_lo: int) -> None:
        """Ring of stored contributions: subtract and re-add them, never recompute."""
        ring = self.ring
        self.sums += c_new
        ring.subtract_rows(self.sums, leaving)
        if self.shadow.active:
            self.shadow.push_stored(c_new, ring, ring.lo, new_lo)
        ring.append(c_new, stamp, new_lo)  # a copy: the caller may reuse its buffer
        self._renew_shadow(take_ref=False)

    def push_block(self, c: FloatArray, st: FloatArray | None) -> None:
        """Stored contributions (M, L) of a block, stamps (M,) s or None: :meth:`push` of each, replayed exactly.

        :class:`~jointfit_core.ring_replay.RingBlockReplay` (time windows: stamps non-decreasing).
        """
        ring, shadow = self.ring, self.shadow
        replay = RingBlockReplay(
            c, st, self.spec, ring.lo, ring.hi, ring.rows, ring.stamps, ring.max_frames, ring.stamp_segments()
        )
        # the sums first: they read the ring as it was before the block, which stored_ring then overwrites
        state = (self.sums, shadow.sums, shadow.active, shadow.next, shadow.end)
        self.sums, shadow.sums, shadow.active, shadow.next, shadow.end = replay.sums_and_shadow(state)
        ring.rows, ring.stamps, ring.lo, ring.hi = replay.stored_ring()

    def _renew_shadow(self, take_ref: bool) -> None:
        """A rebuild that has covered the window replaces the live sums (and, ``take_ref``, their reference); then a new one begins.

        The new rebuild is about ``ref_of`` of the live sums (or their own reference point).
        """
        shadow = self.shadow
        if shadow.complete:
            self.sums = shadow.sums
            if take_ref:
                self.ref = shadow.ref
            shadow.active = False
        if not shadow.active:
            new_ref = self._ref_of(self.sums, self.ref) if self._ref_of is not None else None
            ref = self.ref.copy() if new_ref is None else np.asarray(new_ref, dtype=np.float64)
            shadow.start(ref, self.ring.lo, self.ring.hi)
