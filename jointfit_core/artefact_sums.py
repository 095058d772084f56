"""Soft-tissue artefact (STA) covariance of the online estimates, from running sums.

The batch fits (:mod:`jointfit_core.artefact`) propagate a prior on each
skin cluster's rigid motion on its bone through every frame. The online
estimator keeps only sums, so this module keeps the few extra sums that the
same propagation needs and does it on them:

- per frame, the features ``f_t`` of the joint angles (rotation vector of the
  relative rotation ``Q_t``, its squares and cross products: the linear plus
  quadratic artefact model of Camomilla et al. 2013 and Bonci et al. 2014)
  and their products with the relative pose: ``sum f``, ``sum Q (x) f``,
  ``sum t (x) f``, ``sum (Q^T t) (x) f``, ``sum |f|^2``, ``sum f f^T`` and
  ``sum f f^T (x) Q``
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
``Q_t n_c - n_p``, which sees the cluster turns that tilt the axis: its
projection on the columns of a turn that follows the hinge angle, from the
features' second moments ``sum f f^T`` and ``sum f f^T Q`` (as the batch fit's
:func:`jointfit_core.artefact._moment_scale`); the larger of the two is used.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .artefact import NU_MIN, posterior_scale2, prior_scale2, t_widened
from .pose import skew
from .segments import gauge_free_pinv, normal_matrix, svd3

__all__ = [
    "N_FEATURE_MOMENTS",
    "N_FEATURE_SUMS",
    "SumsArtefact",
    "artefact_from_sums",
    "ball_parameters",
    "ball_parameters_jacobian",
    "feature_sums",
    "hinge_parameters",
    "rotation_features",
]

FloatArray = NDArray[np.float64]

#: Number of joint-angle features (rotation vector, squares, cross products).
N_FEATURES = 9
#: Layout of :func:`feature_sums`: f (9), Q_ij f_k (81), t_i f_k (27), (Q^T t)_i f_k (27), |f|^2 (1);
#: with ``moments`` (hinges) then f_a f_b for a <= b (45, :data:`_PAIRS` order), f_a f_b Q_ij (45 x 9, pair-major).
_F = slice(0, 9)
_QF = slice(9, 90)
_TF = slice(90, 117)
_PF = slice(117, 144)
_FF = 144
N_FEATURE_SUMS = 145
_FFS = slice(145, 190)
_FFQ = slice(190, 595)
#: Numbers the second moments add to :func:`feature_sums` (hinges: their alignment reading's Gram).
N_FEATURE_MOMENTS = 450
#: The feature pairs ``(a, b)``, ``a <= b``, of the second moments ``sum f_a f_b`` (and ``sum f_a f_b Q``).
_PAIRS = np.triu_indices(N_FEATURES)
#: A hinge has one joint angle, whose linear and quadratic terms span a plane of the features.
HINGE_FEATURES = 2
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


def feature_sums(Q: FloatArray, t: FloatArray, moments: bool = False) -> FloatArray:
    """Per-frame contributions (N, L) of relative poses ``Q`` (N, 3, 3), ``t`` (N, 3).

    ``L`` is :data:`N_FEATURE_SUMS`, plus :data:`N_FEATURE_MOMENTS` with ``moments``
    (``sum f f^T`` and ``sum f f^T (x) Q``, which a hinge's alignment reading needs).
    """
    f = rotation_features(Q)
    n = f.shape[0]
    out = np.empty((n, N_FEATURE_SUMS + (N_FEATURE_MOMENTS if moments else 0)))
    out[:, _F] = f
    out[:, _QF] = (Q.reshape(n, 9, 1) * f[:, None, :]).reshape(n, 81)
    out[:, _TF] = (t[:, :, None] * f[:, None, :]).reshape(n, 27)
    qt = np.einsum("nji,nj->ni", Q, t)
    out[:, _PF] = (qt[:, :, None] * f[:, None, :]).reshape(n, 27)
    out[:, _FF] = np.einsum("nk,nk->n", f, f)
    if moments:
        ff = f[:, _PAIRS[0]] * f[:, _PAIRS[1]]
        out[:, _FFS] = ff
        out[:, _FFQ] = (ff[:, :, None] * Q.reshape(n, 1, 9)).reshape(n, 405)
    return out


def ball_parameters(n: float, S: FloatArray, sum_t: FloatArray, sum_qt: FloatArray) -> FloatArray:
    """``(c_p, c_c)`` (6,) of Stoddart's eq. 9 from the sums (no bias compensation)."""
    out: FloatArray = np.linalg.solve(normal_matrix(S, n), np.concatenate([sum_t, -sum_qt]))
    return out


def ball_parameters_jacobian(n: float, S: FloatArray, sum_t: FloatArray, sum_qt: FloatArray) -> FloatArray:
    """Derivative (6, 15) of :func:`ball_parameters` with respect to ``(S.ravel(), sum_t, sum_qt)``.

    Notes
    -----
    With ``A x = b``, ``b = (sum_t, -sum_qt)``: ``dx = A^-1 (db - dA x)``. A unit change of
    ``S_ij`` gives ``dA = -[[0, E_ij], [E_ij^T, 0]]``, so its column is ``x_c[j] A^-1 e_i +
    x_p[i] A^-1 e_(3+j)``; ``sum_t`` and ``sum_qt`` enter ``b`` only (Stoddart et al. eq. 9).
    Exact, where the finite differences it replaces cost 30 solves and carried their step's
    rounding (relative ~1e-10).
    """
    A_inv = np.linalg.inv(normal_matrix(S, n))
    x = A_inv @ np.concatenate([sum_t, -sum_qt])
    out = np.empty((6, 15))
    # column 3 i + j: x_c[j] A^-1[:, i] + x_p[i] A^-1[:, 3 + j]
    out[:, :9] = (A_inv[:, :3, None] * x[None, None, 3:] + x[None, :3, None] * A_inv[:, None, 3:]).reshape(6, 9)
    out[:, 9:12] = A_inv[:, :3]
    out[:, 12:] = -A_inv[:, 3:]
    return out


def hinge_parameters(
    n: float, S: FloatArray, sum_t: FloatArray, sum_qt: FloatArray, reference: FloatArray
) -> FloatArray:
    """``(n_p, n_c, point_p, point_c)`` (..., 12) of the hinge closed form from the sums.

    As :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums`: the top
    singular pair of ``S`` (signed so that ``n_p . reference >= 0``) and the
    pseudo-inverse solution of eq. 9 without the gauge direction, each point
    moved to the axis point nearest its local origin (without the bias
    step: its derivatives are second order). ``S`` (..., 3, 3), ``sum_t`` and
    ``sum_qt`` (..., 3) may carry leading axes (many sums at once, as the finite
    differences of :func:`artefact_from_sums` take them).
    """
    U, s, V = svd3(S)
    flip = np.where(U[..., :, 0] @ reference >= 0.0, 1.0, -1.0)[..., None]
    a = (gauge_free_pinv(U, s, V, n) @ np.concatenate([sum_t, -sum_qt], axis=-1)[..., None])[..., 0]
    n_p, n_c = flip * U[..., :, 0], flip * V[..., :, 0]
    a_p, a_c = a[..., :3], a[..., 3:]
    point_p = a_p - n_p * np.sum(n_p * a_p, axis=-1, keepdims=True)
    point_c = a_c - n_c * np.sum(n_c * a_c, axis=-1, keepdims=True)
    out: FloatArray = np.concatenate([n_p, n_c, point_p, point_c], axis=-1)
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
    cluster_motion : ndarray, shape (2, 6)
        Per frame, the variance of each cluster's motion on its bone about its window mean,
        ``(omega, u)`` per component (rad^2, input units squared), parent then child: the same
        prior at the same scale, over the window's mean feature energy (``s^2 v_j |f_t - fbar|^2``
        averaged over the frames). Zero for rigid clusters. What a single frame's pose of the
        cluster is off from its bone's, which the per-frame world outputs add
        (:class:`~jointfit_core.joint_world.WorldOutput`).
    """

    cov: FloatArray
    scale: float
    cluster_motion: FloatArray = field(default_factory=lambda: np.zeros((2, 6)))


def _centred(fs: FloatArray, n: float, S: FloatArray, sum_t: FloatArray, sum_qt: FloatArray) -> tuple[FloatArray, ...]:
    """Window-centred ``sum Q f_k`` (9, 3, 3), ``sum t f_k``, ``sum Q^T t f_k`` (9, 3) and ``sum |f - fbar|^2``."""
    fbar = fs[_F] / n
    SQ = fs[_QF].reshape(3, 3, 9).transpose(2, 0, 1) - fbar[:, None, None] * S[None]
    ST = fs[_TF].reshape(3, 9).T - fbar[:, None] * sum_t[None]
    SP = fs[_PF].reshape(3, 9).T - fbar[:, None] * sum_qt[None]
    ff = max(float(fs[_FF]) - n * float(fbar @ fbar), 0.0)
    return SQ, ST, SP, np.array(ff)


def _centred_moments(fs: FloatArray, n: float, S: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Window-centred ``F = sum (f - fbar)(f - fbar)^T`` (9, 9) and ``M_ab = sum (f_a - fbar_a)(f_b - fbar_b) Q`` (9, 9, 3, 3)."""
    fbar = fs[_F] / n
    a, b = _PAIRS
    F = np.zeros((N_FEATURES, N_FEATURES))
    F[a, b] = fs[_FFS]
    F[b, a] = fs[_FFS]
    F -= n * np.outer(fbar, fbar)
    M = np.zeros((N_FEATURES, N_FEATURES, 3, 3))
    ffq = fs[_FFQ].reshape(-1, 3, 3)
    M[a, b] = ffq
    M[b, a] = ffq
    SQ_raw = fs[_QF].reshape(3, 3, 9).transpose(2, 0, 1)  # sum f_k Q, not centred
    M -= fbar[:, None, None, None] * SQ_raw[None] + fbar[None, :, None, None] * SQ_raw[:, None]
    M += np.multiply.outer(np.outer(fbar, fbar), S)
    return F, M


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


def _rotation_moments(
    fs: FloatArray,
    n: float,
    S: FloatArray,
    SQ: FloatArray,
    directions: tuple[FloatArray, FloatArray],
    dn: FloatArray,
    rot_var: tuple[float, float],
    ss: float,
    smooth: float,
) -> tuple[float, float]:
    """The prior's ``s^2`` read from the axis-alignment residual ``s_t = Q_t n_c - n_p`` on its columns, and its dof.

    Parameters
    ----------
    fs : ndarray, shape (N_FEATURE_SUMS + N_FEATURE_MOMENTS,)
        The window's :func:`feature_sums` with ``moments``.
    n : float
        Frames (or weight) in the window.
    S : ndarray, shape (3, 3)
        ``sum Q``.
    SQ : ndarray, shape (9, 3, 3)
        Window-centred ``sum Q_t f_tk`` (:func:`_centred`).
    directions : (ndarray (3,), ndarray (3,))
        The estimated ``(n_p, n_c)`` (unit).
    dn : ndarray, shape (6, 54)
        The directions' change per unit entry of ``G`` for its 54 turn entries
        (``omega_p`` components, then ``omega_c``; 9 features each, feature fastest).
    rot_var : (float, float)
        Per unit ``s^2``, the prior variance of one turn component of the parent's and the
        child's cluster per unit feature (rad^2 per input unit^2).
    ss : float
        ``sum_t |s_t|^2`` (dimensionless).
    smooth : float
        Its smooth part (:func:`~jointfit_core.serial.smooth_energy_from_lags`); the rest is
        white noise.

    Returns
    -------
    scale2 : float
        The moment estimate of ``s^2`` (input units squared per rad^2), clipped at 0.
    nu : float
        Its effective degrees of freedom, ``(sum lam^2)^2 / sum lam^4`` (inf without columns).

    Notes
    -----
    A hinge has one joint angle, so its artefact (linear plus quadratic in that angle) varies
    in a plane of the 9 features: the plane in which the window's centred features vary most
    (:data:`HINGE_FEATURES` leading eigenvectors of ``sum (f - fbar)(f - fbar)^T``). The other
    feature directions are the relative rotation's components off the axis, which for a hinge
    are not joint angles but the artefact itself (and noise): with them among the columns any
    off-axis rotation, whatever moved the cluster (a thigh cluster moving with the hip, on a
    skeleton), was explained as cluster motion following itself, and read in full.

    A turn ``g_t = G f_t`` of the clusters on their bones (``f`` in that plane) moves the
    residual by ``[Q_t n_c]x omega_p - Q_t [n_c]x omega_c`` plus the directions' refit
    ``Q_t dn_c - dn_p``: per unit entry of ``G`` a column ``C_jk`` over the frames. As the
    batch fit does (:func:`jointfit_core.artefact._moment_scale`), ``s`` is read from the
    residual projected on these columns, ``s^2 = (|C^T s|^2 - sigma^2 tr(C^T C)) / sum lam^2``
    with ``lam`` the eigenvalues of the columns' Gram ``C^T C`` (scaled by the prior's
    variances) and ``sigma^2`` the white noise per component of the residual (which lies in
    the plane normal to the axis): the directions the prior fills most weigh most, and a
    residual it does not predict is left out. Everything is from the sums: ``C^T s`` from
    ``sum f Q`` (the residual is linear in ``Q``), the Gram from ``sum f f^T`` and
    ``sum f f^T Q`` (with ``[Q_t n_c]x`` taken as ``[n_p]x``, exact for a hinge).
    """
    n_p, n_c = (np.asarray(v, dtype=np.float64) for v in directions)
    F, M = _centred_moments(fs, n, S)
    # the hinge angle's features: the plane in which the window's features vary most
    _, vecs = np.linalg.eigh(0.5 * (F + F.T))
    V = vecs[:, ::-1][:, :HINGE_FEATURES]  # (9, r)
    r = V.shape[1]
    F = V.T @ F @ V
    M = np.einsum("ka,klij,lb->abij", V, M, V)
    SQ = np.einsum("ka,kij->aij", V, SQ)
    dn = (dn.reshape(6, 2, 3, N_FEATURES) @ V).reshape(6, 6 * r)
    Ap, Ac = skew(n_p), skew(n_c)  # column j: n x e_j
    dn_p, dn_c = dn[:3], dn[3:]
    h = 3 * r
    # Gram of the direct parts: parent-parent, child-child, parent-child (j, k, j', k')
    pp = np.einsum("kl,ij->ikjl", F, Ap.T @ Ap).reshape(h, h)
    cc = np.einsum("kl,ij->ikjl", F, Ac.T @ Ac).reshape(h, h)
    pc = -np.einsum("ai,klab,bj->ikjl", Ap, M, Ac).reshape(h, h)
    G = np.block([[pp, pc], [pc.T, cc]])
    # direct part against the refit (Q_t dn_c - dn_p), and the refit against itself (normal matrix)
    cross = np.concatenate([
        np.einsum("ai,kab,bc->ikc", Ap, SQ, dn_c).reshape(h, -1),
        np.einsum("ai,kba,bc->ikc", Ac, SQ, dn_p).reshape(h, -1),
    ])
    A = normal_matrix(S, n)
    G = G + cross + cross.T + dn.T @ A @ dn
    # the columns against the residual s_t = Q_t n_c - n_p
    cs = np.concatenate([
        np.cross(SQ @ n_c, n_p).T.reshape(h),  # parent: e_j . ((sum f_k Q) n_c x n_p)
        np.einsum("ai,kba,b->ik", Ac, SQ, n_p).reshape(h),  # child: (n_c x e_j) . (sum f_k Q)^T n_p
    ])
    cs = cs + dn_c.T @ (n * n_c - S.T @ n_p) - dn_p.T @ (S @ n_c - n * n_p)
    sv = np.sqrt(np.repeat(np.asarray(rot_var, dtype=np.float64), h))
    G = 0.5 * (G + G.T) * sv[:, None] * sv[None, :]
    cs = cs * sv
    lam = np.maximum(np.linalg.eigvalsh(G), 0.0)
    den = float(np.sum(lam * lam))
    if not den > 0.0:
        return 0.0, float("inf")
    white = max(ss - smooth, 0.0) / (2.0 * n)
    scale2 = max((float(cs @ cs) - white * float(lam.sum())) / den, 0.0)
    return scale2, den * den / float(np.sum(lam**4))


def _jacobian(solver: Callable[[FloatArray], FloatArray], x0: FloatArray, scales: FloatArray) -> FloatArray:
    """Central finite-difference Jacobian (m, 15) of ``solver`` at ``x0`` with per-entry steps.

    ``solver`` takes the 30 displaced points at once, ``(30, 15) -> (30, m)`` (the + steps, then the - steps).
    """
    k = x0.size
    h = _STEP * scales
    X = np.repeat(x0[None, :], 2 * k, axis=0)
    X[np.arange(k), np.arange(k)] += h
    X[k + np.arange(k), np.arange(k)] -= h
    P = solver(X)
    out: FloatArray = ((P[:k] - P[k:]) / (2.0 * h)[:, None]).T
    return out


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
    rotation_ss: float = 0.0,
    solver_jacobian: Callable[[FloatArray], FloatArray] | None = None,
    deformation: float = 0.0,
    n_markers: int = 4,
) -> SumsArtefact:
    """Soft-tissue covariance of a sums-based estimate (first order in the cluster motion).

    Parameters
    ----------
    fs : ndarray, shape (N_FEATURE_SUMS,) or (N_FEATURE_SUMS + N_FEATURE_MOMENTS,)
        The window's :func:`feature_sums`; a hinge (``directions``) needs them with ``moments``.
    n : float
        Frames (or weight) in the window.
    S, sum_t, sum_qt : ndarray, shapes (3, 3), (3,), (3,)
        ``sum Q``, ``sum t``, ``sum Q^T t`` of the window.
    solver : callable
        ``solver(X) -> params (K, m)`` for ``K`` points ``X`` (K, 15), each ``(S.ravel(),
        sum_t, sum_qt)``: the estimate as a function of those sums (many at once: the
        finite differences take 30).
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
    rotation_ss : float
        Hinge: ``sum_t |Q_t n_c - n_p|^2`` itself (its white part, ``rotation_ss -
        rotation_smooth``, is the noise of the projection).
    solver_jacobian : callable, optional
        ``solver_jacobian(x) -> (m, 15)``, the derivative of ``solver`` at ``x`` (e.g.
        :func:`ball_parameters_jacobian`); None: central finite differences of ``solver``.
    deformation : float
        The skin clusters' deformation variance per coordinate (input units squared; the larger
        of the two, pooled pose-fit residual variance minus white noise variance), which sets the
        literature prior on the scale (:func:`~jointfit_core.artefact.prior_scale2`); 0: no prior.
    n_markers : int
        Markers of that cluster.

    Returns
    -------
    SumsArtefact

    Raises
    ------
    ValueError
        ``directions`` given with ``fs`` lacking the moments.

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
    turn off the axis. It is read on the columns a turn following the hinge
    angle gives it (:func:`_rotation_moments`: projected, as the batch fit
    reads its scale, not as an energy ratio, which took every off-axis
    rotation for such a turn: on a skeleton, the thigh cluster moving with
    the hip made the knees' direction sd 21-42 deg for 3.5-5.4 deg errors),
    times ``nu / (nu - 2)`` for its few effective degrees of freedom. The
    scale is the larger of the two readings (without the second, a knee
    whose shank cluster turned about the shank read no artefact and was
    confidently wrong: ``bench/sta_online.py``).

    **The literature prior** (:func:`~jointfit_core.artefact.posterior_scale2`, eq. A6 of
    :mod:`jointfit_core.artefact`; ``deformation`` and ``n_markers`` set it) joins the point
    reading, which is credited :data:`~jointfit_core.artefact.NU_MIN` effective directions: a
    window whose rigid artefact happened to leave almost no smooth residual is no longer read as
    free of it (``bench/sta_rom.py``: a hip at 8 deg of range published 15.5 sd^2 off, a knee at
    20 deg 21.7 deg off with an sd of 5.1 deg, e/2 16.8; now 6.2 and 1.1). The alignment reading
    keeps its ``nu / (nu - 2)`` without the prior: on the sums' reduced feature plane it already
    reads low against the batch fit, and the factor (3, ``nu`` at its floor) is its calibration;
    with the prior on it too the knees of ``bench/sta_online.py`` went from mean e/2 0.45-0.52 to
    0.24-0.47.
    """
    m = solver(np.concatenate([S.ravel(), sum_t, sum_qt])[None, :]).shape[-1]
    if directions is not None and fs.size < N_FEATURE_SUMS + N_FEATURE_MOMENTS:
        raise ValueError(
            f"fs: a hinge needs the feature sums with their moments ({N_FEATURE_SUMS + N_FEATURE_MOMENTS}), got {fs.size}"
        )
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
    ball_jac = ball_parameters_jacobian(n, S, sum_t, sum_qt)
    J_x = _jacobian(solver, x0, steps) if solver_jacobian is None else solver_jacobian(x0)
    dparams = J_x @ delta  # (m, 108)
    # visible residual energy per unit s^2 (ball normal matrix, centre pair from eq. 9)
    da = ball_jac @ delta
    A = normal_matrix(S, n)
    absorbed_jk = np.einsum("ik,ij,jk->k", da, A, da)  # (108,)
    var = np.concatenate([_prior_variances(radii[0]) * w[0], _prior_variances(radii[1]) * w[1]])
    vjk = np.repeat(var, 9)
    c_p, c_c = (np.asarray(c, dtype=np.float64) for c in centres)
    direct = w[0] * (2.0 * float(c_p @ c_p) / max(radii[0] ** 2, 1e-300) + 3.0)
    direct += w[1] * (2.0 * float(c_c @ c_c) / max(radii[1] ** 2, 1e-300) + 3.0)
    visible = direct * ff - float(absorbed_jk @ vjk)
    scale2 = smooth_energy / visible if visible > 0.0 else 0.0
    # the literature prior tied to the cluster's deformation (artefact.py, eq. A6), in these units (the
    # weights here are 1, not the deformation variance), where it is more cautious; the energy reading is
    # credited NU_MIN directions
    prior2 = prior_scale2(n_markers, ff / n) * max(float(deformation), 0.0) / float(w.max())
    scale2 = max(scale2, posterior_scale2(scale2, NU_MIN, prior2)[0])
    if directions is not None and rotation_smooth > 0.0:
        # only the turns (omega) reach the alignment residual; read on their columns, as the batch fit
        turns = np.r_[0:27, 54:81]
        rot2, nu = _rotation_moments(
            fs, n, S, SQ, directions, dparams[:6, turns], (float(var[0]), float(var[6])), rotation_ss, rotation_smooth
        )
        # read from nu effective directions: the error over the covariance is F(k, nu)-like (artefact.py, eq. A5)
        scale2 = max(scale2, t_widened(rot2, nu))
    cov = scale2 * ((dparams * vjk) @ dparams.T)
    motion = scale2 * (ff / n) * var.reshape(2, 6)
    return SumsArtefact(0.5 * (cov + cov.T), math.sqrt(scale2 * float(w.max())), motion)
