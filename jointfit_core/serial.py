"""Frame-to-frame (lag-1) correlation of the joint-constraint residual, from running sums.

A closed-form joint estimate averages a per-frame constraint residual over N
frames. Its covariance, propagated as if the frames were independent, is
far too small when the residual is smooth in time (soft-tissue artefact at
100 Hz: lag-1 autocorrelation 0.95-0.998), because then N frames carry the
information of about ``N (1 - rho) / (1 + rho)`` independent ones. This
module measures that autocorrelation ``rho`` of the residual of the two-segment
constraint from sums that an online estimator keeps in O(1) per frame, and
gives the matching batch formulas (for tests and offline use).

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
    """The lag-1 correlation correction applied to an estimate's covariances.

    Attributes
    ----------
    rho : float
        ``rho_raw`` clipped to ``[0, RHO_MAX]``, from which ``factor`` is
        computed when the correction is on.
    rho_raw : float
        Lag-1 autocorrelation of the constraint residual over the window (NaN
        when there is no lag pair or no residual).
    factor : float
        ``(1 + rho) / (1 - rho)``: what the covariances were multiplied by
        (1 when the correction is switched off).
    n_pairs : float
        Lag pairs in the window (their weight under forgetting).
    """

    rho: float
    rho_raw: float
    factor: float
    n_pairs: float


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
