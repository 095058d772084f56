"""Soft-tissue artefact (STA) covariance of the online estimates, from running sums.

The batch fits (:mod:`jointfit_core.artefact`) propagate a prior on each
skin cluster's rigid motion on its bone through every frame. The online
estimator keeps only sums, so this module keeps the few extra sums that the
same propagation needs and does it on them:

- per frame, the features ``f_t`` of the joint angles (rotation vector of the
  relative rotation ``Q_t``, its squares and cross products: the linear plus
  quadratic artefact model of Camomilla et al. 2013 and Bonci et al. 2014)
  and their products with the relative pose: ``sum f``, ``sum Q (x) f``,
  ``sum t (x) f``, ``sum (Q^T t) (x) f`` and ``sum |f|^2``
  (:func:`feature_sums`, :data:`N_FEATURE_SUMS` numbers, exactly additive);
- per solve, the first-order change of the estimate when each cluster moves
  on its bone by ``g_t = G f_t`` (``G`` 12 x 9 with independent entries of
  variance ``s^2 v_j``, :func:`artefact_from_sums`). The features are centred
  over the window, so a constant offset (which only relabels the joint) is
  not part of the artefact. The propagated covariance does not shrink with
  the window: ``sum_t Q_t f_t`` grows like N, and so does the normal matrix.

The prior's overall scale ``s`` is read from the data: the smooth part of
the joint residual (its autocovariance at short lags, to which white marker
noise contributes nothing) is the visible part of the same cluster motion,
whose expected size per unit prior is known from the geometry and the
movement. A hinge has a second reading, from its axis-alignment residual
``Q_t n_c - n_p``, which sees the cluster turns that tilt the axis; the
larger of the two is used.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .pose import skew

__all__ = [
    "N_FEATURE_SUMS",
    "SumsArtefact",
    "artefact_from_sums",
    "ball_parameters",
    "feature_sums",
    "hinge_parameters",
    "rotation_features",
]

FloatArray = NDArray[np.float64]

#: Number of joint-angle features (rotation vector, squares, cross products).
N_FEATURES = 9
#: Layout of :func:`feature_sums`: f (9), Q_ij f_k (81), t_i f_k (27), (Q^T t)_i f_k (27), |f|^2 (1).
_F = slice(0, 9)
_QF = slice(9, 90)
_TF = slice(90, 117)
_PF = slice(117, 144)
_FF = 144
N_FEATURE_SUMS = 145
#: Relative step of the finite differences of the solvers.
_STEP = 1e-6


def rotation_features(Q: FloatArray) -> FloatArray:
    """Linear and quadratic joint-angle features of relative rotations, (N, 3, 3) -> (N, 9).

    ``q`` is the rotation vector of ``Q`` (rad, from the template frame's
    relative orientation); the features are ``q``, ``q**2`` and
    ``q0 q1, q0 q2, q1 q2``, not centred (the sums are centred per window).
    """
    tr = np.clip((np.trace(Q, axis1=1, axis2=2) - 1.0) * 0.5, -1.0, 1.0)
    theta = np.arccos(tr)
    w = 0.5 * np.stack([Q[:, 2, 1] - Q[:, 1, 2], Q[:, 0, 2] - Q[:, 2, 0], Q[:, 1, 0] - Q[:, 0, 1]], axis=1)
    sin = np.sin(theta)
    ratio = np.where(sin > 1e-9, theta / np.maximum(sin, 1e-9), 1.0)
    q = w * ratio[:, None]
    out: FloatArray = np.concatenate([q, q * q, q[:, [0]] * q[:, [1]], q[:, [0]] * q[:, [2]], q[:, [1]] * q[:, [2]]], 1)
    return out


def feature_sums(Q: FloatArray, t: FloatArray) -> FloatArray:
    """Per-frame contributions (N, :data:`N_FEATURE_SUMS`) of relative poses ``Q`` (N, 3, 3), ``t`` (N, 3)."""
    f = rotation_features(Q)
    n = f.shape[0]
    out = np.empty((n, N_FEATURE_SUMS))
    out[:, _F] = f
    out[:, _QF] = (Q.reshape(n, 9, 1) * f[:, None, :]).reshape(n, 81)
    out[:, _TF] = (t[:, :, None] * f[:, None, :]).reshape(n, 27)
    qt = np.einsum("nji,nj->ni", Q, t)
    out[:, _PF] = (qt[:, :, None] * f[:, None, :]).reshape(n, 27)
    out[:, _FF] = np.einsum("nk,nk->n", f, f)
    return out


def feature_sums_one(z: FloatArray) -> FloatArray:
    """:func:`feature_sums` of one relative pose ``z = [Q | t]`` (3, 4): its contribution (:data:`N_FEATURE_SUMS`,).

    The per-frame path's form (scalar rotation vector, no batch overhead); equal to the
    batched one to rounding (tested).
    """
    (q00, q01, q02, _), (q10, q11, q12, _), (q20, q21, q22, _) = z.tolist()
    theta = math.acos(min(max((q00 + q11 + q22 - 1.0) * 0.5, -1.0), 1.0))
    sin = math.sin(theta)
    ratio = theta / sin if sin > 1e-9 else 1.0
    a, b, c = 0.5 * (q21 - q12) * ratio, 0.5 * (q02 - q20) * ratio, 0.5 * (q10 - q01) * ratio
    f = np.array([a, b, c, a * a, b * b, c * c, a * b, a * c, b * c])
    out = np.empty(N_FEATURE_SUMS)
    out[_F] = f
    Q, t = z[:, :3], z[:, 3]
    out[_QF] = np.multiply.outer(Q.ravel(), f).ravel()
    out[_TF] = np.multiply.outer(t, f).ravel()
    out[_PF] = np.multiply.outer(t @ Q, f).ravel()
    out[_FF] = f @ f
    return out


def ball_parameters(n: float, S: FloatArray, sum_t: FloatArray, sum_qt: FloatArray) -> FloatArray:
    """``(c_p, c_c)`` (6,) of Stoddart's eq. 9 from the sums (no bias compensation)."""
    A = np.block([[n * np.eye(3), -S], [-S.T, n * np.eye(3)]])
    out: FloatArray = np.linalg.solve(A, np.concatenate([sum_t, -sum_qt]))
    return out


def hinge_parameters(
    n: float, S: FloatArray, sum_t: FloatArray, sum_qt: FloatArray, reference: FloatArray
) -> FloatArray:
    """``(n_p, n_c, point_p, point_c)`` (12,) of the hinge closed form from the sums.

    As :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums`: the top
    singular pair of ``S`` (signed so that ``n_p . reference >= 0``) and the
    pseudo-inverse solution of eq. 9 without the gauge direction, each point
    moved to the axis point nearest its local origin.
    """
    U, s, Vt = np.linalg.svd(S)
    V = Vt.T
    flip = 1.0 if U[:, 0] @ reference >= 0.0 else -1.0
    E, lam = [], []
    for k in range(3):
        for sign, value in ((1.0, n - s[k]), (-1.0, n + s[k])):
            if k == 0 and sign > 0:
                continue
            E.append(np.concatenate([U[:, k], sign * V[:, k]]) / np.sqrt(2.0))
            lam.append(value)
    Em = np.stack(E, axis=1)
    a = (Em / np.asarray(lam)) @ (Em.T @ np.concatenate([sum_t, -sum_qt]))
    n_p, n_c = flip * U[:, 0], flip * V[:, 0]
    out: FloatArray = np.concatenate([n_p, n_c, a[:3] - n_p * (n_p @ a[:3]), a[3:] - n_c * (n_c @ a[3:])])
    return out


@dataclass(frozen=True)
class SumsArtefact:
    """The soft-tissue part of an online estimate's covariance.

    Attributes
    ----------
    cov : ndarray, shape (m, m)
        Over the solver's parameter vector (ball: ``c_p, c_c``, input units
        squared; hinge: ``n_p, n_c, point_p, point_c``).
    scale : float
        Estimated rms cluster shift on the bone per radian of joint rotation
        (input units per rad; 0 when the residual shows no smooth part).
    """

    cov: FloatArray
    scale: float


def _centred(fs: FloatArray, n: float, S: FloatArray, sum_t: FloatArray, sum_qt: FloatArray) -> tuple[FloatArray, ...]:
    """Window-centred ``sum Q f_k`` (9, 3, 3), ``sum t f_k``, ``sum Q^T t f_k`` (9, 3) and ``sum |f - fbar|^2``."""
    fbar = fs[_F] / n
    SQ = fs[_QF].reshape(3, 3, 9).transpose(2, 0, 1) - fbar[:, None, None] * S[None]
    ST = fs[_TF].reshape(3, 9).T - fbar[:, None] * sum_t[None]
    SP = fs[_PF].reshape(3, 9).T - fbar[:, None] * sum_qt[None]
    ff = max(float(fs[_FF]) - n * float(fbar @ fbar), 0.0)
    return SQ, ST, SP, np.array(ff)


def _prior_variances(radius: float) -> FloatArray:
    """Per unit scale, the prior variances of one cluster's ``(omega, u)`` (6,): ``1 / r^2`` and 1."""
    return np.concatenate([np.full(3, 1.0 / max(radius**2, 1e-300)), np.ones(3)])


def _sum_perturbations(SQ: FloatArray, ST: FloatArray, SP: FloatArray) -> FloatArray:
    """Change of ``(S, sum t, sum Q^T t)`` (15,) per unit entry of ``G``: (15, 12, 9).

    A cluster motion ``(omega_p, u_p, omega_c, u_c)`` about the local origins
    changes the relative pose by ``dQ = -[omega_p]x Q + Q [omega_c]x``,
    ``dt = Q u_c - u_p - [omega_p]x t`` and ``d(Q^T t) = -[omega_c]x Q^T t +
    u_c - Q^T u_p`` (first order); with ``g_t = G f_t`` and centred features
    the window's sums change by the centred products below.
    """
    out = np.zeros((15, 12, 9))
    basis = np.eye(3)
    for j in range(3):
        e = skew(basis[j])
        # omega_p (columns 0-2)
        out[:9, j] = (-(e[None] @ SQ)).reshape(9, 9).T
        out[9:12, j] = -(ST @ e.T).T
        # u_p (3-5): dS 0, dsum_t 0 (centred), dsum_qt = -S_k^T e_j
        out[12:15, 3 + j] = -SQ[:, j, :].T
        # omega_c (6-8)
        out[:9, 6 + j] = (SQ @ e[None]).reshape(9, 9).T
        out[12:15, 6 + j] = -(SP @ e.T).T
        # u_c (9-11): dsum_t = S_k e_j
        out[9:12, 9 + j] = SQ[:, :, j].T
    return out


def _jacobian(solver: Callable[[FloatArray], FloatArray], x0: FloatArray, scales: FloatArray) -> FloatArray:
    """Central finite-difference Jacobian (m, 15) of ``solver`` at ``x0`` with per-entry steps."""
    cols = []
    for i in range(x0.size):
        h = _STEP * scales[i]
        xp, xm = x0.copy(), x0.copy()
        xp[i] += h
        xm[i] -= h
        cols.append((solver(xp) - solver(xm)) / (2.0 * h))
    return np.stack(cols, axis=1)


def artefact_from_sums(
    fs: FloatArray,
    n: float,
    S: FloatArray,
    sum_t: FloatArray,
    sum_qt: FloatArray,
    solver: Callable[[FloatArray], FloatArray],
    centres: tuple[FloatArray, FloatArray],
    radii: tuple[float, float],
    weights: tuple[float, float],
    smooth_energy: float,
    directions: tuple[FloatArray, FloatArray] | None = None,
    rotation_smooth: float = 0.0,
) -> SumsArtefact:
    """Soft-tissue covariance of a sums-based estimate (first order in the cluster motion).

    Parameters
    ----------
    fs : ndarray, shape (N_FEATURE_SUMS,)
        The window's :func:`feature_sums`.
    n : float
        Frames (or weight) in the window.
    S, sum_t, sum_qt : ndarray, shapes (3, 3), (3,), (3,)
        ``sum Q``, ``sum t``, ``sum Q^T t`` of the window.
    solver : callable
        ``solver(x) -> params (m,)`` with ``x = (S.ravel(), sum_t, sum_qt)``
        (15,): the estimate as a function of those sums.
    centres : (ndarray (3,), ndarray (3,))
        The joint's residual pair ``(c_p, c_c)`` in the local frames (input units).
    radii : (float, float)
        Rms radii of the two templates (input units): a cluster turn and a
        shift of the prior's size move the markers alike (``v = 1 / r^2`` for
        rotations, 1 for translations, as in :mod:`jointfit_core.artefact`).
    weights : (float, float)
        Relative artefact size of the parent and the child (0: rigid).
    smooth_energy : float
        The smooth part of the joint residual's energy at ``centres``
        (input units squared, summed over the frames): what white marker
        noise does not explain.
    directions : (ndarray (3,), ndarray (3,)), optional
        Hinge: the axis directions ``(n_p, n_c)``, which are also the first
        six parameters ``solver`` returns. The axis-alignment residual
        ``Q_t n_c - n_p`` then gives a second reading of the scale.
    rotation_smooth : float
        Hinge: the smooth part of ``sum_t |Q_t n_c - n_p|^2`` (dimensionless).

    Returns
    -------
    SumsArtefact

    Notes
    -----
    ``d params = J_x dx``, ``dx = sum_jk Delta_jk G_jk`` (:func:`_sum_perturbations`),
    so ``cov = s^2 J_x (sum_jk v_j Delta_jk Delta_jk^T) J_x^T``.
    Per unit ``s^2`` the residual ``r_t = c_p - Q_t c_c - t_t`` gains ``D_t g_t``
    (the Jacobian of the batch fits) minus what the refit absorbs, so its
    expected sum of squares is ``sum_j v_j |D e_j|^2 sum_t |f_t - fbar|^2 -
    sum_jk v_j da_jk^T A da_jk`` (``A`` the normal matrix of eq. 9, ``da``
    the change of the centre pair); ``s^2`` is the residual's smooth energy
    over it.
    Hinge: a cluster's turn about a line through the axis point (the shank's
    long axis) tilts the estimated axis but hardly moves the point, so the
    point residual may show almost nothing of the motion that biases the
    direction most; the alignment residual ``Q_t n_c - n_p`` shows every
    turn off the axis (``|omega x n|^2``, ``2 / r^2`` per unit scale, minus what
    the direction's refit absorbs, ``dn^T A dn``). The scale is the larger of
    the two readings (without it, a knee whose shank cluster turned about
    the shank read no artefact and was confidently wrong: ``bench/sta_online.py``).
    """
    m = solver(np.concatenate([S.ravel(), sum_t, sum_qt])).size
    w = np.asarray(weights, dtype=np.float64)
    smooth_energy = float(smooth_energy) if np.isfinite(smooth_energy) else 0.0
    rotation_smooth = float(rotation_smooth) if directions is not None and np.isfinite(rotation_smooth) else 0.0
    if n < 3 or not float(w.max()) > 0.0 or not max(smooth_energy, rotation_smooth) > 0.0:
        return SumsArtefact(np.zeros((m, m)), 0.0)
    SQ, ST, SP, ff_arr = _centred(fs, n, S, sum_t, sum_qt)
    ff = float(ff_arr)
    delta = _sum_perturbations(SQ, ST, SP).reshape(15, 108)
    x0 = np.concatenate([S.ravel(), sum_t, sum_qt])
    length = max(float(np.linalg.norm(sum_t)) / n, float(np.linalg.norm(sum_qt)) / n, max(radii), 1e-300)
    steps = np.concatenate([np.full(9, n), np.full(6, n * length)])
    dparams = _jacobian(solver, x0, steps) @ delta  # (m, 108)
    # visible residual energy per unit s^2 (ball normal matrix, centre pair from eq. 9)
    da = _jacobian(lambda x: ball_parameters(n, x[:9].reshape(3, 3), x[9:12], x[12:]), x0, steps) @ delta
    A = np.block([[n * np.eye(3), -S], [-S.T, n * np.eye(3)]])
    absorbed_jk = np.einsum("ik,ij,jk->k", da, A, da)  # (108,)
    # hinge: what the directions' refit absorbs of the alignment residual (its normal matrix is A too)
    absorbed_rot = np.einsum("ik,ij,jk->k", dparams[:6], A, dparams[:6]) if directions is not None else absorbed_jk
    var = np.concatenate([_prior_variances(radii[0]) * w[0], _prior_variances(radii[1]) * w[1]])
    vjk = np.repeat(var, 9)
    c_p, c_c = (np.asarray(c, dtype=np.float64) for c in centres)
    direct = w[0] * (2.0 * float(c_p @ c_p) / max(radii[0] ** 2, 1e-300) + 3.0)
    direct += w[1] * (2.0 * float(c_c @ c_c) / max(radii[1] ** 2, 1e-300) + 3.0)
    visible = direct * ff - float(absorbed_jk @ vjk)
    scale2 = smooth_energy / visible if visible > 0.0 else 0.0
    if directions is not None:
        # only the turns (omega) reach the alignment residual: |omega x n|^2 has 2 / r^2 per unit scale
        rot = np.concatenate([var[:3], np.zeros(3), var[6:9], np.zeros(3)])
        visible_rot = 2.0 * float(rot[0] + rot[6]) * ff - float(absorbed_rot @ np.repeat(rot, 9))
        if visible_rot > 0.0:
            scale2 = max(scale2, rotation_smooth / visible_rot)
    cov = scale2 * ((dparams * vjk) @ dparams.T)
    return SumsArtefact(0.5 * (cov + cov.T), math.sqrt(scale2 * float(w.max())))
