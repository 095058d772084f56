"""Posed frames waiting to enter a joint's sums, in preallocated arrays (the live feed's queue).

:meth:`~jointfit_core.joint_sums.RelativePoseSums.add_frame` puts a live frame here
and the sums take the queue as one block
(:meth:`~jointfit_core.joint_sums.RelativePoseSums.flush`), so that the live and the
offline feed share the block path. Appending writes into rows of arrays allocated
once (no per-frame allocation); :meth:`FrameQueue.block` hands the queued rows over
as a :class:`PosedBlock`, the form ``add_block`` takes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .segment_pair import PairSet
from .serial import NOMINAL_RATE_HZ

__all__ = ["FrameQueue", "PosedBlock"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class PosedBlock:
    """Frames whose two segments are posed, in order, as a joint's sums take them
    (:meth:`~jointfit_core.joint_sums.RelativePoseSums.add_block`; the offline feed's blocks and the
    live feed's queue, :meth:`FrameQueue.block`).

    Attributes
    ----------
    R, d, ss : ndarray, shapes (M, 2, 3, 3), (M, 2, 3), (M, 2)
        Per frame, the parent's and the child's rotation (template frame to world), translation
        (input units) and pose-fit residual sum of squares (input units squared).
    W_sets, dof_sets : ndarray, shapes (S, 72), (S, 2)
        The unit pose covariances and dofs of ``S`` visible marker sets.
    which : ndarray of int, shape (M,)
        Each frame's visible marker set (its row in ``W_sets`` and ``dof_sets``).
    paired : ndarray of bool, shape (M,)
        Per frame, whether it carries its lag pair with the frame before it (the block's
        previous row; for row 0, the last frame the window took).
    stamps : ndarray, shape (M,), or None
        Seconds (None: a window without stamps).
    times : ndarray, shape (M,)
        The frames' times for the pairs at lags in seconds (the stamps, or frame numbers at the
        nominal rate).
    Y, wn_sets : ndarray, shapes (M, 2, Pmax, 3), (S, 2, Pmax), or None
        Skin markers: the frames' markers and the marker sets' pose weights, for the white-noise
        sums (:class:`~jointfit_core.white_noise_sums.SecondDifferences`); None: they add nothing.
    """

    R: FloatArray
    d: FloatArray
    ss: FloatArray
    W_sets: FloatArray
    dof_sets: FloatArray
    which: NDArray[np.intp]
    paired: NDArray[np.bool_]
    stamps: FloatArray | None
    times: FloatArray
    Y: FloatArray | None = None
    wn_sets: FloatArray | None = None

    def rows(self, rows: NDArray[np.intp], paired: NDArray[np.bool_]) -> PosedBlock:
        """The block's frames ``rows`` (in order) with new lag-pair flags ``paired`` (the marker sets kept whole)."""
        return PosedBlock(
            R=self.R[rows],
            d=self.d[rows],
            ss=self.ss[rows],
            W_sets=self.W_sets,
            dof_sets=self.dof_sets,
            which=self.which[rows],
            paired=paired,
            stamps=None if self.stamps is None else self.stamps[rows],
            times=self.times[rows],
            Y=None if self.Y is None else self.Y[rows],
            wn_sets=self.wn_sets,
        )


class FrameQueue:
    """Up to ``capacity`` posed frames of one kind (stamped or not, with markers or not), oldest first.

    Parameters
    ----------
    capacity : int
        Rows allocated; :attr:`full` once that many are queued.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self.n = 0
        self._R = np.empty((capacity, 2, 3, 3))
        self._d = np.empty((capacity, 2, 3))
        self._ss = np.empty((capacity, 2))
        self._stamps = np.empty(capacity)
        self._numbers = np.empty(capacity)
        self._paired = np.empty(capacity, dtype=bool)
        self._Y: FloatArray | None = None  # (capacity, 2, Pmax, 3), allocated with the first frame's markers
        self._pairs: list[PairSet] = []
        self.kind: tuple[bool, bool] = (False, False)  # (stamped, with markers) of the queued frames

    @property
    def full(self) -> bool:
        """True when no row is left."""
        return self.n >= self.capacity

    def fits(self, stamped: bool, markers: bool) -> bool:
        """Whether a frame of this kind may join the queued ones (any may join an empty queue)."""
        return self.n == 0 or self.kind == (stamped, markers)

    def append(
        self,
        R: FloatArray,
        d: FloatArray,
        ss: FloatArray,
        pairs: PairSet,
        stamp: float | None,
        frame_no: int,
        Y: FloatArray | None,
        paired: bool,
    ) -> None:
        """Copy one frame into the next row (the caller checked :meth:`fits` and :attr:`full`).

        ``R`` (2, 3, 3), ``d`` (2, 3), ``ss`` (2,), ``Y`` (2, Pmax, 3) or None, as
        :meth:`~jointfit_core.joint_sums.RelativePoseSums.add_frame` takes them.
        """
        k = self.n
        self._R[k] = R
        self._d[k] = d
        self._ss[k] = ss
        self._stamps[k] = np.nan if stamp is None else stamp
        self._numbers[k] = frame_no
        self._paired[k] = paired
        if Y is not None:
            if self._Y is None or self._Y.shape[1:] != Y.shape:
                self._Y = np.empty((self.capacity, *Y.shape))
            self._Y[k] = Y
        self._pairs.append(pairs)
        self.kind = (stamp is not None, Y is not None)
        self.n = k + 1

    def block(self) -> PosedBlock:
        """The queued frames (views of the rows) with their distinct marker sets; empties the queue.

        The views stay valid until the next :meth:`append`.
        """
        m = self.n
        sets: dict[int, int] = {}
        rows: list[PairSet] = []
        which = np.empty(m, dtype=np.intp)
        for k, ps in enumerate(self._pairs):  # a few distinct sets (occlusion patterns) per block
            row = sets.get(id(ps))
            if row is None:
                row = sets[id(ps)] = len(rows)
                rows.append(ps)
            which[k] = row
        stamped, markers = self.kind
        stamps = self._stamps[:m] if stamped else None
        times = stamps if stamps is not None else self._numbers[:m] / NOMINAL_RATE_HZ
        Y = self._Y[:m] if markers and self._Y is not None else None
        out = PosedBlock(
            R=self._R[:m],
            d=self._d[:m],
            ss=self._ss[:m],
            W_sets=np.array([ps.W_flat for ps in rows]),
            dof_sets=np.array([ps.dof for ps in rows]),
            which=which,
            paired=self._paired[:m],
            stamps=stamps,
            times=times,
            Y=Y,
            wn_sets=np.array([ps.wn for ps in rows]) if Y is not None else None,
        )
        self.n = 0
        self._pairs = []
        return out
