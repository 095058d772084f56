"""Sliding-window sums of per-frame contributions, O(1) per frame with bounded drift.

The online estimators keep, for the frames of a window, the sums of fixed-size
per-frame contribution vectors (counts, moments, pose products). Adding the
newest frame and subtracting the frames that leave costs the same whatever
the window length. :class:`SlidingSums` is the one interface to the two kinds
of window:

* a window of frames or of seconds (:class:`~jointfit_core.ring_sums.RingWindowSums`):
  the rows of the window's frames stay in a ring buffer
  (:class:`~jointfit_core.record_ring.RecordRing`) so that leaving frames can
  be subtracted. Drift: repeated add/subtract accumulates rounding error
  without bound, and sums about a reference point that no longer lies near
  the data lose digits by cancellation; a *shadow* copy of the sums
  (:class:`~jointfit_core.shadow_sums.ShadowSums`) is rebuilt from the ring
  one frame per update (about a fresh reference point at the data's current
  mean), and replaces the live sums when it has covered the window. So the
  sums in use always come from at most about two window lengths of
  add/subtract steps, and every update does the same, constant amount of
  work (no periodic O(window) spike);
* exponential forgetting (:class:`~jointfit_core.forgetting_sums.ForgettingSums`)
  needs no ring buffer: the sums decay by a constant factor per frame (or per
  second), so old rounding errors decay with them; the reference point is
  moved by an exact shift of the sums when the data have wandered from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from .errors import InputError
from .forgetting_sums import ForgettingSums
from .ring_sums import RingWindowSums
from .window_spec import WindowSpec, window_spec

__all__ = ["WindowSpec", "SlidingSums", "window_spec"]

FloatArray = NDArray[np.float64]

#: Contribution function: records (m, R) and reference points (m, 3) -> contributions (m, L).
ContribFn = Callable[[FloatArray, FloatArray], FloatArray]
#: Exact shift of a sums vector (L,) from reference point ``old`` to ``new`` (3,).
ShiftFn = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]
#: New reference point (3,) from the sums (L,) about ``ref``, or None to keep ``ref``.
RefFn = Callable[[FloatArray, FloatArray], "FloatArray | None"]


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
    The sums themselves are kept by a
    :class:`~jointfit_core.ring_sums.RingWindowSums` (frame and time windows)
    or a :class:`~jointfit_core.forgetting_sums.ForgettingSums` (exponential
    forgetting); this class checks what is pushed and counts it. Frame
    windows keep a ring buffer of ``frames`` records; time windows a ring
    that grows by doubling up to ``max_frames``. Each :meth:`push` computes
    the contributions of the new frame, of the leaving frames and of one
    frame of the shadow rebuild in a single vectorised call.
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
        self._first_ref = first_ref
        self._count_index = np.zeros(0, dtype=np.intp) if count_index is None else np.asarray(count_index)
        if isinstance(max_frames, bool) or int(max_frames) < 1:
            raise InputError(f"max_frames: expected a positive integer, got {max_frames!r}")
        # The sums, and how frames enter and leave them: a frame or time window's, or exponential forgetting's.
        self._window_sums: RingWindowSums | ForgettingSums
        if spec.exponential:
            self._window_sums = ForgettingSums(spec, self.n_sums, contrib, ref_of, shift, self._count_index)
        else:
            self._window_sums = RingWindowSums(spec, self.record_size, self.n_sums, contrib, ref_of, int(max_frames))
        self.clear()

    # ------------------------------------------------------------------ state

    def clear(self) -> None:
        """Forget every frame."""
        self._window_sums.clear()
        self.n_pushed = 0
        self.last_stamp: float | None = None
        self._stamps_sorted = True  # every stamp pushed so far at least the previous one (time windows)

    @property
    def sums(self) -> FloatArray:
        """The sums of the contributions in the window (weighted, with forgetting), shape (L,)."""
        return self._window_sums.sums

    @property
    def ref(self) -> FloatArray:
        """The reference point the contributions are about, shape (3,) (the origin without one)."""
        return self._window_sums.ref

    @property
    def counts_sq(self) -> FloatArray:
        """Sums of squared weights of the count entries (equal to the counts in ring modes)."""
        if isinstance(self._window_sums, ForgettingSums):
            return self._window_sums.counts_sq
        out: FloatArray = self.sums[self._count_index]
        return out

    @property
    def n_window(self) -> int:
        """Number of frames currently in the window (ring modes; for forgetting, frames pushed)."""
        if isinstance(self._window_sums, ForgettingSums):
            return self.n_pushed
        return self._window_sums.ring.hi - self._window_sums.ring.lo

    def _ring_window(self, what: str) -> RingWindowSums:
        """The ring window; an InputError naming ``what`` asked for one under exponential forgetting."""
        if not isinstance(self._window_sums, RingWindowSums):
            raise InputError(f"{what}: exponential forgetting keeps no records")
        return self._window_sums

    def window_records(self) -> FloatArray:
        """Copy of the records in the window, oldest first, shape (n, R) (ring modes only).

        When the sums use no reference point the ring keeps the contributions
        instead, shape (n, L).
        """
        return self._ring_window("window_records").ring.window_rows()

    def window_stamps(self) -> FloatArray:
        """Stamps of the records in the window (NaN when not stamped), shape (n,)."""
        return self._ring_window("window_stamps").ring.window_stamps()

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
            self._window_sums.ref = np.asarray(self._first_ref(record), dtype=np.float64)
        if self.spec.seconds is not None:
            st = float(stamp)  # type: ignore[arg-type]  # checked above
            if not (math.isfinite(st) and (self.last_stamp is None or st >= self.last_stamp)):
                self._stamps_sorted = False
        if isinstance(self._window_sums, ForgettingSums):
            self._window_sums.push(record, stamp, self.n_pushed, self.last_stamp)
        else:
            self._window_sums.push(record, stamp)
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
        The block is added at once when the records are the contributions
        themselves (no contribution function, no reference point:
        :class:`~jointfit_core.estimator.OnlineJoint`'s sums), except, in a
        frame or time window, contributions of length 1 and time windows
        whose stamps ever decreased (the estimators drop frames whose stamp
        does not increase); then the rows are pushed one by one. A frame or
        time window replays the block
        exactly (:class:`~jointfit_core.ring_replay.RingBlockReplay`): the
        sums, the shadow, the ring and the counters are bit-for-bit those of
        the sequential pushes, at a cost of O(M) numpy work and O(cycles)
        Python steps. Exponential forgetting applies it in closed form
        (:meth:`ForgettingSums.block_weights
        <jointfit_core.forgetting_sums.ForgettingSums.block_weights>`), equal
        to the sequential recursion up to rounding (relative differences of a
        few ulp per frame of the half-life, not bit-for-bit).
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
        vectorised = self._stores_contributions() and (self.spec.exponential or self.n_sums > 1)
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
            self._window_sums.ref = np.asarray(self._first_ref(recs[0]), dtype=np.float64)
        if isinstance(self._window_sums, ForgettingSums):
            self._window_sums.push_block(recs, st, self.n_pushed, self.last_stamp)
        else:
            self._window_sums.push_block(recs, st)
        self.n_pushed += m
        if st is not None:
            self.last_stamp = float(st[-1])

    def _stores_contributions(self) -> bool:
        """Whether the records pushed are the contributions themselves and never change (no contribution function, no reference point)."""
        if self._contrib is not None:
            return False
        return isinstance(self._window_sums, ForgettingSums) or self._window_sums.store_contrib

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
        window = self._window_sums
        if not (isinstance(window, ForgettingSums) and self._stores_contributions() and not self._count_index.size):
            raise InputError("push_weighted_sum: only for exponential forgetting of stored contributions without counts")
        tot = np.asarray(total, dtype=np.float64)
        if tot.shape != (self.n_sums,):
            raise InputError(f"total: expected shape ({self.n_sums},), got shape {tot.shape}")
        if m <= 0:
            return
        window.add_weighted_sum(tot, w_old)
        self.n_pushed += m
        if stamps is not None:
            self.last_stamp = float(stamps[-1])

    def block_weights(self, m: int, stamps: FloatArray | None) -> tuple[FloatArray, float]:
        """Exponential forgetting of a block of ``m`` frames: each frame's weight after the block, and the old sums'.

        Returns ``(w, w_old)``, ``w`` shape (m,): the product of the decays applied after each
        frame, and the decay of the sums before the block
        (:meth:`ForgettingSums.block_weights <jointfit_core.forgetting_sums.ForgettingSums.block_weights>`).
        ``stamps`` (m,) are needed by time half-lives.
        """
        assert isinstance(self._window_sums, ForgettingSums)
        return self._window_sums.block_weights(m, stamps, self.n_pushed, self.last_stamp)

    # ------------------------------------------------------------------ the ring's state, as tests and bench/vector_core.py read it

    @property
    def _shadow(self) -> FloatArray:
        """The drift control's rebuilt sums, shape (L,) (:attr:`ShadowSums.sums <jointfit_core.shadow_sums.ShadowSums.sums>`)."""
        return self._ring_window("_shadow").shadow.sums

    @property
    def _shadow_active(self) -> bool:
        """Whether a rebuild is under way (:attr:`ShadowSums.active <jointfit_core.shadow_sums.ShadowSums.active>`)."""
        return self._ring_window("_shadow_active").shadow.active

    @property
    def _shadow_next(self) -> int:
        """The next frame the rebuild adds (:attr:`ShadowSums.next <jointfit_core.shadow_sums.ShadowSums.next>`)."""
        return self._ring_window("_shadow_next").shadow.next

    @property
    def _shadow_end(self) -> int:
        """One past the last frame the rebuild adds (:attr:`ShadowSums.end <jointfit_core.shadow_sums.ShadowSums.end>`)."""
        return self._ring_window("_shadow_end").shadow.end

    @property
    def _rec(self) -> FloatArray:
        """The ring's rows, shape (capacity, R or L) (:attr:`RecordRing.rows <jointfit_core.record_ring.RecordRing.rows>`)."""
        return self._ring_window("_rec").ring.rows

    @property
    def _lo(self) -> int:
        """Absolute index of the oldest frame in the window."""
        return self._ring_window("_lo").ring.lo

    @property
    def _hi(self) -> int:
        """One past the newest frame's absolute index."""
        return self._ring_window("_hi").ring.hi
