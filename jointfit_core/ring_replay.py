"""Exact replay of a block of pushes into a sliding window's ring of stored contributions.

:meth:`jointfit_core.stats.SlidingSums.push_many` adds the frames of a block
to a frame or time window (:class:`~jointfit_core.ring_sums.RingWindowSums`)
whose ring keeps the per-frame contribution vectors themselves (no reference
point). Pushing them one by one costs one Python
step per frame; :class:`RingBlockReplay` works out the whole block's schedule
with integer arithmetic instead (which frames leave at each step, which the
drift control's shadow rebuild adds, removes and rebuilds, and at which steps
the shadow replaces the live sums), and then forms the live sums after the
last replacement, and the shadow, each as one sequential ``numpy.add.reduce``
of their start value and the rows added and subtracted in push order. The
results are therefore bit for bit those of the sequential pushes
(:meth:`~jointfit_core.stats.SlidingSums.push` /
``RingWindowSums._push_contrib``), at O(M) numpy work and O(cycles) Python steps.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .window_spec import WindowSpec

__all__ = ["NO_ROW", "RingBlockReplay", "ShadowState"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Op code of "no row" in the replay (row codes are absolute frame indices >= 0, or -1 - k for the
#: k-th summed group of rows).
NO_ROW = -(2**62)

#: The drift control's state: (live sums (L,), shadow sums (L,), shadow active, next frame it rebuilds,
#: one past the last frame it covers).
ShadowState = tuple[FloatArray, FloatArray, bool, int, int]


class RingBlockReplay:
    """One block of stored contributions pushed into a ring window, replayed exactly.

    Parameters
    ----------
    c : ndarray, shape (M, L)
        The block's contributions, oldest first (M >= 1).
    st : ndarray, shape (M,), or None
        Their stamps (s); needed by time windows, which also need them non-decreasing.
    spec : WindowSpec
        A frame or a time window (not exponential forgetting).
    lo, hi : int
        Absolute indices of the oldest frame in the window and one past the newest, before the block.
    rec, stamp : ndarray, shapes (cap, L) and (cap,)
        The ring of contributions and their stamps before the block (read, not changed).
    max_frames : int
        The ring's capacity limit (time windows).
    stamp_segments : list of ndarray
        Time windows: the window's stamps as contiguous pieces of the ring, oldest first.
    """

    def __init__(
        self,
        c: FloatArray,
        st: FloatArray | None,
        spec: WindowSpec,
        lo: int,
        hi: int,
        rec: FloatArray,
        stamp: FloatArray,
        max_frames: int,
        stamp_segments: list[FloatArray],
    ) -> None:
        self.c, self.st = c, st
        self.m = c.shape[0]
        self.n_sums = c.shape[1]
        self.lo0, self.h0 = lo, hi
        self.rec, self.stamp = rec, stamp
        self.cap0 = rec.shape[0]
        self.seconds = spec.seconds
        m = self.m
        hi_before = hi + np.arange(m)  # hi before each push
        # lo after each push (absolute indices)
        if spec.frames is not None:
            cand = hi_before + 1 - spec.frames
        else:
            assert st is not None
            horizon = st - float(spec.seconds)  # type: ignore[arg-type]
            count = np.searchsorted(st, horizon, side="right")  # new frames at or before the horizon
            for seg in stamp_segments:
                count = count + np.searchsorted(seg, horizon, side="right")
            cand = np.minimum(lo + count, hi_before)
            cand = np.maximum(cand, hi_before + 1 - max_frames)
        self.lo_after: IntArray = np.maximum.accumulate(np.maximum(cand, lo))
        self.lo_before: IntArray = np.empty(m, dtype=np.int64)
        self.lo_before[0] = lo
        self.lo_before[1:] = self.lo_after[:-1]
        self.n_leave = self.lo_after - self.lo_before
        cap = self.cap0
        if spec.seconds is not None:
            size = int((hi_before + 1 - self.lo_after).max())
            while cap < size and cap < max_frames:
                cap = min(2 * cap, max_frames)
        self.cap = cap
        self.extras: list[FloatArray] = []  # sums of several leaving rows, (n, L) each; coded -1 - position overall

    # ------------------------------------------------------------------ rows by code

    def _fill(self, dst: FloatArray, codes: IntArray, sign: float) -> None:
        """``dst[i] = sign * row(codes[i])``: rows by absolute index (the ring before this block, or
        the block), summed groups, or -0.0 (adding it changes nothing, bit for bit) for :data:`NO_ROW`."""
        c, h0, cap0 = self.c, self.h0, self.cap0
        a, b = int(codes[0]), int(codes[-1])
        src: FloatArray | None = None
        if a >= 0 and b - a == codes.size - 1 and (codes.size < 3 or bool((np.diff(codes) == 1).all())):
            # consecutive frames (the common case): slices
            if a >= h0:
                src = c[a - h0 : b - h0 + 1]
            elif b < h0 and a % cap0 <= b % cap0:
                src = self.rec[a % cap0 : b % cap0 + 1]
        if src is not None:
            if sign < 0.0:
                np.negative(src, out=dst)
            else:
                dst[...] = src
            return
        new = codes >= h0
        old = np.flatnonzero((codes >= 0) & ~new)
        got = np.flatnonzero(new)
        summed = np.flatnonzero((codes < 0) & (codes != NO_ROW))
        if old.size:
            dst[old] = self.rec.take(codes[old] % cap0, axis=0)
        if got.size:
            dst[got] = c.take(codes[got] - h0, axis=0)
        if summed.size:
            dst[summed] = np.concatenate(self.extras)[-1 - codes[summed]]
        if sign < 0.0:
            np.negative(dst, out=dst)
        dst[codes == NO_ROW] = -0.0

    def _group_codes(self, steps: IntArray, next_before: IntArray | None = None, end: int = 0) -> IntArray:
        """Codes of the sums of the frames leaving at each of ``steps`` (with ``next_before``: only
        those the shadow holds), summed as ``RingWindowSums._push_contrib`` sums them (:meth:`~jointfit_core.record_ring.RecordRing.subtract_rows`,
        row after row; the frames left out are -0.0 rows, which change nothing)."""
        first = self.lo_before[steps]
        width = int((self.lo_after[steps] - first).max())
        idx = first[:, None] + np.arange(width)
        ok = idx < self.lo_after[steps][:, None]
        if next_before is not None:
            ok &= (idx < next_before[:, None]) | (idx >= end)
        buf = np.empty((idx.size, self.n_sums))
        self._fill(buf, np.where(ok, idx, NO_ROW).ravel(), 1.0)
        base = sum(e.shape[0] for e in self.extras)
        self.extras.append(buf.reshape(steps.size, width, self.n_sums).sum(axis=1))
        return -1 - (base + np.arange(steps.size, dtype=np.int64))

    def _reduce(self, start: FloatArray, columns: list[tuple[IntArray, float]]) -> FloatArray:
        """``start`` plus, step after step, each column's row times its sign, added one after the other."""
        used = [(codes, sign) for codes, sign in columns if codes.size and (codes != NO_ROW).any()]
        n = columns[0][0].size if used else 0
        block = np.empty((1 + n * len(used), self.n_sums))
        block[0] = start
        grid = block[1:].reshape(n, len(used), self.n_sums)
        for j, (codes, sign) in enumerate(used):
            self._fill(grid[:, j], codes, sign)
        out: FloatArray = np.add.reduce(block, axis=0)
        return out

    def _sums_columns(self, a: int) -> list[tuple[IntArray, float]]:
        """The live sums' operations of steps a .. M-1: + the new frame, - the leaving ones."""
        steps = np.arange(a, self.m)
        leave = np.where(self.n_leave[steps] == 1, self.lo_before[steps], NO_ROW)
        several = self.n_leave[steps] > 1
        if several.any():
            leave[several] = self._group_codes(steps[several])
        return [(self.h0 + steps, 1.0), (leave, -1.0)]

    # ------------------------------------------------------------------ results

    def sums_and_shadow(self, state: ShadowState) -> ShadowState:
        """The live sums and the shadow rebuild after the block, from their state before it.

        ``state``: ``(sums, shadow, active, next, end)`` (:data:`ShadowState`); returns the same after
        the block's pushes (the shadow's schedule worked out cycle by cycle).
        """
        sums, shadow_start, active, nxt, end = state
        m, h0, lo_after, lo_before, n_leave = self.m, self.h0, self.lo_after, self.lo_before, self.n_leave
        sums_start = sums
        sums_from = 0  # first step whose live-sum operations count (after the last replacement)
        k = 0
        if not active:  # the very first push: no shadow yet
            nxt, end, shadow_start, k, active = int(lo_after[0]), h0 + 1, np.zeros(self.n_sums), 1, True
        shadow = shadow_start
        while k < m:
            steps = np.arange(k, m)
            # next after each step, while the rebuild continues: u_j = max(u_{j-1}, lo_j + 1 - j)
            u = np.maximum.accumulate(np.concatenate([[nxt - (k - 1)], lo_after[k:] + 1 - steps]))[1:]
            next_after = u + steps
            done = np.flatnonzero(next_after >= end)
            last = k + int(done[0]) if done.size else m - 1
            cyc = np.arange(k, last + 1)
            next_before = np.concatenate([[nxt], next_after[: last - k]])
            m_j = np.maximum(next_before, lo_after[cyc])
            rebuild = np.where(m_j < end, m_j, NO_ROW)
            # leaving frames the shadow holds: rebuilt already, or added since the rebuild began
            first = lo_before[cyc]
            one = (n_leave[cyc] == 1) & ((first < next_before) | (first >= end))
            inside = np.where(one, first, NO_ROW)
            several = n_leave[cyc] > 1
            if several.any():
                inside[several] = self._group_codes(cyc[several], next_before[several], end)
            shadow = self._reduce(shadow_start, [(h0 + cyc, 1.0), (inside, -1.0), (rebuild, 1.0)])
            if done.size:  # the rebuild has covered the window: it replaces the live sums
                sums_start, sums_from = shadow, last + 1
                nxt, end = int(lo_after[last]), int(h0 + last + 1)
                shadow_start = shadow = np.zeros(self.n_sums)
            else:
                nxt = int(next_after[-1])
            k = last + 1
        return self._reduce(sums_start, self._sums_columns(sums_from)), shadow, active, nxt, end

    def stored_ring(self) -> tuple[FloatArray, FloatArray, int, int]:
        """The ring after the block: ``(rec, stamp, lo, hi)``, grown as the pushes would have grown it.

        The frames that stay are stored; the ring of the constructor is written in place unless it grew.
        """
        c, st, h0, cap, cap0 = self.c, self.st, self.h0, self.cap, self.cap0
        lo_end, hi_end = int(self.lo_after[-1]), h0 + self.m
        rec, stamp = self.rec, self.stamp
        if cap != cap0:
            keep_old = np.arange(max(self.lo0, lo_end), h0)
            rec = np.empty((cap, self.rec.shape[1]))
            stamp = np.empty(cap)
            rec[keep_old % cap] = self.rec[keep_old % cap0]
            stamp[keep_old % cap] = self.stamp[keep_old % cap0]
        at = max(lo_end, h0)
        while at < hi_end:  # at most two slices (the ring wraps once)
            slot = at % cap
            stop = min(hi_end, at + cap - slot)
            rec[slot : slot + stop - at] = c[at - h0 : stop - h0]
            stamp[slot : slot + stop - at] = np.nan if st is None else st[at - h0 : stop - h0]
            at = stop
        return rec, stamp, lo_end, hi_end
