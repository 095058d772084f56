"""Sums under exponential forgetting: every frame's weight decays by a constant factor per frame or per second.

:class:`ForgettingSums` is the part of :class:`~jointfit_core.stats.SlidingSums`
for half-lives. It needs no ring buffer: the sums decay as frames are added,
so old rounding errors decay with them; the reference point is moved by an
exact shift of the sums when the data have wandered from it. A block of
stored contributions is added in closed form (:meth:`ForgettingSums.block_weights`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .window_spec import WindowSpec

if TYPE_CHECKING:
    from .stats import ContribFn, RefFn, ShiftFn

__all__ = ["ForgettingSums"]

FloatArray = NDArray[np.float64]

#: Check every this many frames whether to move the reference point.
_REREF_EVERY = 256


class ForgettingSums:
    """Sums of per-frame contributions, each weighted by the decay since its frame.

    Parameters
    ----------
    spec : WindowSpec
        Exponential forgetting (``half_life`` in frames or ``half_life_s`` in seconds).
    n_sums : int
        Length L of a contribution.
    contrib, ref_of, shift : callable or None
        As :class:`~jointfit_core.stats.SlidingSums` takes them; the reference point is
        moved (every :data:`_REREF_EVERY` frames) only with both ``ref_of`` and ``shift``.
    count_index : ndarray of int, shape (K,)
        Entries of the contribution that are plain weights (counts).

    Attributes
    ----------
    sums : ndarray, shape (L,)
        The decayed sums.
    ref : ndarray, shape (3,)
        Their reference point.
    counts_sq : ndarray, shape (K,)
        Decayed sums of the squared weights of the count entries.
    """

    def __init__(
        self,
        spec: WindowSpec,
        n_sums: int,
        contrib: ContribFn | None,
        ref_of: RefFn | None,
        shift: ShiftFn | None,
        count_index: NDArray[np.intp],
    ) -> None:
        self.spec = spec
        self.n_sums = n_sums
        self._contrib = contrib
        self._ref_of = ref_of
        self._shift = shift
        self._count_index = count_index
        hl = spec.half_life if spec.half_life is not None else spec.half_life_s
        self._log_decay = -np.log(2.0) / float(hl)  # type: ignore[arg-type]
        self.clear()

    def clear(self) -> None:
        """Forget every frame."""
        self.ref = np.zeros(3)
        self.sums = np.zeros(self.n_sums)
        self.counts_sq = np.zeros(self._count_index.size)

    def push(self, record: FloatArray, stamp: float | None, n_pushed: int, last_stamp: float | None) -> None:
        """Decay the sums and add one frame's record (R,).

        ``stamp`` (s): needed by time half-lives; ``n_pushed``, ``last_stamp``: the frames
        pushed before this one, and the latest stamp (s) among them.
        """
        if n_pushed > 0:
            if self.spec.half_life_s is not None:
                assert stamp is not None and last_stamp is not None  # checked by SlidingSums.push
                steps = max(float(stamp) - last_stamp, 0.0)
            else:
                steps = 1.0
            decay = float(np.exp(self._log_decay * steps))
            self.sums *= decay
            self.counts_sq *= decay * decay
        c = record if self._contrib is None else self._contrib(record[None, :], self.ref[None, :])[0]
        self.sums += c
        self.counts_sq += c[self._count_index] ** 2
        if self._ref_of is not None and self._shift is not None and n_pushed % _REREF_EVERY == _REREF_EVERY - 1:
            new_ref = self._ref_of(self.sums, self.ref)
            if new_ref is not None:
                self.sums = self._shift(self.sums, self.ref, new_ref)
                self.ref = new_ref

    def block_weights(
        self, m: int, stamps: FloatArray | None, n_pushed: int, last_stamp: float | None
    ) -> tuple[FloatArray, float]:
        """Each frame's weight after a block of ``m`` frames, and the old sums'.

        Parameters
        ----------
        m : int
            Frames in the block (>= 1).
        stamps : ndarray, shape (m,), or None
            Their stamps (s); needed by time half-lives.
        n_pushed : int
            Frames pushed before the block.
        last_stamp : float or None
            The latest stamp among them (s).

        Returns
        -------
        w : ndarray, shape (m,)
            The product of the decays applied after each frame.
        w_old : float
            The decay of the sums before the block.

        Notes
        -----
        ``w_k`` is ``exp`` of the sum of the decays' exponents after frame k, so
        ``w_old sums + sum_k w_k c_k`` equals the sequential recursion of
        :meth:`push` up to rounding (relative differences of a few ulp per
        frame of the half-life, not bit for bit).
        """
        if self.spec.half_life_s is not None:
            st = stamps
            assert st is not None and (last_stamp is not None or n_pushed == 0)
            prev = np.empty(m)
            prev[0] = st[0] if n_pushed == 0 else last_stamp
            prev[1:] = st[:-1]
            steps = np.maximum(st - prev, 0.0)
        else:
            steps = np.ones(m)
        if n_pushed == 0:
            steps[0] = 0.0  # the first frame ever finds nothing to decay
        expo = self._log_decay * steps
        # after[k]: exponent of the decays applied after frame k (frames k+1 .. m-1)
        after = np.zeros(m)
        after[:-1] = np.cumsum(expo[::-1])[::-1][1:]
        return np.exp(after), float(np.exp(after[0] + expo[0]))

    def push_block(self, c: FloatArray, st: FloatArray | None, n_pushed: int, last_stamp: float | None) -> None:
        """Stored contributions (M, L) of a block, stamps (M,) s or None, added in closed form (:meth:`block_weights`)."""
        m = c.shape[0]
        w, w_old = self.block_weights(m, st, n_pushed, last_stamp)
        self.sums = w_old * self.sums + w @ c
        if self._count_index.size:
            self.counts_sq = w_old * w_old * self.counts_sq + (w * w) @ (c[:, self._count_index] ** 2)

    def add_weighted_sum(self, total: FloatArray, w_old: float) -> None:
        """A block given as its weighted sum ``total`` (L,) (weights from :meth:`block_weights`): ``sums <- w_old sums + total``."""
        self.sums = w_old * self.sums + total
