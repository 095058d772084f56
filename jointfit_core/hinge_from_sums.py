"""Hinge axis between two moving segments from running sums of relative poses.

The online counterpart of :func:`jointfit_core.segments.fit_axis_two_segments`
(closed form, no refinement over frames): everything it needs is in
:class:`~jointfit_core.segments.PoseSums`, so an online estimator solves it in
O(1) whatever the window length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import check_vector3
from .errors import InputError, NotIdentifiableError
from .pose import skew
from .segments import (
    SINGULAR_REL,
    PoseSums,
    _axis_verdict,
    _check_cov6,
    _FrozenArrays,
    _motion,
    _sums_meat,
    _sums_rms,
    debiased_sums,
    first_order_bias_step,
    gauge_free_pinv,
    noise_bias_matrices,
    svd3,
)

__all__ = ["PoseSumsAxis", "axis_from_pose_sums"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class PoseSumsAxis(_FrozenArrays):
    """Hinge axis from running sums (closed form, first-order covariances).

    Attributes
    ----------
    direction_parent, direction_child : ndarray, shape (3,)
        Unit axis direction in the parent and the child local frame.
    point_parent, point_child : ndarray, shape (3,)
        The point of the axis nearest each local origin (input units).
    cov_direction_parent, cov_direction_child : ndarray, shape (3, 3)
        Covariances of the directions (rank 2, orthogonal to them).
    cov_point_parent, cov_point_child : ndarray, shape (3, 3)
        Covariances of the points (input units squared).
    rms : float
        Rms of ``|c_p - Q_t c_c - t_t|`` at the fitted axis-point pair.
    n_frames : int
    identifiable : bool
    reason : str
    """

    direction_parent: FloatArray
    direction_child: FloatArray
    point_parent: FloatArray
    point_child: FloatArray
    cov_direction_parent: FloatArray
    cov_direction_child: FloatArray
    cov_point_parent: FloatArray
    cov_point_child: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str


def _kq(K: FloatArray, M: FloatArray) -> FloatArray:
    """``sum_t Q_t M Q_t^T`` from ``K = sum kron(Q_t, Q_t)``."""
    out: FloatArray = (K @ M.ravel()).reshape(3, 3)
    return out


def _direction_covariance(
    U: FloatArray, s: FloatArray, V: FloatArray, n: float, K: FloatArray, rot_p: FloatArray, rot_c: FloatArray
) -> FloatArray:
    """Joint covariance (6, 6) of the top singular pair ``(u_0, v_0)`` of ``S = sum Q_t``.

    First-order perturbation of the singular vectors under ``dQ_t = -[w_p]x Q_t + Q_t [w_c]x``
    (local rotation errors of the two poses, independent, covariances ``rot_p`` and ``rot_c``):
    ``du_0 = sum_k u_k (s_0 a_k + s_k b_k) / (s_0^2 - s_k^2)``,
    ``dv_0 = sum_k v_k (s_k a_k + s_0 b_k) / (s_0^2 - s_k^2)`` with ``a_k = u_k^T dS v_0`` and
    ``b_k = u_0^T dS v_k`` (k = 1, 2). Per frame, ``a_k = w_p . (u_k x Q v_0) - u_k^T Q [v_0]x w_c`` and
    ``b_k = w_p . (u_0 x Q v_k) - u_0^T Q [v_k]x w_c``, so the covariance of the four sums needs only
    ``sum Q^T M Q`` and ``sum Q M Q^T`` for fixed ``M``, i.e. ``K``.
    """
    u = [U[:, k] for k in range(3)]
    v = [V[:, k] for k in range(3)]
    # Entries of (a_1, a_2, b_1, b_2): parent part w_p . ([l]x Q r) and child part -(m^T Q [r]x w_c);
    # all 16 pairs (i, j) at once: C_ij = r_i^T kqt([l_i]x^T rot_p [l_j]x) r_j + l_i^T kq([r_i]x rot_c [r_j]x^T) l_j.
    left = np.stack([u[1], u[2], u[0], u[0]])
    right = np.stack([v[0], v[0], v[1], v[2]])
    sl, sr = skew(left), skew(right)
    m_p = np.einsum("iba,bc,jcd->ijad", sl, rot_p, sl).reshape(16, 9)
    m_c = np.einsum("iab,bc,jdc->ijad", sr, rot_c, sr).reshape(16, 9)
    parent = np.einsum("ia,ijab,jb->ij", right, (m_p @ K).reshape(4, 4, 3, 3), right)  # kqt: K^T vec(M)
    child = np.einsum("ia,ijab,jb->ij", left, (m_c @ K.T).reshape(4, 4, 3, 3), left)  # kq: K vec(M)
    C = parent + child
    L = np.zeros((6, 4))
    for k in (1, 2):
        den = s[0] ** 2 - s[k] ** 2
        L[:3, k - 1] += s[0] * u[k] / den
        L[:3, k + 1] += s[k] * u[k] / den
        L[3:, k - 1] += s[k] * v[k] / den
        L[3:, k + 1] += s[0] * v[k] / den
    out: FloatArray = L @ C @ L.T
    return out


def axis_from_pose_sums(
    sums: PoseSums,
    W_parent_local: ArrayLike,
    W_child_local: ArrayLike,
    *,
    length_scale: float = 0.0,
    reference_direction: ArrayLike | None = None,
    compensate_bias: bool = True,
    W_bias: tuple[ArrayLike, ArrayLike] | None = None,
) -> PoseSumsAxis:
    """Hinge axis from running sums of relative poses (closed form).

    Parameters
    ----------
    sums : PoseSums
        Sums over the frames (:func:`jointfit_core.segments.pose_sums_from_relative`).
    W_parent_local, W_child_local : array_like, shape (6, 6)
        Mean local pose covariances of the two segments over the summed
        frames, as in :func:`jointfit_core.segments.centre_from_pose_sums`.
    length_scale : float
        Lower bound of the lever arm used in the identifiability check.
    reference_direction : array_like, shape (3,), optional
        ``direction_parent`` has a non-negative dot product with it; default
        the parent local axis along which the direction is largest.
    compensate_bias : bool
        Remove the second-order bias caused by the pose noise from the
        direction and the point pair (default True; see Notes).
    W_bias : (array_like, array_like), shapes (6, 6), optional
        The pose covariances (parent, child) of the bias compensation when
        they are not the covariance's (skin markers: those of the white
        marker noise), as in :func:`~jointfit_core.segments.centre_from_pose_sums`.

    Returns
    -------
    PoseSumsAxis

    Raises
    ------
    InputError
        Fewer than 3 frames, badly shaped covariances or reference.
    NotIdentifiableError
        No relative rotation (the axis is undefined).

    Notes
    -----
    The direction is the top singular pair of ``S = sum Q_t`` and the point
    pair the pseudo-inverse solution of the ball-joint normal equations in
    the complement of ``(n_p, n_c)``, as in the closed form that
    :func:`~jointfit_core.segments.fit_axis_two_segments` reports for skin
    markers (for rigid markers it then refines over the frames, a little
    more precise; this does not).
    Covariances, first order in the pose noise: the direction pair from the
    perturbation of the singular vectors (see :func:`_direction_covariance`);
    the point pair from the sandwich of
    :func:`~jointfit_core.segments.centre_from_pose_sums` with the
    pseudo-inverse; the reported points ``c - n (n . c)`` add the along-axis
    shift caused by the direction's uncertainty (treated as independent of
    the point pair's).

    **Bias compensation.** A small rotation noise ``w`` lowers ``Q`` on
    average: ``E[exp(-[w_p]x) Q exp([w_c]x)] = (I + A_p / 2) Q (I + A_c / 2)``
    to second order, with ``A = Sigma - tr(Sigma) I`` and ``Sigma`` the
    rotation block of the local pose covariance. The anisotropic part turns
    the singular vectors of ``S``; it does not shrink with ``N`` and, when
    the frames rotate little (a still stance followed by a short flexion),
    it is as large as the signal: on the fake mocap's knee, 670 still frames
    and 80 moving ones put the axis point 9 mm off with an sd of 3 mm.
    The direction and the point pair are therefore solved from the
    corrected sums of :func:`~jointfit_core.segments.debiased_sums`, as the
    ball's (:func:`~jointfit_core.segments.centre_from_pose_sums`); without
    rotation beyond the noise, from the noisy sums with the ball's
    first-order step.
    """
    Wp6 = _check_cov6(W_parent_local, "W_parent_local")
    Wc6 = _check_cov6(W_child_local, "W_child_local")
    n = float(sums.n)
    if n < 3:
        raise InputError(f"sums: expected at least 3 frames, got {n:g}")
    S = np.asarray(sums.S)
    K = np.asarray(sums.K)
    raw = svd3(S)
    deficit = np.clip(1.0 - raw[1] / n, 0.0, None)
    if deficit[1] <= SINGULAR_REL:
        raise NotIdentifiableError(
            "no relative rotation between the child and the parent: the hinge axis is undefined; flex the joint"
        )
    g = np.concatenate([sums.sum_t, -np.asarray(sums.sum_qt_t)])
    A_p, A_c = noise_bias_matrices(Wp6, Wc6, W_bias)
    S_c, g_c = debiased_sums(sums, A_p, A_c) if compensate_bias else (S, g)
    U, s, V = svd3(S_c)
    n_p, n_c = U[:, 0].copy(), V[:, 0].copy()
    if reference_direction is not None:
        ref = check_vector3(reference_direction, name="reference_direction", unit=True)
    else:
        ref = np.zeros(3)
        ref[int(np.argmax(np.abs(n_p)))] = 1.0
    flip = 1.0 if n_p @ ref >= 0.0 else -1.0

    # The point pair: the (corrected) normal equations in the complement of the gauge direction.
    if n - s[1] > SINGULAR_REL * n:
        H_pinv = gauge_free_pinv(U, s, V, n)
        a = H_pinv @ g_c
    else:  # no rotation beyond the noise: the noisy equations and the ball's first-order step
        H_pinv = gauge_free_pinv(*raw, n)
        a = first_order_bias_step(H_pinv @ g, H_pinv, S, n, A_p, A_c)
    c_p, c_c = a[:3], a[3:]

    # Sandwich covariance of the point pair (as centre_from_pose_sums, with the pseudo-inverse).
    cov_a = H_pinv @ _sums_meat(sums, c_p, c_c, Wp6, Wc6) @ H_pinv

    cov_dir = _direction_covariance(U, s, V, n, K, Wp6[:3, :3], Wc6[:3, :3])
    n_p, n_c = flip * n_p, flip * n_c
    point_p = c_p - n_p * (n_p @ c_p)
    point_c = c_c - n_c * (n_c @ c_c)
    P_p = np.eye(3) - np.outer(n_p, n_p)
    P_c = np.eye(3) - np.outer(n_c, n_c)
    Jn_p = -((n_p @ c_p) * np.eye(3) + np.outer(n_p, c_p))
    Jn_c = -((n_c @ c_c) * np.eye(3) + np.outer(n_c, c_c))
    cov_dir_p, cov_dir_c = cov_dir[:3, :3], cov_dir[3:, 3:]
    cov_pt_p = P_p @ cov_a[:3, :3] @ P_p + Jn_p @ cov_dir_p @ Jn_p.T
    cov_pt_c = P_c @ cov_a[3:, 3:] @ P_c + Jn_c @ cov_dir_c @ Jn_c.T

    mo = _motion(S, n, Wp6[:3, :3], _kq(K, Wc6[:3, :3]) / n)
    identifiable, reason = _axis_verdict(
        mo, cov_dir_p, cov_dir_c, cov_pt_p, cov_pt_c, point_p, point_c, length_scale
    )

    def sym(m: FloatArray) -> FloatArray:
        return 0.5 * (m + m.T)

    return PoseSumsAxis(
        direction_parent=n_p,
        direction_child=n_c,
        point_parent=point_p,
        point_child=point_c,
        cov_direction_parent=sym(cov_dir_p),
        cov_direction_child=sym(cov_dir_c),
        cov_point_parent=sym(cov_pt_p),
        cov_point_child=sym(cov_pt_c),
        rms=_sums_rms(sums, c_p, c_c),
        n_frames=round(n),
        identifiable=identifiable,
        reason=reason,
    )
