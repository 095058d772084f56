"""One joint's window of relative-pose statistics: what each frame adds, and the sums.

:class:`RelativePoseSums` is the part of an online joint
(:class:`~jointfit_core.estimator.OnlineJoint`) that belongs to the joint alone
(issue 16, item 3): given the two segments' poses of a frame (or of a block of
frames), it forms the frame's contribution (the relative pose ``Z = [Q | t]``,
its outer product, the pose-noise terms of the visible marker sets, the lag
pairs, the soft-tissue feature sums and the movement) and pushes it into the
sliding window (:class:`~jointfit_core.stats.SlidingSums`). Posing and gating
the segments happen before it; solving reads :attr:`RelativePoseSums.window`.
A frame fed alone is queued and summed with the frames after it as a block
(one code path for the live and the offline feed, vectorised over the queue),
before anything reads the sums.

The layout of the sums vector is defined here (``_Z`` ... ``_FM``); the solve
(:func:`~jointfit_core.estimator.solve_window`) reads it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .artefact_sums import N_FEATURE_MOMENTS, N_FEATURE_SUMS, feature_sums
from .errors import InputError
from .frame_queue import FrameQueue, PosedBlock
from .segment_pair import PairSet
from .serial import (
    LAG_TOLERANCE,
    N_TIME_LAG_SUMS,
    SERIAL_LAGS_S,
    LagHistory,
    LagSums,
    TimeLagSums,
)
from .stats import SlidingSums, WindowSpec
from .white_noise_sums import SecondDifferences
from .window_entries import WindowEntries

__all__ = ["MOVING_DEG", "PENDING_MAX", "RelativePoseSums", "moving_seconds"]

FloatArray = NDArray[np.float64]

#: Sums layout, with Z = [Q | t] (3 x 4, row-major) the relative pose: n, vec(Z) (12),
#: vec(Z) vec(Z)^T (144: holds Q (x) Q, Q^T t and |t|^2), unit W_p (36), unit W_c (36),
#: ss_p, dof_p, ss_c, dof_c, then the lag pair ending at the frame
#: (:class:`~jointfit_core.serial.LagSums`): n_pairs, Z_k + Z_{k-1} (12), Z_k^T Z_{k-1} (16).
_Z = slice(1, 13)
_ZZ = slice(13, 157)
_W = slice(157, 229)
_SS = 229
_LAG = 233
#: Then the soft-tissue feature sums (:func:`~jointfit_core.artefact_sums.feature_sums`; zero for rigid markers).
_FS = slice(_LAG + 29, _LAG + 29 + N_FEATURE_SUMS)
#: Then the lag pairs in seconds (:class:`~jointfit_core.serial.TimeLagSums`, :class:`~jointfit_core.serial.LagHistory`).
_TL = slice(_FS.stop, _FS.stop + N_TIME_LAG_SUMS)
#: Then the seconds of movement the frame adds (:func:`moving_seconds`).
_MOVE = _TL.stop
#: Then, skin markers only (zero for rigid), the white-noise sums of the frame triple ending at the frame:
#: ss_p, dof_p, ss_c, dof_c (:class:`~jointfit_core.white_noise_sums.SecondDifferences`).
_WN = slice(_MOVE + 1, _MOVE + 5)
_N_SUMS = _WN.stop
#: Skin hinges only, at the end: the features' second moments (the alignment reading's Gram).
_FM = slice(_N_SUMS, _N_SUMS + N_FEATURE_MOMENTS)
_N_SUMS_HINGE = _FM.stop

#: Movement: a frame in the statistics counts as movement when its relative rotation differs by more
#: than this (deg) from that of its lag pair about 0.32 s earlier (``SERIAL_LAGS_S[3]``, a frame
#: 0.16-0.48 s before it). White noise of 1 mm on 50 mm clusters moves it by ~2 deg; functional
#: movements turn joints at 30-100 deg/s (10-30 deg in 0.32 s).
MOVING_DEG = 5.0
_MOVE_LAG = SERIAL_LAGS_S.index(0.32)
_MOVE_NODE = (N_TIME_LAG_SUMS - 2) // len(SERIAL_LAGS_S)
_MOVE_AT = 2 + _MOVE_LAG * _MOVE_NODE  # that lag's node in the time-lag contribution
_MOVE_GAP_MAX = (1.0 + LAG_TOLERANCE) * SERIAL_LAGS_S[_MOVE_LAG]
_MOVE_TRACE_MIN = 1.0 + 2.0 * math.cos(math.radians(MOVING_DEG))  # tr(Q_k^T Q_j) at that turn


def moving_seconds(lagged: FloatArray) -> FloatArray:
    """Seconds of movement frames add, from their time-lag contributions ``(..., N_TIME_LAG_SUMS)`` -> ``(...)``.

    A frame whose pair at 0.32 s (:class:`~jointfit_core.serial.LagHistory`) turned by more than
    :data:`MOVING_DEG` adds its gap to the frame before it (at most 0.48 s, the pair's reach; an
    occlusion's gap is not movement); other frames add 0. ``tr(Q_k^T Q_j) = 1 + 2 cos(angle)`` is
    the trace of the top-left block of the pair's ``Z_k^T Z_j``.
    """
    node = lagged[..., _MOVE_AT : _MOVE_AT + _MOVE_NODE]
    trace = node[..., 13] + node[..., 18] + node[..., 23]
    out: FloatArray = np.where((node[..., 0] > 0.0) & (trace < _MOVE_TRACE_MIN), np.minimum(lagged[..., 1], _MOVE_GAP_MAX), 0.0)
    return out


#: Most frames :meth:`RelativePoseSums.add_frame` queues before it sums them (the node reads the sums
#: every estimate period, which sums the queue sooner: 10 frames at 100 Hz).
PENDING_MAX = 64


class RelativePoseSums:
    """A joint's sliding window of relative-pose sums, fed frame by frame or block by block.

    Parameters
    ----------
    spec : WindowSpec
        The window (frames, seconds or exponential forgetting).
    skin : bool
        Keep the soft-tissue feature sums (either segment on skin markers).
    moments : bool
        Keep the features' second moments too (skin hinges).
    max_frames : int or None, optional
        A time window's most frames: at a faster input, at most one frame per
        ``seconds / max_frames`` of stamp time enters (:class:`~jointfit_core.window_entries.WindowEntries`);
        None: every frame.

    Attributes
    ----------
    window : SlidingSums or None
        The window's sums (layout: this module's ``_Z`` ... ``_FM``); None until a frame entered.
    chained : bool
        Whether the last frame that reached the joint could enter the statistics (it entered, or
        :attr:`entries` left it out of a time window fed faster than it holds): the next frame then
        carries its lag pair with it (see :class:`~jointfit_core.joint_estimate.JointEstimate`, Notes,
        *lag pairs*). The joint clears it for a frame that reaches it but cannot enter.
    entries : WindowEntries
        Which frames enter (a time window fed faster than ``max_frames`` allows leaves some out;
        :attr:`WindowEntries.thinned <jointfit_core.window_entries.WindowEntries.thinned>` counts them).

    Notes
    -----
    **What a frame adds.** Per frame, both poses are fitted to the visible
    markers (Stoddart eq. 4); a frame where a segment's visible markers are
    nearly collinear or bunched (rotation variance above
    :data:`~jointfit_core.segments.POSE_VAR_RATIO_MAX` times the full
    template's) does not reach the window. The window keeps the sums of
    :class:`~jointfit_core.segments.PoseSums`, of the unit-noise local pose
    covariances of the visible marker sets, and of the pose-fit residuals;
    the joint's noise estimate
    (:attr:`~jointfit_core.joint_estimate.JointEstimate.noise_std`) is the
    pooled residual over the window (``sum SS / sum (3 n_vis - 6)``, not
    corrected for the template's own degrees of freedom, which is negligible
    after a few dozen frames).
    """

    def __init__(self, spec: WindowSpec, skin: bool, moments: bool, max_frames: int | None = None) -> None:
        self.spec = spec
        #: Which frames enter a time window faster than it holds (every frame for other windows).
        self.entries = WindowEntries(spec.seconds, max_frames)
        self._skin = skin
        self._moments = moments
        self.n_sums = _N_SUMS_HINGE if moments else _N_SUMS
        self._sums: SlidingSums | None = None
        self._queue = FrameQueue(PENDING_MAX)  # frames added, not yet summed (add_frame)
        self.chained = False
        self._z_prev = np.zeros((3, 4))  # Z of the previous frame that entered the statistics
        self._history = LagHistory()  # recent frames in the statistics, for the pairs at lags in seconds
        self._second = SecondDifferences()  # skin: the white-noise sums' last two frames

    @property
    def window(self) -> SlidingSums | None:
        """The window's sums, every frame added so far in them (None until a frame entered)."""
        if self._queue.n:
            self.flush()
        return self._sums

    def _window(self) -> SlidingSums:
        if self._sums is None:
            # a thinned time window holds at most max_frames + 1 frames (its span cuts at most that many bins;
            # one more for rounding at the bins' edges): its ring need not double past them
            cap = self.entries.max_frames
            self._sums = SlidingSums(self.spec, self.n_sums, self.n_sums, None, max_frames=1_000_000 if cap is None else cap + 2)
        return self._sums

    @property
    def n_pending(self) -> int:
        """Frames added by :meth:`add_frame` and not summed yet (:meth:`flush` sums them)."""
        return self._queue.n

    def add_frame(
        self,
        R: FloatArray,
        d: FloatArray,
        ss: FloatArray,
        pairs: PairSet,
        stamp: float | None,
        frame_no: int,
        Y: FloatArray | None = None,
    ) -> bool:
        """Add one frame whose two segments are posed (summed at the next :meth:`flush`); whether it entered.

        Parameters
        ----------
        R : ndarray, shape (2, 3, 3)
            Parent and child rotations (template frame to world).
        d : ndarray, shape (2, 3)
            Their translations (input units).
        ss : ndarray, shape (2,)
            Their pose fits' residual sums of squares (input units squared).
        pairs : PairSet
            The frame's visible marker sets (their unit pose covariances and dofs).
        stamp : float or None
            Seconds; without one, the frame's time is ``frame_no`` at the nominal rate.
        frame_no : int
            The frame's number (1-based count of the frames that reached the joint).
        Y : ndarray, shape (2, Pmax, 3), optional
            Both segments' markers (input units): skin markers' white-noise sums
            (:class:`~jointfit_core.white_noise_sums.SecondDifferences`); without it they add nothing.

        Notes
        -----
        The frame is copied into a queue and summed with the frames queued after it by
        :meth:`add_block` (one code path for frames and blocks, vectorised over the queue): at
        the latest after :data:`PENDING_MAX` frames, and whenever the sums are read
        (:attr:`window`, :meth:`entered` and the readers built on them), so that a reader never
        sees a sum without the frames added before. A live frame's outputs do not depend on the
        sums, so the node publishes them without this work. A time window fed faster than it holds
        (:attr:`entries`) leaves the frame out (False), keeping the chain of lag pairs.
        """
        paired = self.entries.admit(stamp, self.chained)
        self.chained = True
        if paired is None:
            return False
        queue = self._queue
        if not queue.fits(stamp is not None, Y is not None):
            self.flush()  # a block holds frames of one kind
        queue.append(R, d, ss, pairs, stamp, frame_no, Y, paired)
        if queue.full:
            self.flush()
        return True

    def flush(self) -> None:
        """Sum the frames :meth:`add_frame` queued, in order, as one block."""
        if self._queue.n:
            self._sum_block(self._queue.block())

    def add_block(self, block: PosedBlock) -> None:
        """Push a block of frames whose two segments are posed, in a few vectorised steps.

        Notes
        -----
        The frames :meth:`add_frame` queued are summed first (the order is kept). Exponential
        forgetting sums the block's weighted contributions with matrix products, never forming
        them one per frame. A time window fed faster than it holds takes the block's frames
        that :attr:`entries` admits, as :meth:`add_frame` would one by one.
        """
        self.flush()
        rows, paired = self.entries.admit_block(block.stamps, block.paired)
        if rows is not None:
            if rows.size == 0:
                return
            block = block.rows(rows, paired)
        self._sum_block(block)

    def _sum_block(self, block: PosedBlock) -> None:
        """:meth:`add_block` of frames that come after every frame summed so far."""
        R, d, ss, W_sets, dof_sets = block.R, block.d, block.ss, block.W_sets, block.dof_sets
        which, paired, stamps, Y, wn_sets = block.which, block.paired, block.stamps, block.Y, block.wn_sets
        m = R.shape[0]
        window = self._window()
        x = np.empty((m, 3, 4))
        x[:, :, :3] = R[:, 1]
        np.subtract(d[:, 1], d[:, 0], out=x[:, :, 3])
        z = np.matmul(np.swapaxes(R[:, 0], 1, 2), x)  # [Q | t] = R_p^T [R_c | d_c - d_p]
        zf = z.reshape(m, 12)
        # Lag pairs: the previous frame that entered is the previous row (the previous block's last for row 0).
        z_prev = np.empty_like(z)
        z_prev[0] = self._z_prev
        z_prev[1:] = z[:-1]
        lagged = np.empty((m, N_TIME_LAG_SUMS))
        self._history.contributions(np.asarray(block.times, dtype=np.float64), z, lagged)
        white = np.zeros((m, 4))
        if self._skin and Y is not None and wn_sets is not None:
            white = self._second.add_many(Y, wn_sets[which], R, d, paired)
        if window.spec.exponential:
            self._push_weighted(window, z, z_prev, ss, W_sets, dof_sets, which, paired, stamps, lagged, white)
        else:
            pr = np.flatnonzero(paired)
            c = np.empty((m, self.n_sums))
            c[:, 0] = 1.0
            c[:, _Z] = zf
            np.multiply(zf[:, :, None], zf[:, None, :], out=c[:, _ZZ].reshape(m, 12, 12))
            c[:, _W] = W_sets[which]
            c[:, _SS : _SS + 4 : 2] = ss
            c[:, _SS + 1 : _SS + 4 : 2] = dof_sets[which]
            c[:, _LAG:] = 0.0
            c[pr, _LAG] = 1.0
            c[pr, _LAG + 1 : _LAG + 13] = (z[pr] + z_prev[pr]).reshape(pr.size, 12)
            if self._skin:
                fsum = feature_sums(z[:, :, :3], z[:, :, 3], self._moments)
                c[:, _FS] = fsum[:, :N_FEATURE_SUMS]
                c[:, _N_SUMS:] = fsum[:, N_FEATURE_SUMS:]
            c[:, _TL] = lagged
            c[:, _MOVE] = moving_seconds(lagged)
            c[:, _WN] = white
            c[pr, _LAG + 13 : _LAG + 29] = np.matmul(np.swapaxes(z[pr], 1, 2), z_prev[pr]).reshape(pr.size, 16)
            window.push_many(c, stamps)
        self._z_prev[...] = z[-1]

    def _push_weighted(
        self,
        window: SlidingSums,
        z: FloatArray,
        z_prev: FloatArray,
        ss: FloatArray,
        W_sets: FloatArray,
        dof_sets: FloatArray,
        which: NDArray[np.intp],
        paired: NDArray[np.bool_],
        stamps: FloatArray | None,
        lagged: FloatArray,
        white: FloatArray,
    ) -> None:
        """:meth:`add_block` under exponential forgetting: no window ring to keep records for, one weighted sum."""
        m = z.shape[0]
        zf = z.reshape(m, 12)
        w, w_old = window.block_weights(m, stamps)
        total = np.empty(self.n_sums)
        total[0] = w.sum()
        total[_Z] = w @ zf
        total[_ZZ] = ((zf * w[:, None]).T @ zf).ravel()
        set_weight = np.bincount(which, weights=w, minlength=W_sets.shape[0])
        total[_W] = set_weight @ W_sets
        total[_SS : _SS + 4 : 2] = w @ ss
        total[_SS + 1 : _SS + 4 : 2] = set_weight @ dof_sets
        # rows without a lag pair weigh zero (cheaper than gathering the paired rows)
        wp = w * paired
        total[_LAG] = wp.sum()
        total[_LAG + 1 : _LAG + 13] = wp @ (z + z_prev).reshape(m, 12)
        cross = (z * wp[:, None, None]).reshape(-1, 4).T @ z_prev.reshape(-1, 4)
        total[_LAG + 13 : _LAG + 29] = cross.ravel()
        if self._skin:
            fsum = w @ feature_sums(z[:, :, :3], z[:, :, 3], self._moments)
            total[_FS] = fsum[:N_FEATURE_SUMS]
            total[_N_SUMS:] = fsum[N_FEATURE_SUMS:]  # the moments: skin hinges only
        else:
            total[_FS] = 0.0
        total[_TL] = w @ lagged
        total[_MOVE] = w @ moving_seconds(lagged)
        total[_WN] = w @ white
        window.push_weighted_sum(total, w_old, m, stamps)

    def entered(self, status: str) -> FloatArray:
        """The window's sums vector; InputError (naming ``status``) when no frame has entered the statistics yet."""
        window = self.window
        if window is None or window.sums[0] <= 0.0:
            raise InputError(f"no frame has entered the statistics yet ({status or 'no posed frame'})")
        return window.sums

    def lag_sums(self, status: str) -> LagSums:
        """The window's lag-pair sums (:class:`~jointfit_core.serial.LagSums`)."""
        return LagSums.from_vector(self.entered(status)[_LAG : _LAG + 29])

    def time_lag_sums(self, status: str) -> TimeLagSums:
        """The window's lag-pair sums at lags in seconds (:class:`~jointfit_core.serial.TimeLagSums`)."""
        return TimeLagSums.from_vector(self.entered(status)[_TL])

    @property
    def movement_seconds(self) -> float:
        """Seconds of movement in the window (weighted, with forgetting; :func:`moving_seconds`)."""
        window = self.window
        return 0.0 if window is None else float(window.sums[_MOVE])

    def noise_sums(self) -> tuple[FloatArray, FloatArray] | None:
        """The window's pose-fit residual sums of squares and dofs, (2,) each (parent, child); None before any frame."""
        window = self.window
        if window is None:
            return None
        s = window.sums
        return s[_SS : _SS + 4 : 2], s[_SS + 1 : _SS + 4 : 2]
