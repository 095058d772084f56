"""Correlation in time of the joint-constraint residual, from running sums: frame to frame and at lags in seconds.

A closed-form joint estimate averages a per-frame constraint residual over N
frames. Its covariance, propagated as if the frames were independent, is
far too small when the residual is smooth in time (soft-tissue artefact at
100 Hz: lag-1 autocorrelation 0.95-0.998), because then N frames carry the
information of about ``N / F`` independent ones, ``F`` the residual's
integrated autocorrelation. This module measures the autocorrelation of the
residual of the two-segment constraint from sums that an online estimator
keeps in O(1) per frame, and gives the matching batch formulas (for tests
and offline use): at lag 1 (:class:`LagSums`), and at lags in seconds
(:data:`SERIAL_LAGS_S`, :class:`TimeLagSums`, :class:`LagHistory`), from
which :func:`integrated_factor` gives ``F`` whatever the frame rate (the
AR(1) ``(1 + rho) / (1 - rho)`` of the lag-1 ``rho`` alone does not:
``bench/serial_lags.py``). The lag sums also tell the residual's smooth part
from white noise (:func:`smooth_energy_from_lags`), which scales the
soft-tissue covariance, and give the hinge's axis-alignment residual
(:func:`rotation_residual_sums`).

The residual of frame k is linear in the parameters ``x = (c_p, c_c)``:
``r_k = c_p - Q_k c_c - t_k = c_p - Z_k u`` with ``Z_k = [Q_k | t_k]``
(3 x 4, the relative pose of the child in the parent frame, as in
:class:`~jointfit_core.segments.PoseSums`) and ``u = (c_c, 1)``. So

``sum_k r_k . r_{k-1} = m |c_p|^2 - c_p^T (sum_k (Z_k + Z_{k-1})) u + u^T (sum_k Z_k^T Z_{k-1}) u``

over the ``m`` lag pairs (:class:`LagSums`), and
``sum_k |r_k|^2 = n |c_p|^2 - 2 c_p^T (sum_k Z_k) u + u^T (sum_k Z_k^T Z_k) u``
over the ``n`` frames (:class:`~jointfit_core.segments.PoseSums`). Written
as ``r_k = A_k x - b_k`` with ``A_k = [I, -Q_k]``, ``b_k = t_k``, the lag sum
is ``x^T sym(sum A_k^T A_{k-1}) x - x^T sum (A_k^T b_{k-1} + A_{k-1}^T b_k) +
sum b_k . b_{k-1}``; the 6x6 matrix is ``[[m I, -P_Q / 2], [-P_Q^T / 2,
sym(C_QQ)]]`` with ``P_Q`` and ``C_QQ`` the rotation blocks of ``sum_pair``
and ``cross``, so the 29 numbers of :class:`LagSums` hold all of it.

The online estimator stores the pair ``(k-1, k)`` with frame k (see
:class:`~jointfit_core.estimator.OnlineJoint`), so a window's lag sums are
:func:`lag_sums_from_relative` over its frames and the frame before them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .segments import PoseSums

__all__ = [
    "RHO_MAX",
    "LagSums",
    "SerialInflation",
    "lag_sums_from_relative",
    "residual_sum_squares_from_sums",
    "residual_lag_sum_from_sums",
    "lag1_autocorrelation_from_sums",
    "constraint_residual_autocorrelation",
    "serial_factor",
    "hinge_residual_pair",
    "rotation_residual_sums",
]

FloatArray = NDArray[np.float64]

#: Upper clip of the autocorrelation used for the inflation (keeps the factor finite,
#: at most 1999); the default of :func:`jointfit_core.model_error.residual_inflation`.
RHO_MAX = 0.999


@dataclass(frozen=True, eq=False)
class LagSums:
    """Sums over lag pairs ``(k-1, k)`` of consecutive frames: all that ``sum r_k . r_{k-1}`` needs.

    Attributes
    ----------
    n_pairs : float
        Number of pairs summed (sum of their weights under forgetting).
    sum_pair : ndarray, shape (3, 4)
        ``sum (Z_k + Z_{k-1})`` with ``Z_k = [Q_k | t_k]`` (rotation dimensionless,
        translation in input units).
    cross : ndarray, shape (4, 4)
        ``sum Z_k^T Z_{k-1}``: ``[[sum Q_k^T Q_{k-1}, sum Q_k^T t_{k-1}],
        [sum t_k^T Q_{k-1}, sum t_k . t_{k-1}]]``.
    """

    n_pairs: float
    sum_pair: FloatArray
    cross: FloatArray

    @classmethod
    def from_vector(cls, v: ArrayLike) -> LagSums:
        """From the flat layout ``(n_pairs, vec(sum_pair) (12), vec(cross) (16))`` (29,), row-major."""
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (29,):
            raise InputError(f"lag sums: expected a vector of 29 numbers, got shape {a.shape}")
        return cls(float(a[0]), a[1:13].reshape(3, 4).copy(), a[13:29].reshape(4, 4).copy())


@dataclass(frozen=True)
class SerialInflation:
    """The serial-correlation correction applied to an estimate's covariances.

    Attributes
    ----------
    rho : float
        ``rho_raw`` clipped to ``[0, RHO_MAX]`` (reported; the factor is not computed from it alone).
    rho_raw : float
        Lag-1 (frame-to-frame) autocorrelation of the constraint residual over
        the window (NaN when there is no lag pair or no residual).
    factor : float
        What the covariances were multiplied by: the integrated autocorrelation
        of the residual over :data:`SERIAL_WINDOW_S` (:func:`integrated_factor`
        of its correlation at the frame interval and at :data:`SERIAL_LAGS_S`);
        1 when the correction is switched off.
    n_pairs : float
        Lag-1 pairs in the window (their weight under forgetting).
    frame_interval_s : float
        Mean gap between consecutive frames in the window (s; NaN when not
        known, e.g. in calibrations saved before it existed).
    """

    rho: float
    rho_raw: float
    factor: float
    n_pairs: float
    frame_interval_s: float = float("nan")

    @property
    def correlation_time_s(self) -> float:
        """Seconds of data per independent sample, ``factor * frame_interval_s``: the same at any frame rate."""
        return self.factor * self.frame_interval_s


def _z(Q: FloatArray, t: FloatArray) -> FloatArray:
    return np.concatenate([Q, t[:, :, None]], axis=2)


def lag_sums_from_relative(Q_parent_child: ArrayLike, t_parent_child: ArrayLike) -> LagSums:
    """Lag-pair sums of a sequence of relative poses in time order.

    Parameters
    ----------
    Q_parent_child : array_like, shape (N, 3, 3)
        Child-to-parent rotations ``R_p^T R_c``, frames in time order; NaN
        for a frame where a segment was not posed.
    t_parent_child : array_like, shape (N, 3)
        ``R_p^T (d_c - d_p)``, input units.

    Returns
    -------
    LagSums
        Over the pairs of consecutive rows ``(k-1, k)`` that are both finite
        (a NaN row breaks the chain).
    """
    Q = np.asarray(Q_parent_child, dtype=np.float64)
    t = np.asarray(t_parent_child, dtype=np.float64)
    if Q.ndim != 3 or Q.shape[1:] != (3, 3) or t.shape != (Q.shape[0], 3):
        raise InputError(
            f"lag sums: expected Q of shape (N, 3, 3) and t of shape (N, 3), got {Q.shape} and {t.shape}"
        )
    ok = np.asarray(np.isfinite(Q).all(axis=(1, 2)) & np.isfinite(t).all(axis=1), dtype=bool)
    pairs = ok[1:] & ok[:-1]
    Z = _z(Q, t)
    cur, prev = Z[1:][pairs], Z[:-1][pairs]
    return LagSums(
        n_pairs=float(pairs.sum()),
        sum_pair=(cur + prev).sum(axis=0),
        cross=np.einsum("nji,njk->ik", cur, prev),
    )


def residual_sum_squares_from_sums(sums: PoseSums, centre_parent: ArrayLike, centre_child: ArrayLike) -> float:
    """``sum_k |c_p - Q_k c_c - t_k|^2`` over the summed frames (clipped at 0 against rounding)."""
    c_p = np.asarray(centre_parent, dtype=np.float64)
    c_c = np.asarray(centre_child, dtype=np.float64)
    ss = (
        float(sums.n) * float(c_p @ c_p + c_c @ c_c)
        + float(sums.sum_tt)
        - 2.0 * float(c_p @ (sums.S @ c_c + sums.sum_t))
        + 2.0 * float(c_c @ sums.sum_qt_t)
    )
    return max(ss, 0.0)


def residual_lag_sum_from_sums(lag: LagSums, centre_parent: ArrayLike, centre_child: ArrayLike) -> float:
    """``sum_k r_k . r_{k-1}`` over the lag pairs, ``r_k = c_p - Q_k c_c - t_k`` (see the module notes)."""
    c_p = np.asarray(centre_parent, dtype=np.float64)
    u = np.ones(4)
    u[:3] = centre_child
    return float(c_p @ (lag.n_pairs * c_p - lag.sum_pair @ u)) + float(u @ (lag.cross @ u))


def _rho(lag_sum: float, n_pairs: float, ss: float, n: float) -> float:
    if not (n_pairs > 0.0 and n > 0.0 and ss > 0.0):
        return float("nan")
    return (lag_sum / n_pairs) / (ss / n)


def lag1_autocorrelation_from_sums(
    sums: PoseSums, lag: LagSums, centre_parent: ArrayLike, centre_child: ArrayLike
) -> float:
    """Lag-1 autocorrelation of the constraint residual at ``(c_p, c_c)``, from running sums.

    Parameters
    ----------
    sums : PoseSums
        Sums over the frames.
    lag : LagSums
        Sums over the lag pairs.
    centre_parent, centre_child : array_like, shape (3,)
        Where the residual ``c_p - Q_k c_c - t_k`` is evaluated (input units).

    Returns
    -------
    float
        ``(sum_pairs r_k . r_{k-1} / n_pairs) / (sum_frames |r_k|^2 / n)``,
        unclipped; NaN without pairs or with a zero residual.

    Notes
    -----
    The mean products per pair over the mean square per frame: the ratio of
    the two sample moments, so that a pair set that does not cover every
    frame (chain breaks, window boundaries) is compared with the frames'
    mean square, not their total. The residual is not centred: at the
    least-squares ``c_p`` its mean is zero (the normal equations' first
    block), up to the bias compensation's small shift.
    """
    ss = residual_sum_squares_from_sums(sums, centre_parent, centre_child)
    return _rho(residual_lag_sum_from_sums(lag, centre_parent, centre_child), lag.n_pairs, ss, float(sums.n))


def constraint_residual_autocorrelation(
    Q_parent_child: ArrayLike, t_parent_child: ArrayLike, x: ArrayLike
) -> float:
    """Lag-1 autocorrelation of ``r_k = c_p - Q_k c_c - t_k`` computed from the residuals themselves.

    Parameters
    ----------
    Q_parent_child : array_like, shape (N, 3, 3)
        Relative rotations in time order, NaN for unused frames.
    t_parent_child : array_like, shape (N, 3)
        Relative translations (input units).
    x : array_like, shape (6,)
        ``(c_p, c_c)``, input units.

    Returns
    -------
    float
        As :func:`lag1_autocorrelation_from_sums` with the frames and the
        consecutive finite pairs of the sequence (the direct batch formula).
    """
    Q = np.asarray(Q_parent_child, dtype=np.float64)
    t = np.asarray(t_parent_child, dtype=np.float64)
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (6,):
        raise InputError(f"x: expected (c_p, c_c) of shape (6,), got {a.shape}")
    if Q.ndim != 3 or Q.shape[1:] != (3, 3) or t.shape != (Q.shape[0], 3):
        raise InputError(f"expected Q of shape (N, 3, 3) and t of shape (N, 3), got {Q.shape} and {t.shape}")
    ok = np.asarray(np.isfinite(Q).all(axis=(1, 2)) & np.isfinite(t).all(axis=1), dtype=bool)
    r = np.zeros((Q.shape[0], 3))
    r[ok] = a[:3] - np.einsum("nij,j->ni", Q[ok], a[3:]) - t[ok]
    pairs = ok[1:] & ok[:-1]
    lag_sum = float(np.einsum("ni,ni->", r[1:][pairs], r[:-1][pairs]))
    return _rho(lag_sum, float(pairs.sum()), float(np.einsum("ni,ni->", r, r)), float(ok.sum()))


def serial_factor(rho_raw: float, rho_max: float = RHO_MAX) -> tuple[float, float]:
    """``(rho, (1 + rho) / (1 - rho))`` with ``rho = clip(rho_raw, 0, rho_max)`` (NaN counts as 0).

    Parameters
    ----------
    rho_raw : float
        Estimated lag-1 autocorrelation (e.g. :func:`lag1_autocorrelation_from_sums`).
    rho_max : float
        Upper clip, in ``[0, 1)`` (default :data:`RHO_MAX`).

    Returns
    -------
    rho : float
        The clipped autocorrelation.
    factor : float
        What a covariance computed as if the frames were independent must be multiplied by.

    Notes
    -----
    The variance of a mean of N samples of an AR(1) process with lag-1
    correlation ``rho`` is ``(1 + rho) / (1 - rho)`` times that of N
    independent ones (N much longer than the correlation time); the same
    holds for a least-squares estimate whose regressors vary slowly over a
    correlation time, and over-states it when they vary faster (seeded
    two-segment rigs at 100 Hz, AR(1) marker noise: mean e/rank 0.8-1.0 at
    ``rho = 0.95``, 0.55-0.8 at 0.98). A negative estimate is clipped at 0 so
    that white residuals never shrink the covariance; on white residuals
    this inflates by about ``2 * 0.4 sd(rho_raw)``, ~3 % at N = 300 frames.
    """
    if not 0.0 <= rho_max < 1.0:
        raise InputError(f"rho_max: expected a number in [0, 1), got {rho_max!r}")
    rho = min(max(float(rho_raw), 0.0), float(rho_max)) if math.isfinite(rho_raw) else 0.0
    return rho, (1.0 + rho) / (1.0 - rho)


def hinge_residual_pair(
    sums: PoseSums,
    direction_parent: ArrayLike,
    direction_child: ArrayLike,
    point_parent: ArrayLike,
    point_child: ArrayLike,
) -> tuple[FloatArray, FloatArray]:
    """The axis-point pair ``(c_p, c_c)`` at which the hinge closed form's residual is evaluated.

    :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums` solves the
    ball-joint normal equations without the gauge direction ``(n_p, n_c)``
    (sliding both points along the axis) and reports each point moved to
    the axis point nearest its local origin. This recovers the solved pair:
    it lies on the line ``(p_p, p_c) + beta (n_p, -n_c)`` (the solution is
    orthogonal to ``(n_p, n_c)``, and so is this line), and minimises the
    residual sum of squares there, so ``beta = d^T (g - H p) / d^T H d`` with
    ``d = (n_p, -n_c)`` and ``H``, ``g`` the normal equations' matrix and
    right-hand side from the sums.

    Parameters
    ----------
    sums : PoseSums
    direction_parent, direction_child : array_like, shape (3,)
        Unit axis directions (parent, child local frames).
    point_parent, point_child : array_like, shape (3,)
        The reported axis points (input units).

    Returns
    -------
    centre_parent, centre_child : ndarray, shape (3,)
    """
    n_p = np.asarray(direction_parent, dtype=np.float64)
    n_c = np.asarray(direction_child, dtype=np.float64)
    p_p = np.asarray(point_parent, dtype=np.float64)
    p_c = np.asarray(point_child, dtype=np.float64)
    n = float(sums.n)
    S = np.asarray(sums.S)
    # H = [[n I, -S], [-S^T, n I]], g = (sum t, -sum Q^T t), d = (n_p, -n_c), p = (p_p, p_c).
    d_H_d = n * float(n_p @ n_p + n_c @ n_c) + 2.0 * float(n_p @ S @ n_c)
    r_p = np.asarray(sums.sum_t) - (n * p_p - S @ p_c)  # (g - H p), parent block
    r_c = -np.asarray(sums.sum_qt_t) - (n * p_c - S.T @ p_p)
    beta = float(n_p @ r_p - n_c @ r_c) / d_H_d if d_H_d > 0.0 else 0.0
    return p_p + beta * n_p, p_c - beta * n_c


def rotation_residual_sums(
    sums: PoseSums, lag: LagSums, direction_parent: ArrayLike, direction_child: ArrayLike
) -> tuple[float, float]:
    """``sum_k |Q_k n_c - n_p|^2`` over the frames and ``sum_k s_k . s_{k-1}`` over the lag pairs, ``s_k = Q_k n_c - n_p``.

    The hinge's axis-alignment residual (dimensionless): how far each frame's
    relative rotation is from a turn about the axis ``(n_p, n_c)``. From the
    sums: ``n (|n_c|^2 + |n_p|^2) - 2 n_p^T S n_c`` and ``n_c^T (sum Q_k^T Q_{k-1})
    n_c - n_p^T (sum (Q_k + Q_{k-1})) n_c + m |n_p|^2`` (the rotation blocks of
    :class:`LagSums`). The first is clipped at 0 against rounding.

    Parameters
    ----------
    sums : PoseSums
    lag : LagSums
    direction_parent, direction_child : array_like, shape (3,)
        Unit axis directions in the parent and the child frame.

    Returns
    -------
    ss, lag_sum : float
    """
    n_p = np.asarray(direction_parent, dtype=np.float64)
    n_c = np.asarray(direction_child, dtype=np.float64)
    ss = float(sums.n) * float(n_c @ n_c + n_p @ n_p) - 2.0 * float(n_p @ np.asarray(sums.S) @ n_c)
    lag_sum = (
        float(n_c @ lag.cross[:3, :3] @ n_c)
        - float(n_p @ lag.sum_pair[:, :3] @ n_c)
        + lag.n_pairs * float(n_p @ n_p)
    )
    return max(ss, 0.0), lag_sum


# --------------------------------------------------------------------------- lags in seconds

#: Lags (s) at which the online estimator keeps lag-pair sums besides the frame-to-frame pairs: the
#: constraint residual's correlation is read at these times whatever the frame rate.
SERIAL_LAGS_S = (0.04, 0.08, 0.16, 0.32, 0.64, 1.28, 2.56)
#: Bartlett window (s) of the integrated autocorrelation (:func:`integrated_factor`).
SERIAL_WINDOW_S = 3.0
#: Frames without stamps are taken to come at this rate (Hz) for the time lags.
NOMINAL_RATE_HZ = 100.0
#: A pair is taken when the frame nearest the lag is at most this share of the lag away from it.
LAG_TOLERANCE = 0.5
#: Detection of a smooth part: lags up to this (s) are pooled (:func:`smooth_energy_from_lags`).
SMOOTH_LAGS_MAX_S = 0.32
#: Detection of a smooth part: the pooled lag sums must exceed this many sd of white noise's (2.3 %
#: of white residuals pass). For markers declared on skin a missed artefact makes the estimate
#: confidently wrong (a knee at 12.5 Hz with 5 mm of artefact, bench/sta_online.py: 23 % of the
#: trials with e/2 > 3 at 3 sd, 17 % at 2 sd, 7 % at 1 sd); a false one adds a term of the noise's
#: size, which in a window with little movement is large (at 1 sd, a rigid hinge declared skin got
#: a direction sd of 12 deg in its first moments of movement: test_honesty.py).
SMOOTH_THRESHOLD_SD = 2.0
#: Per lag: n_pairs, sum (Z_k + Z_j) (12), sum Z_k^T Z_j (16) (the :class:`LagSums` layout), sum of lags (s).
_NODE = 30
#: Layout of the time-lag sums: consecutive frames' gaps (count, sum in s), then one node per lag.
N_TIME_LAG_SUMS = 2 + len(SERIAL_LAGS_S) * _NODE

__all__ += [
    "SERIAL_LAGS_S",
    "SERIAL_WINDOW_S",
    "SMOOTH_THRESHOLD_SD",
    "NOMINAL_RATE_HZ",
    "N_TIME_LAG_SUMS",
    "TimeLagSums",
    "LagHistory",
    "time_lag_sums_from_relative",
    "lag_nodes",
    "integrated_factor",
    "smooth_energy_from_lags",
]


@dataclass(frozen=True, eq=False)
class TimeLagSums:
    """Lag-pair sums at lags in seconds (:data:`SERIAL_LAGS_S`) and the frames' spacing.

    Attributes
    ----------
    n_gaps : float
        Consecutive frame pairs whose gap is summed (their weight under forgetting).
    sum_gaps : float
        Sum of those gaps (s).
    nodes : tuple of LagSums
        One per lag of :data:`SERIAL_LAGS_S`: the pairs ``(j, k)`` with ``t_k - t_j`` nearest that lag.
    sum_lags : ndarray, shape (len(SERIAL_LAGS_S),)
        Per lag, the sum of the pairs' actual time differences (s).
    """

    n_gaps: float
    sum_gaps: float
    nodes: tuple[LagSums, ...]
    sum_lags: FloatArray

    @classmethod
    def from_vector(cls, v: ArrayLike) -> TimeLagSums:
        """From the flat layout (:data:`N_TIME_LAG_SUMS`,): ``n_gaps, sum_gaps``, then per lag ``LagSums`` (29), sum of lags."""
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (N_TIME_LAG_SUMS,):
            raise InputError(f"time-lag sums: expected a vector of {N_TIME_LAG_SUMS} numbers, got shape {a.shape}")
        blocks = a[2:].reshape(len(SERIAL_LAGS_S), _NODE)
        return cls(float(a[0]), float(a[1]), tuple(LagSums.from_vector(b[:29]) for b in blocks), blocks[:, 29].copy())

    @property
    def frame_interval(self) -> float:
        """Mean gap between consecutive frames (s); NaN without gaps."""
        return self.sum_gaps / self.n_gaps if self.n_gaps > 0.0 else float("nan")


class LagHistory:
    """The recent frames' times and relative poses, to pair each new frame with those a lag earlier.

    O(1) per frame and lag (a binary search in a buffer trimmed to the longest lag): the per-frame
    contribution :meth:`contributions` goes into the estimator's sums with the frame, and leaves the
    window with it. Times must increase; a time that does not restarts the history.
    """

    def __init__(self, lags_s: tuple[float, ...] = SERIAL_LAGS_S) -> None:
        self.lags = np.asarray(lags_s, dtype=np.float64)
        self.horizon = (1.0 + LAG_TOLERANCE) * float(self.lags.max())
        self._t = np.empty(256)
        self._z = np.empty((256, 12))
        self._n = 0

    def clear(self) -> None:
        """Forget the frames (a break: no pair reaches across it)."""
        self._n = 0

    def _append(self, t: FloatArray, z: FloatArray) -> int:
        """Append (trimming what no new frame can pair with); the index of the first new frame."""
        m = t.size
        if self._n and not t[0] > self._t[self._n - 1]:
            self.clear()
        first = int(np.searchsorted(self._t[: self._n], t[0] - self.horizon)) if self._n else 0
        keep = self._n - first
        if keep + m > self._t.size:
            size = max(2 * self._t.size, 2 * (keep + m))
            t_new, z_new = np.empty(size), np.empty((size, 12))
            t_new[:keep], z_new[:keep] = self._t[first : self._n], self._z[first : self._n]
            self._t, self._z = t_new, z_new
        elif self._n + m > self._t.size:
            self._t[:keep] = self._t[first : self._n].copy()
            self._z[:keep] = self._z[first : self._n].copy()
        else:  # room after the frames kept as they are (older ones included: they pair with nothing new)
            keep = self._n
        self._t[keep : keep + m] = t
        self._z[keep : keep + m] = z
        self._n = keep + m
        return keep

    def contributions(self, times: FloatArray, z: FloatArray, out: FloatArray) -> None:
        """Add frames and write their contributions (M, :data:`N_TIME_LAG_SUMS`) to ``out``.

        Parameters
        ----------
        times : ndarray, shape (M,)
            Increasing times (s) of frames that enter the statistics.
        z : ndarray, shape (M, 3, 4)
            Their relative poses ``[Q | t]``.
        out : ndarray, shape (M, N_TIME_LAG_SUMS)
            Overwritten: each frame's gap to the frame before it and its pairs with the frames
            :data:`SERIAL_LAGS_S` earlier (zero where no frame is within :data:`LAG_TOLERANCE`).
        """
        m = times.size
        if m == 0:
            return
        back = np.flatnonzero(np.diff(times) <= 0.0)
        if back.size:  # a time that does not increase restarts the history there (as frame by frame)
            cut = int(back[0]) + 1
            self.contributions(times[:cut], z[:cut], out[:cut])
            self.clear()
            self.contributions(times[cut:], z[cut:], out[cut:])
            return
        h = self._append(times, z.reshape(m, 12))
        T, Z = self._t[: self._n], self._z[: self._n]
        own = h + np.arange(m)
        out[:, 0] = own > 0
        out[:, 1] = np.where(own > 0, times - T[np.maximum(own - 1, 0)], 0.0)
        target = times[:, None] - self.lags[None, :]  # (M, J)
        hi = np.minimum(np.searchsorted(T, target), own[:, None])  # first at or after the target, never the frame
        lo = np.maximum(hi - 1, 0)
        use_lo = (hi >= own[:, None]) | (np.abs(T[lo] - target) <= np.abs(T[hi] - target))
        k = np.where(use_lo, lo, hi)
        gap = times[:, None] - T[k]
        ok = (k < own[:, None]) & (np.abs(gap - self.lags[None, :]) <= LAG_TOLERANCE * self.lags[None, :])
        cur = z.reshape(m, 1, 3, 4)
        prev = Z[k].reshape(m, -1, 3, 4)
        blocks = out[:, 2:].reshape(m, self.lags.size, _NODE)
        blocks[:, :, 0] = ok
        blocks[:, :, 1:13] = ((cur + prev) * ok[:, :, None, None]).reshape(m, -1, 12)
        blocks[:, :, 13:29] = (np.swapaxes(cur, 2, 3) @ prev * ok[:, :, None, None]).reshape(m, -1, 16)
        blocks[:, :, 29] = np.where(ok, gap, 0.0)


def time_lag_sums_from_relative(Q_parent_child: ArrayLike, t_parent_child: ArrayLike, times: ArrayLike) -> TimeLagSums:
    """:class:`TimeLagSums` of a sequence of relative poses (the batch formula; NaN rows are left out)."""
    Q = np.asarray(Q_parent_child, dtype=np.float64)
    t = np.asarray(t_parent_child, dtype=np.float64)
    s = np.asarray(times, dtype=np.float64)
    if Q.ndim != 3 or Q.shape[1:] != (3, 3) or t.shape != (Q.shape[0], 3) or s.shape != (Q.shape[0],):
        raise InputError(
            f"time-lag sums: expected Q (N, 3, 3), t (N, 3) and times (N,), got {Q.shape}, {t.shape} and {s.shape}"
        )
    ok = np.isfinite(Q).all(axis=(1, 2)) & np.isfinite(t).all(axis=1) & np.isfinite(s)
    out = np.zeros((int(ok.sum()), N_TIME_LAG_SUMS))
    LagHistory().contributions(s[ok], _z(Q[ok], t[ok]), out)
    return TimeLagSums.from_vector(out.sum(axis=0))


def lag_nodes(lag1: LagSums, tl: TimeLagSums, min_pairs: float = 10.0) -> list[tuple[float, LagSums]]:
    """The lags at which a window's residual correlation can be read: ``(mean lag (s), its pair sums)``, increasing.

    The consecutive frames' pairs (at the mean frame interval) first, then each time lag with at least
    ``min_pairs`` pairs whose mean lag is not within a quarter of a frame interval of one already listed
    (at 12.5 Hz the 0.08 s lag is the frame interval: the same pairs, counted once).
    """
    dt = tl.frame_interval
    nodes: list[tuple[float, LagSums]] = []
    if lag1.n_pairs >= min_pairs and math.isfinite(dt):
        nodes.append((dt, lag1))
    for node, total in zip(tl.nodes, tl.sum_lags, strict=True):
        if node.n_pairs >= min_pairs:
            lag = float(total / node.n_pairs)
            if not any(abs(lag - x) < 0.25 * dt for x, _ in nodes):
                nodes.append((lag, node))
    nodes.sort(key=lambda item: item[0])
    return nodes


def integrated_factor(
    lags: ArrayLike,
    rhos: ArrayLike,
    frame_interval: float,
    n_frames: float,
    n_pairs: ArrayLike | None = None,
    window_s: float = SERIAL_WINDOW_S,
) -> float:
    """Variance factor of a mean of correlated frames: ``1 + 2 sum_l (1 - l dt / T) rho(l dt)`` (Bartlett).

    Parameters
    ----------
    lags : array_like, shape (K,)
        Increasing lags (s) at which the autocorrelation was measured.
    rhos : array_like, shape (K,)
        The autocorrelation there (NaN entries are left out; each clipped to [-1, 1]).
    frame_interval : float
        ``dt``, the mean gap between frames (s).
    n_frames : float
        Frames in the window: the factor is at most that (one frame's worth of information).
    n_pairs : array_like, shape (K,), optional
        Pairs behind each ``rho``: the sum stops at the first lag whose ``rho`` is within 2 sd of
        white noise (``2 / sqrt(n_pairs)``), as Sokal's window stops where the correlation is
        noise; without it, every lag up to ``T`` counts.
    window_s : float
        ``T``: lags up to it are summed (default :data:`SERIAL_WINDOW_S`).

    Returns
    -------
    float
        At least 1; 1 without lags.

    Notes
    -----
    Between the measured lags ``rho`` is interpolated linearly, and from the last one counted down
    to 0 at the next (or at ``T``). The sum over frames ``l dt`` is, up to ``O(dt)``, ``2 / dt``
    times the integral of ``(1 - tau / T) rho(tau)``: the seconds of data per independent sample do
    not depend on the frame rate (an AR(1) factor from the lag-1 correlation alone does:
    ``bench/serial_lags.py``). The stop keeps white residuals at a factor of about 1 (summing
    every lag's noise would inflate them by ~30 % at 100 Hz).
    """
    x = np.asarray(lags, dtype=np.float64)
    y = np.asarray(rhos, dtype=np.float64)
    good = np.isfinite(x) & np.isfinite(y) & (x > 0.0) & (x < window_s)
    if not (good.any() and math.isfinite(frame_interval) and frame_interval > 0.0):
        return 1.0
    end = window_s
    if n_pairs is not None:
        c = np.asarray(n_pairs, dtype=np.float64)[good]
        noise = ~(y[good] > 2.0 / np.sqrt(np.maximum(c, 1.0)))
        if noise.any():
            stop = int(np.argmax(noise))
            if stop == 0:
                return 1.0
            end = float(x[good][stop])
            good[np.flatnonzero(good)[stop:]] = False
    x = np.concatenate([x[good], [end]])
    y = np.concatenate([np.clip(y[good], -1.0, 1.0), [0.0]])
    steps = np.arange(1, max(int(window_s / frame_interval), 1) + 1) * frame_interval
    steps = steps[(steps >= x[0] * (1.0 - 1e-9)) & (steps < end)]
    rho = np.interp(steps, x, y)
    factor = 1.0 + 2.0 * float(np.sum((1.0 - steps / window_s) * rho))
    return min(max(factor, 1.0), max(float(n_frames), 1.0))


def smooth_energy_from_lags(
    lag_sums: ArrayLike, n_pairs: ArrayLike, lags: ArrayLike, ss: float, n: float, lag_max: float = SMOOTH_LAGS_MAX_S
) -> float:
    """The smooth part of a residual's energy over ``n`` frames, from its lag sums; its detection limit when it is not told from noise.

    Parameters
    ----------
    lag_sums, n_pairs, lags : array_like, shape (K,)
        Per lag (increasing, s): the sum of ``r_k . r_j`` over its pairs, their number.
    ss : float
        ``sum |r_k|^2`` over the ``n`` frames.
    n : float

    Returns
    -------
    float
        ``n`` times the autocovariance at the shortest lag (white noise has none), when the lag sums
        up to ``lag_max`` together exceed :data:`SMOOTH_THRESHOLD_SD` sd of theirs for white noise
        (at most ``ss / sqrt(n_pairs)`` each, the lags independent): a smooth part small against the
        noise, which a single lag at a low frame rate cannot tell from it, is told by several. When
        they do not, the largest smooth part they could not tell (the threshold's share per lag, or
        the shortest lag's autocovariance if larger) times ``n``: not seeing a smooth part does not
        show there is none, and read as 0 the skin prior's part vanished (a 5 mm knee at 25 Hz was
        published at e/2 of 26-127 for 12 s, ``test/test_sta_online.py``).
    """
    g = np.asarray(lag_sums, dtype=np.float64)
    c = np.asarray(n_pairs, dtype=np.float64)
    x = np.asarray(lags, dtype=np.float64)
    use = (c > 0.0) & (x <= lag_max)
    if not (use.any() and ss > 0.0 and n > 0.0):
        return 0.0
    stat = float(np.sum(g[use] / c[use]))
    sd = ss / n * math.sqrt(float(np.sum(1.0 / c[use])))
    if not stat > SMOOTH_THRESHOLD_SD * sd:
        return max(float(g[0] / c[0]), SMOOTH_THRESHOLD_SD * sd / float(np.count_nonzero(use)), 0.0) * n
    return max(float(g[0] / c[0]), 0.0) * n
