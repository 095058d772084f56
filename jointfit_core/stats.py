"""Sliding-window sums of per-frame contributions, O(1) per frame with bounded drift.

The online estimators keep, for the frames of a window, the sums of fixed-size
per-frame contribution vectors (counts, moments, pose products). Adding the
newest frame and subtracting the frames that leave costs the same whatever
the window length; the raw records of the window stay in a ring buffer so
that leaving frames can be subtracted.

Drift. Repeated add/subtract accumulates rounding error without bound, and
sums about a reference point that no longer lies near the data lose digits
by cancellation. :class:`SlidingSums` bounds both: a *shadow* copy of the sums
is rebuilt from the ring buffer one frame per update (about a fresh
reference point at the data's current mean), and replaces the live sums when
it has covered the window. So the sums in use always come from at most about
two window lengths of add/subtract steps, and every update does the same,
constant amount of work (no periodic O(window) spike).

Exponential forgetting needs no ring buffer: the sums decay by a constant
factor per frame (or per second), so old rounding errors decay with them;
the reference point is moved by an exact shift of the sums when the data
have wandered from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from .errors import InputError
from .record_ring import RecordRing
from .ring_replay import RingBlockReplay
from .window_spec import WindowSpec, window_spec

__all__ = ["WindowSpec", "SlidingSums", "window_spec"]

FloatArray = NDArray[np.float64]

#: Contribution function: records (m, R) and reference points (m, 3) -> contributions (m, L).
ContribFn = Callable[[FloatArray, FloatArray], FloatArray]
#: Exact shift of a sums vector (L,) from reference point ``old`` to ``new`` (3,).
ShiftFn = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]
#: New reference point (3,) from the sums (L,) about ``ref``, or None to keep ``ref``.
RefFn = Callable[[FloatArray, FloatArray], "FloatArray | None"]

#: Under exponential forgetting, check every this many frames whether to move the reference point.
_REREF_EVERY = 256


class SlidingSums:
    """Sums of per-frame contribution vectors over a sliding window.

    Parameters
    ----------
    spec : WindowSpec
        Which frames are summed.
    record_size : int
        Length R of the raw record kept per frame (e.g. ``3 P`` coordinates).
    n_sums : int
        Length L of a contribution vector.
    contrib : callable or None
        ``contrib(records (m, R), refs (m, 3)) -> (m, L)``: contributions of
        ``m`` records about their reference points. Must be exactly additive
        over frames (sums of per-frame terms). None: the records pushed are
        the contributions themselves (``R == L``, no reference point).
    ref_of : callable, optional
        ``ref_of(sums (L,), ref (3,)) -> (3,) or None``: a reference point near
        the summed data (e.g. their mean). None: the reference stays at the
        origin (contributions that do not depend on it).
    first_ref : callable, optional
        ``first_ref(record (R,)) -> (3,)``: reference point for the first frame.
    shift : callable, optional
        ``shift(sums, old_ref, new_ref) -> sums``: exact re-referencing,
        needed only for exponential forgetting with a ``ref_of``.
    count_index : ndarray of int, optional
        Entries of the contribution that are plain weights (counts); for
        exponential forgetting their sums of squared weights are also kept
        (:attr:`counts_sq`), which effective degrees of freedom need.
    max_frames : int
        Capacity limit of the ring buffer for time windows (frames beyond it
        leave early). Default 1 000 000.

    Notes
    -----
    Frame windows keep a ring buffer of ``frames`` records; time windows a
    ring that grows by doubling up to ``max_frames``. Each :meth:`push`
    computes the contributions of the new frame, of the leaving frames and
    of one frame of the shadow rebuild in a single vectorised call.
    """

    def __init__(
        self,
        spec: WindowSpec,
        record_size: int,
        n_sums: int,
        contrib: ContribFn | None,
        *,
        ref_of: RefFn | None = None,
        first_ref: Callable[[FloatArray], FloatArray] | None = None,
        shift: ShiftFn | None = None,
        count_index: NDArray[np.intp] | None = None,
        max_frames: int = 1_000_000,
    ) -> None:
        self.spec = spec
        self.record_size = int(record_size)
        self.n_sums = int(n_sums)
        if contrib is None and (ref_of is not None or record_size != n_sums):
            raise InputError("contrib: None needs records of the contributions' length and no reference point")
        self._contrib = contrib
        self._ref_of = ref_of
        self._first_ref = first_ref
        self._shift = shift
        self._count_index = np.zeros(0, dtype=np.intp) if count_index is None else np.asarray(count_index)
        if isinstance(max_frames, bool) or int(max_frames) < 1:
            raise InputError(f"max_frames: expected a positive integer, got {max_frames!r}")
        cap = spec.frames if spec.frames is not None else (0 if spec.exponential else min(64, int(max_frames)))
        # Without a reference point the contributions never change, so the ring keeps them
        # (leaving frames are subtracted without recomputing); otherwise it keeps the records.
        self._store_contrib = ref_of is None
        self._ring = RecordRing(cap, self.n_sums if self._store_contrib else self.record_size, int(max_frames))
        if spec.exponential:
            hl = spec.half_life if spec.half_life is not None else spec.half_life_s
            self._log_decay = -np.log(2.0) / float(hl)  # type: ignore[arg-type]
        self.clear()

    # ------------------------------------------------------------------ state

    def clear(self) -> None:
        """Forget every frame."""
        self.ref = np.zeros(3)
        self.sums = np.zeros(self.n_sums)
        self._counts_sq = np.zeros(self._count_index.size)
        self.n_pushed = 0
        self.last_stamp: float | None = None
        self._ring.clear()
        self._shadow_active = False
        self._shadow = np.zeros(self.n_sums)
        self._shadow_ref = np.zeros(3)
        self._shadow_end = 0
        self._shadow_next = 0
        self._stamps_sorted = True  # every stamp pushed so far at least the previous one (time windows)

    @property
    def n_window(self) -> int:
        """Number of frames currently in the window (ring modes; for forgetting, frames pushed)."""
        return self.n_pushed if self.spec.exponential else self._ring.hi - self._ring.lo

    def window_records(self) -> FloatArray:
        """Copy of the records in the window, oldest first, shape (n, R) (ring modes only).

        When the sums use no reference point the ring keeps the contributions
        instead, shape (n, L).
        """
        if self.spec.exponential:
            raise InputError("window_records: exponential forgetting keeps no records")
        return self._ring.window_rows()

    def window_stamps(self) -> FloatArray:
        """Stamps of the records in the window (NaN when not stamped), shape (n,)."""
        if self.spec.exponential:
            raise InputError("window_stamps: exponential forgetting keeps no records")
        return self._ring.window_stamps()

    # ------------------------------------------------------------------ updates

    def push(self, record: FloatArray, stamp: float | None = None) -> None:
        """Add one frame's record (and drop the frames that leave the window).

        Parameters
        ----------
        record : ndarray, shape (R,)
            Already checked by the caller.
        stamp : float, optional
            Seconds; required by time windows and time half-lives, and must
            increase (the caller drops frames whose stamp does not).
        """
        if self.spec.needs_stamps and stamp is None:
            raise InputError(f"stamp: the window ({self.spec.describe()}) needs a stamp with every frame")
        if self.n_pushed == 0 and self._first_ref is not None:
            self.ref = np.asarray(self._first_ref(record), dtype=np.float64)
        if self.spec.seconds is not None:
            st = float(stamp)  # type: ignore[arg-type]  # checked above
            if not (math.isfinite(st) and (self.last_stamp is None or st >= self.last_stamp)):
                self._stamps_sorted = False
        if self.spec.exponential:
            self._push_decay(record, stamp)
        else:
            self._push_ring(record, stamp)
        self.n_pushed += 1
        if stamp is not None:
            self.last_stamp = float(stamp)

    def push_many(self, records: FloatArray, stamps: FloatArray | None = None) -> None:
        """Add the frames of a block, oldest first: the state of :meth:`push` of each row in turn.

        Parameters
        ----------
        records : ndarray, shape (M, R)
            One record per frame, already checked by the caller.
        stamps : ndarray, shape (M,), optional
            Seconds; required by time windows and time half-lives (the
            caller drops frames whose stamp does not increase).

        Raises
        ------
        InputError
            Records of the wrong shape, stamps of the wrong shape, or no
            stamps for a window that needs them (nothing is added).

        Notes
        -----
        *Stored contributions* (no contribution function, no reference
        point: :class:`~jointfit_core.estimator.OnlineJoint`'s sums) in a
        frame or time window: the block is replayed exactly. The frames that
        leave at each step, the shadow rebuild's schedule (which frames it
        adds, removes and rebuilds at each step, and the steps at which it
        replaces the live sums) and the ring's growth are worked out with
        integer arithmetic over the block; then the live sums after the last
        replacement, and the shadow, are each one sequential
        ``numpy.add.reduce`` (row after row, as :meth:`push` adds them) of
        their start value and the rows added and subtracted in that order.
        The sums, the shadow, the ring and the counters are therefore
        bit-for-bit those of the sequential pushes, at a cost of
        O(M) numpy work and O(cycles) Python steps. Time windows need
        non-decreasing stamps for this (the usual case: the estimators drop
        frames whose stamp does not increase); otherwise, with a
        contribution function or a reference point, and for contributions
        of length 1, the rows are pushed one by one.

        *Exponential forgetting* with stored contributions: the block is
        applied in closed form, ``sums <- w_old sums + sum_k w_k c_k`` with
        ``w_k`` the product of the decays after frame k (``exp`` of the sum
        of their exponents); this equals the sequential recursion up to
        rounding (relative differences of a few ulp per frame of the
        half-life, not bit-for-bit).
        """
        recs = np.asarray(records, dtype=np.float64)
        if recs.ndim != 2 or recs.shape[1] != self.record_size:
            raise InputError(f"records: expected shape (M, {self.record_size}), got shape {recs.shape}")
        m = recs.shape[0]
        st: FloatArray | None = None
        if stamps is not None:
            st = np.asarray(stamps, dtype=np.float64)
            if st.shape != (m,):
                raise InputError(f"stamps: expected shape ({m},), got shape {st.shape}")
        elif self.spec.needs_stamps and m:
            raise InputError(f"stamp: the window ({self.spec.describe()}) needs a stamp with every frame")
        if m == 0:
            return
        # (a single-column reduce would be summed pairwise by numpy, not row after row)
        vectorised = self._contrib is None and self._store_contrib and (self.spec.exponential or self.n_sums > 1)
        if vectorised and st is not None and self.spec.seconds is not None:
            ordered = bool(np.all(st[1:] >= st[:-1])) and bool(np.isfinite(st).all())
            if self.last_stamp is not None:
                ordered = ordered and bool(st[0] >= self.last_stamp)
            vectorised = ordered and self._stamps_sorted
        if not vectorised:
            for k in range(m):
                self.push(recs[k], None if st is None else float(st[k]))
            return
        if self.n_pushed == 0 and self._first_ref is not None:
            self.ref = np.asarray(self._first_ref(recs[0]), dtype=np.float64)
        if self.spec.exponential:
            self._push_many_decay(recs, st)
        else:
            self._push_many_ring(recs, st)
        self.n_pushed += m
        if st is not None:
            self.last_stamp = float(st[-1])

    def push_weighted_sum(self, total: FloatArray, w_old: float, m: int, stamps: FloatArray | None) -> None:
        """Exponential forgetting: add a block of ``m`` frames given as its weighted sum.

        ``total`` (n_sums,) is ``sum_k w_k c_k`` with ``(w, w_old)`` from :meth:`block_weights`
        for the same block; the sums become ``w_old * sums + total``, as :meth:`push_many` of
        the contributions would make them, without forming the (m, n_sums) contributions (the
        caller can sum its structured parts with matrix products). Only for stored
        contributions without counts (``count_index``) under exponential forgetting.

        Raises
        ------
        InputError
            The sums are of another kind, or ``total`` has the wrong shape.
        """
        if not (self.spec.exponential and self._contrib is None and self._store_contrib and not self._count_index.size):
            raise InputError("push_weighted_sum: only for exponential forgetting of stored contributions without counts")
        tot = np.asarray(total, dtype=np.float64)
        if tot.shape != (self.n_sums,):
            raise InputError(f"total: expected shape ({self.n_sums},), got shape {tot.shape}")
        if m <= 0:
            return
        self.sums = w_old * self.sums + tot
        self.n_pushed += m
        if stamps is not None:
            self.last_stamp = float(stamps[-1])

    def block_weights(self, m: int, stamps: FloatArray | None) -> tuple[FloatArray, float]:
        """Exponential forgetting of a block of ``m`` frames: each frame's weight after the block, and the old sums'.

        Returns ``(w, w_old)``, ``w`` shape (m,): the product of the decays applied after each
        frame, and the decay of the sums before the block (see :meth:`push_many`). ``stamps``
        (m,) are needed by time half-lives.
        """
        if self.spec.half_life_s is not None:
            st = stamps
            assert st is not None and (self.last_stamp is not None or self.n_pushed == 0)
            prev = np.empty(m)
            prev[0] = st[0] if self.n_pushed == 0 else self.last_stamp
            prev[1:] = st[:-1]
            steps = np.maximum(st - prev, 0.0)
        else:
            steps = np.ones(m)
        if self.n_pushed == 0:
            steps[0] = 0.0  # the first frame ever finds nothing to decay
        expo = self._log_decay * steps
        # after[k]: exponent of the decays applied after frame k (frames k+1 .. m-1)
        after = np.zeros(m)
        after[:-1] = np.cumsum(expo[::-1])[::-1][1:]
        return np.exp(after), float(np.exp(after[0] + expo[0]))

    def _push_many_decay(self, c: FloatArray, st: FloatArray | None) -> None:
        """Exponential forgetting of a block of contributions, in closed form (see :meth:`push_many`)."""
        m = c.shape[0]
        w, w_old = self.block_weights(m, st)
        self.sums = w_old * self.sums + w @ c
        if self._count_index.size:
            self._counts_sq = w_old * w_old * self._counts_sq + (w * w) @ (c[:, self._count_index] ** 2)

    def _push_many_ring(self, c: FloatArray, st: FloatArray | None) -> None:
        """Exact replay of :meth:`_push_contrib` over a block (see :meth:`push_many`; :mod:`~jointfit_core.ring_replay`)."""
        ring = self._ring
        replay = RingBlockReplay(
            c, st, self.spec, ring.lo, ring.hi, ring.rows, ring.stamps, ring.max_frames, ring.stamp_segments()
        )
        # the sums first: they read the ring as it was before the block, which stored_ring then overwrites
        state = (self.sums, self._shadow, self._shadow_active, self._shadow_next, self._shadow_end)
        self.sums, self._shadow, self._shadow_active, self._shadow_next, self._shadow_end = replay.sums_and_shadow(state)
        ring.rows, ring.stamps, ring.lo, ring.hi = replay.stored_ring()

    def _push_decay(self, record: FloatArray, stamp: float | None) -> None:
        if self.n_pushed > 0:
            if self.spec.half_life_s is not None:
                assert stamp is not None and self.last_stamp is not None  # checked in push
                steps = max(float(stamp) - self.last_stamp, 0.0)
            else:
                steps = 1.0
            decay = float(np.exp(self._log_decay * steps))
            self.sums *= decay
            self._counts_sq *= decay * decay
        c = record if self._contrib is None else self._contrib(record[None, :], self.ref[None, :])[0]
        self.sums += c
        self._counts_sq += c[self._count_index] ** 2
        if self._ref_of is not None and self._shift is not None and self.n_pushed % _REREF_EVERY == _REREF_EVERY - 1:
            new_ref = self._ref_of(self.sums, self.ref)
            if new_ref is not None:
                self.sums = self._shift(self.sums, self.ref, new_ref)
                self.ref = new_ref

    def _push_ring(self, record: FloatArray, stamp: float | None) -> None:
        # Frames that leave: the oldest for a frame window, the stale ones for a time window.
        ring = self._ring
        lo = ring.lo
        new_lo = lo
        if self.spec.frames is not None:
            if ring.hi - lo >= self.spec.frames:
                new_lo = lo + 1
        else:
            new_lo = ring.horizon_lo(float(stamp), float(self.spec.seconds))  # type: ignore[arg-type]
        cap = ring.capacity
        leaving = ring.slots(lo, new_lo)
        if self._store_contrib:
            c_new = record if self._contrib is None else self._contrib(record[None, :], self.ref[None, :])[0]
            self._push_contrib(c_new, stamp, leaving, new_lo, cap)
            return

        # One block of rows: new and leaving frames about the live reference, then the
        # shadow's rows (new, leaving frames it already holds, one rebuilt frame) about its own.
        inside: list[int] = []
        chunk: list[int] = []
        if self._shadow_active:
            inside = self._shadow_leaving(lo, new_lo, cap)
            self._shadow_next = max(self._shadow_next, new_lo)
            if self._shadow_next < self._shadow_end:
                chunk = [self._shadow_next % cap]
                self._shadow_next += 1
        n_live = 1 + len(leaving)
        n_rows = n_live + ((1 + len(inside) + len(chunk)) if self._shadow_active else 0)
        block = np.empty((n_rows, self.record_size))
        refs = np.empty((n_rows, 3))
        block[0] = record
        block[1:n_live] = ring.rows[leaving]
        refs[:n_live] = self.ref
        signs = np.ones(n_rows)
        signs[1:n_live] = -1.0
        if self._shadow_active:
            block[n_live] = record
            block[n_live + 1 : n_live + 1 + len(inside)] = ring.rows[inside]
            block[n_rows - len(chunk) :] = ring.rows[chunk]
            refs[n_live:] = self._shadow_ref
            signs[n_live + 1 : n_live + 1 + len(inside)] = -1.0
        assert self._contrib is not None  # records with a reference point always have a contribution function
        c = self._contrib(block, refs)
        self.sums += signs[:n_live] @ c[:n_live]
        if self._shadow_active:
            self._shadow += signs[n_live:] @ c[n_live:]

        ring.append(record, stamp, new_lo)

        if self._shadow_active and self._shadow_next >= self._shadow_end:
            self.sums = self._shadow
            self.ref = self._shadow_ref
            self._shadow_active = False
        if not self._shadow_active:
            self._start_shadow()

    @property
    def counts_sq(self) -> FloatArray:
        """Sums of squared weights of the count entries (equal to the counts in ring modes)."""
        if self.spec.exponential:
            return self._counts_sq
        out: FloatArray = self.sums[self._count_index]
        return out

    def _push_contrib(
        self, c_new: FloatArray, stamp: float | None, leaving: list[int], new_lo: int, cap: int
    ) -> None:
        """Ring of stored contributions: subtract and re-add them, never recompute."""
        ring = self._ring
        lo = ring.lo
        rec = ring.rows
        self.sums += c_new
        ring.subtract_rows(self.sums, leaving)
        if self._shadow_active:
            self._shadow += c_new
            ring.subtract_rows(self._shadow, self._shadow_leaving(lo, new_lo, cap))
            self._shadow_next = max(self._shadow_next, new_lo)
            if self._shadow_next < self._shadow_end:
                self._shadow += rec[self._shadow_next % cap]
                self._shadow_next += 1
        ring.append(c_new, stamp, new_lo)  # a copy: the caller may reuse its buffer
        if self._shadow_active and self._shadow_next >= self._shadow_end:
            self.sums = self._shadow
            self._shadow_active = False
        if not self._shadow_active:
            self._start_shadow()

    def _shadow_leaving(self, lo: int, new_lo: int, cap: int) -> list[int]:
        """Ring slots of the leaving frames [lo, new_lo) that the shadow already holds.

        Those are the rebuilt ones (below ``_shadow_next``) and the ones added since the rebuild
        began (from ``_shadow_end`` on; a time window can drop those too when stamps jump).
        """
        return [i % cap for i in range(lo, new_lo) if i < self._shadow_next or i >= self._shadow_end]

    def _start_shadow(self) -> None:
        """Begin rebuilding the window's sums from the ring, about a fresh reference point."""
        new_ref = self._ref_of(self.sums, self.ref) if self._ref_of is not None else None
        self._shadow_ref = self.ref.copy() if new_ref is None else np.asarray(new_ref, dtype=np.float64)
        self._shadow = np.zeros(self.n_sums)
        self._shadow_next = self._ring.lo
        self._shadow_end = self._ring.hi
        self._shadow_active = True

    # ------------------------------------------------------------------ the ring's state, as bench/vector_core.py reads it

    @property
    def _rec(self) -> FloatArray:
        """The ring's rows, shape (capacity, R or L) (:attr:`RecordRing.rows <jointfit_core.record_ring.RecordRing.rows>`)."""
        return self._ring.rows

    @property
    def _lo(self) -> int:
        """Absolute index of the oldest frame in the window."""
        return self._ring.lo

    @property
    def _hi(self) -> int:
        """One past the newest frame's absolute index."""
        return self._ring.hi
