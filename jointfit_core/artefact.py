"""Soft-tissue artefact (STA) in the two-segment covariances: white noise, a prior, and what the residuals show.

Skin markers move over the bone smoothly and with the joint angles (Leardini
et al. 2005: 10-30 mm on the thigh, 5-15 mm on the shank). Three things follow
for a joint fitted from cluster poses, and this module provides one tool for
each:

1. **Noise that is noise.** Pose-fit residuals hold the white marker noise and
   the cluster's smooth deformation; :func:`white_noise_std` reads the noise
   from their second differences in time, which a smooth deformation barely
   reaches.
2. **What the residuals cannot see.** A cluster that shifts and turns on its
   bone by an amount that depends on the joint angles moves the fitted joint:
   the part of the form ``delta_p - Q_t delta_c`` is exactly a joint at a
   shifted place and leaves no residual. :func:`artefact_covariance` puts a
   prior on that motion (each cluster's rigid motion on the bone, linear plus
   quadratic in the joint angles, after Camomilla et al. 2013 and Bonci et
   al. 2014), propagates it to the estimate (covariance along the directions
   it can bias) and scales it, per segment, by maximum likelihood from the
   part of the joint residuals that the same prior does predict (empirical
   Bayes): the visible and the invisible parts of one rigid cluster motion
   are tied by the geometry and the movement.
3. **What the residuals do show, correlated in time.** The rest of the
   residual (not explained by the prior) enters the estimate through a
   heteroscedasticity-and-autocorrelation-consistent (HAC, Newey & West
   1987) covariance whose bandwidth is the residual's integrated
   autocorrelation time (Sokal's window), so its effective sample size comes
   from the movement, not from the frame count.

The covariance of an estimate from skin markers is then ``cov_statistical +
cov_artefact``; the first shrinks with the data, the second does not (the
artefact is the same in every cycle of the same movement).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .errors import InputError

__all__ = [
    "ATTACHMENTS",
    "ArtefactCovariance",
    "artefact_covariance",
    "check_attachment",
    "deformation_weights",
    "joint_features",
    "posterior_scale2",
    "prior_scale2",
    "t_widened",
    "white_noise_std",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: How a segment's markers are attached: on the skin (soft-tissue artefact) or rigidly to the bone or body.
ATTACHMENTS = ("skin", "rigid")
#: Fewest effective degrees of freedom credited to the prior's estimated scale (caps its factor at 3).
NU_MIN = 3.0
#: The rigid share of a skin cluster's artefact amplitude, ~75 % (Camomilla et al. 2013; the rest is the
#: cluster's deformation): the literature prior on the scale expects a rigid motion ``RIGID_SHARE /
#: sqrt(1 - RIGID_SHARE^2)`` (1.13) times the deformation the pose-fit residuals show (:func:`prior_scale2`).
RIGID_SHARE = 0.75
#: Weight of that prior, in effective directions of the residual (eq. A6): one, a weak prior (its 90 % range
#: of ``s`` spans a factor of ~30, 0.5-16 ``s_0``), against the 2-3.5 directions the data read a ball's scale from
#: (:func:`_moment_scale`). Enough that a reading far below the prior (a draw whose rigid motion left almost no
#: residual) no longer gives an estimate many sd off (:func:`posterior_scale2`; ``test/test_sta_scale_prior.py``).
PRIOR_NU = 1.0


def check_attachment(value: object, name: str = "attachment") -> tuple[str, str]:
    """``"skin"`` / ``"rigid"`` or a (parent, child) pair of them -> (parent, child)."""
    vals: object = (value, value) if isinstance(value, str) else value
    if not isinstance(vals, (tuple, list)) or len(vals) != 2:
        raise InputError(f"{name}: expected one of {ATTACHMENTS} or a (parent, child) pair, got {value!r}")
    p, c = vals[0], vals[1]
    if p not in ATTACHMENTS or c not in ATTACHMENTS:
        raise InputError(f"{name}: expected one of {ATTACHMENTS} or a (parent, child) pair, got {value!r}")
    return str(p), str(c)


def white_noise_std(
    markers: FloatArray, template: FloatArray, R: FloatArray, d: FloatArray, valid: BoolArray
) -> float:
    """White marker noise per coordinate from the second differences of the pose-fit residuals.

    Parameters
    ----------
    markers : ndarray, shape (N, P, 3)
        Marker positions in time order, world frame, input units; NaN for missing.
    template : ndarray, shape (P, 3)
        The segment's template (local frame).
    R, d : ndarray, shape (N, 3, 3) and (N, 3)
        Its poses (``world = R local + d``); rows where ``valid`` is False are ignored.
    valid : ndarray of bool, shape (N,)
        Posed frames.

    Returns
    -------
    float
        The noise standard deviation (input units), or NaN when no frame
        triple (three consecutive posed frames with the same visible markers,
        at least 4 of them) exists.

    Notes
    -----
    The local residual ``e_t = R_t^T (y_t - d_t) - x`` of a frame is the
    marker noise projected on the complement of the cluster's small rigid
    motions (dimension ``3 P_vis - 6``), plus the cluster's deformation,
    plus the template's error (the same every frame). The second difference
    ``e_{t+1} - 2 e_t + e_{t-1}`` cancels the template error and reduces a
    deformation of frequency ``f`` by ``(2 pi f / rate)^2`` (0.016 at 2 Hz
    and 100 Hz), while white noise gains the variance factor
    ``1 + 4 + 1 = 6``: ``sigma^2 = sum |Delta^2 e|^2 / (6 sum (3 P_vis - 6))``
    over the triples. Without deformation it estimates the same noise as the
    pooled residual (:func:`jointfit_core.pose.noise_std_from_fit`); with it,
    it does not read the deformation as noise. Frames must be in time order
    and sampled fast against the movement.
    """
    vis = np.isfinite(markers).all(axis=2) & valid[:, None]
    Rs = np.where(valid[:, None, None], R, 0.0)
    ds = np.where(valid[:, None], d, 0.0)
    local = np.einsum("nji,npj->npi", Rs, np.where(vis[..., None], markers, 0.0) - ds[:, None, :])
    e = np.where(vis[..., None], local - template[None], 0.0)
    same = (vis[1:-1] == vis[:-2]).all(axis=1) & (vis[1:-1] == vis[2:]).all(axis=1)
    n_vis = vis[1:-1].sum(axis=1)
    ok = same & (n_vis >= 4)
    if not ok.any():
        return float("nan")
    d2 = e[2:] - 2.0 * e[1:-1] + e[:-2]
    ss = float(np.sum(d2[ok] ** 2))
    dof = 6.0 * float(np.sum(3 * n_vis[ok] - 6))
    return float(np.sqrt(ss / dof))


def deformation_weights(
    pooled: tuple[float, float], white: tuple[float, float], attachment: tuple[str, str]
) -> tuple[float, float]:
    """Relative artefact size of the two clusters from their deformation (input units squared).

    ``pooled^2 - white^2`` per segment (clipped at 0) is the variance of the
    cluster's smooth deformation; a cluster deforms and moves on its bone by
    the same soft tissue, the rigid part about as large as the deformation
    (Camomilla et al. 2013: ~75 % of the artefact energy rigid), so the
    prior's two segments are weighted by it. Rigid segments get 0; if neither
    skin segment shows deformation, they are weighted equally (by the larger
    pooled variance).
    """
    skin = [a == "skin" for a in attachment]
    w = [max(p * p - q * q, 0.0) if s else 0.0 for p, q, s in zip(pooled, white, skin, strict=True)]
    if sum(w) <= 0.0:
        level = max(p * p for p in pooled) or 1.0
        w = [level if s else 0.0 for s in skin]
    return float(w[0]), float(w[1])


@dataclass(frozen=True)
class ArtefactCovariance:
    """The parts of a covariance under soft-tissue artefact (parameters of the fit, its units).

    Attributes
    ----------
    statistical : ndarray, shape (m, m)
        White noise and the residuals the prior does not explain, through the
        HAC covariance (at least the white-noise covariance in every direction).
    artefact : ndarray, shape (m, m)
        The prior's covariance at the estimated scales (zero for rigid segments).
    scale : ndarray, shape (2,)
        Estimated prior scale per segment (parent, child): the rms cluster
        translation on the bone per unit of the features (input units per
        radian of joint rotation, per component); 0 for a rigid segment.
    tau : float
        Integrated autocorrelation time of the remaining residual (frames).
    bandwidth : int
        HAC bandwidth (frames).
    cluster_motion : ndarray, shape (2, 6)
        Per frame, the variance of each cluster's motion on its bone, ``(omega, u)`` per
        component (rad^2, units squared), parent then child: the prior at the estimated scales
        over the mean feature energy, ``s_seg^2 v_j mean_t |f_t|^2``. What one frame's cluster
        pose is off from its bone's (the per-frame world outputs add it). Zero for rigid segments.
    """

    statistical: FloatArray
    artefact: FloatArray
    scale: FloatArray
    tau: float
    bandwidth: int
    cluster_motion: FloatArray = field(default_factory=lambda: np.zeros((2, 6)))

    @property
    def total(self) -> FloatArray:
        out: FloatArray = self.statistical + self.artefact
        return out


def joint_features(Q: FloatArray) -> FloatArray:
    """Centred linear and quadratic terms of the relative rotation, (N, 3, 3) -> (N, 9).

    ``q_t`` is the rotation vector of ``Q_t`` relative to the mean relative
    rotation (rad); the features are ``q``, its squares and cross products
    (the Camomilla / Bonci model), each minus its mean over the frames.
    """
    U, _, Vt = np.linalg.svd(Q.sum(axis=0))
    Qbar = U @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))]) @ Vt
    q = Rotation.from_matrix(Qbar.T @ Q).as_rotvec()
    f = np.concatenate([q, q**2, q[:, [0]] * q[:, [1]], q[:, [0]] * q[:, [2]], q[:, [1]] * q[:, [2]]], axis=1)
    out: FloatArray = f - f.mean(axis=0)
    return out


def _prior_variances(template: FloatArray) -> FloatArray:
    """Per unit scale, the prior variances of ``(omega, u)`` (6,): rotation ``1 / r^2``, translation 1.

    ``r`` is the cluster's rms radius: a cluster rotation and a cluster shift
    of the prior's size move its markers by the same amount, as the
    fluoroscopy of Akbarshahi et al. (2010) and Stagni et al. (2005) found
    for the thigh (~10 deg of turning and ~18 mm of shift for a ~100 mm cluster).
    """
    r2 = float(np.mean(np.sum((template - template.mean(axis=0)) ** 2, axis=1)))
    return np.concatenate([np.full(3, 1.0 / max(r2, 1e-300)), np.ones(3)])


def prior_scale2(n_markers: int, feature_ms: float) -> float:
    """The literature prior's scale ``s_0^2`` per unit of a cluster's deformation variance (eq. A6).

    Parameters
    ----------
    n_markers : int
        Markers of the cluster whose deformation sets the prior (3 or more).
    feature_ms : float
        Mean over the frames of ``|f_t|^2``, the centred joint-angle features
        (:func:`joint_features`; rad^2, squared for the quadratic terms).

    Returns
    -------
    float
        ``rho^2 (3 P - 6) / (5 P F)`` with ``rho = RIGID_SHARE / sqrt(1 - RIGID_SHARE^2)``; 0 (no
        prior) without movement or with fewer than 3 markers.

    Notes
    -----
    A deformation with no rigid part, of mean square ``a_d^2`` per marker, leaves the pose-fit residual
    variance ``w = a_d^2 P / (3 P - 6)`` per degree of freedom (the weights of
    :func:`deformation_weights`); a rigid cluster motion of the prior (:func:`_prior_variances`) at
    scale ``s`` moves a marker by ``5 s^2 w F`` in mean square (3 translation components, and 2 of the
    turn's 3 at the cluster's rms radius, per unit feature, times the features' mean square ``F``).
    Equating that with ``rho^2 a_d^2`` gives ``s_0^2 = rho^2 (3 P - 6) / (5 P F)`` in the units of ``w``
    (``test/test_sta_scale_prior.py`` draws both).
    """
    if n_markers < 3 or not feature_ms > 0.0:
        return 0.0
    rho2 = RIGID_SHARE**2 / (1.0 - RIGID_SHARE**2)
    return float(rho2 * (3 * n_markers - 6) / (5.0 * n_markers * feature_ms))


def t_widened(scale2: float, nu: float) -> float:
    """``scale2 nu / (nu - 2)`` with ``nu`` at least :data:`NU_MIN` (eq. A5; ``nu`` infinite: unchanged)."""
    if not np.isfinite(nu):
        return scale2
    nu = max(nu, NU_MIN)
    return scale2 * nu / (nu - 2.0)


def posterior_scale2(scale2: float, nu: float, prior2: float) -> tuple[float, float]:
    """The artefact scale ``s^2`` read on ``nu`` effective directions, combined with the literature prior (eq. A6).

    Parameters
    ----------
    scale2 : float
        The data's reading of ``s^2`` (:func:`_moment_scale`, or the sums' readings).
    nu : float
        Its effective degrees of freedom (``inf``: the data fix it).
    prior2 : float
        The prior's ``s_0^2`` in the same units (:func:`prior_scale2` times the weight); 0: no prior.

    Returns
    -------
    scale2, nu : float
        The posterior's ``(PRIOR_NU s_0^2 + nu s^2) / (PRIOR_NU + nu)`` and ``PRIOR_NU + nu``
        (scaled-inverse-chi-square prior, conjugate); the reading unchanged without a prior or when
        ``nu`` is not finite.
    """
    if not prior2 > 0.0 or not np.isfinite(nu) or not np.isfinite(prior2):
        return scale2, nu
    nu = max(nu, 0.0)
    return (PRIOR_NU * prior2 + nu * scale2) / (PRIOR_NU + nu), PRIOR_NU + nu


def _integrated_time(z: FloatArray) -> tuple[float, int]:
    """Integrated autocorrelation time (frames) of a vector series (N, k) and Sokal's window."""
    n = z.shape[0]
    if n < 8:
        return 1.0, 1
    zc = z - z.mean(axis=0)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    F = np.fft.rfft(zc, size, axis=0)
    acf = np.fft.irfft((F * F.conj()).real.sum(axis=1), size)[:n]
    if acf[0] <= 0.0:
        return 1.0, 1
    rho = acf / acf[0]
    tau = 1.0
    window = 1
    for lag in range(1, n // 4):
        tau += 2.0 * rho[lag]
        window = lag
        if lag >= 5.0 * tau:
            break
    return max(tau, 1.0), window


def _hac(scores: FloatArray, bandwidth: int) -> FloatArray:
    """Bartlett-kernel long-run covariance ``sum_l w_l Gamma_l`` of a score series (N, m)."""
    n, m = scores.shape
    size = 1 << int(np.ceil(np.log2(2 * n)))
    F = np.fft.rfft(scores, size, axis=0)
    cross = np.fft.irfft(F[:, :, None] * F[:, None, :].conj(), size, axis=0)  # lag l: sum_t s_{t+l} s_t^T
    L = min(bandwidth, n - 1)
    w = 1.0 - np.arange(L + 1) / (L + 1.0)
    pos = np.einsum("l,lij->ij", w, cross[: L + 1])
    neg = np.einsum("l,lij->ij", w[1:], cross[size - L :][::-1]) if L > 0 else np.zeros((m, m))
    out: FloatArray = pos + neg
    return 0.5 * (out + out.T)


def _floor(cov: FloatArray, floor: FloatArray) -> FloatArray:
    """The covariance with every direction at least that of ``floor`` (generalised eigenvalues clipped at 1).

    Whitened by the Cholesky factor of ``floor`` (scale-equivariant, so parameters in different units,
    radians and lengths, give the same result in any unit).
    """
    L = np.linalg.cholesky(floor)
    white = np.linalg.solve(L, np.linalg.solve(L, cov).T)
    mu, E = np.linalg.eigh(0.5 * (white + white.T))
    B = L @ E
    out: FloatArray = (B * np.maximum(mu, 1.0)) @ B.T
    return 0.5 * (out + out.T)


def _inv_scaled(A: FloatArray) -> FloatArray:
    """Inverse of a symmetric positive definite matrix scaled to unit diagonal first (units may differ)."""
    d = 1.0 / np.sqrt(np.diag(A))
    inv = np.linalg.inv(A * d[:, None] * d[None, :])
    out: FloatArray = inv * d[:, None] * d[None, :]
    return 0.5 * (out + out.T)


def _white_sandwich(A_inv: FloatArray, J: FloatArray, W: FloatArray) -> FloatArray:
    """White-noise covariance ``A^-1 (sum J_t^T W_t J_t) A^-1`` (m, m) of an unweighted estimate.

    ``A_inv`` (m, m), ``J`` (N, k, m) the residuals' Jacobian, ``W`` (N, k, k) their white-noise covariance.
    """
    meat = np.einsum("nim,nij,njp->mp", J, W, J)
    out: FloatArray = A_inv @ meat @ A_inv
    return 0.5 * (out + out.T)


def _moment_scale(u: FloatArray, B: FloatArray) -> tuple[float, float]:
    """Variance ``s^2`` for ``u ~ N(0, s^2 B B^T + I)`` and its effective degrees of freedom.

    With ``B B^T = V diag(lam) V^T`` and ``w_i = (V^T u)_i``, ``E w_i^2 = 1 + s^2 lam_i``; the fit
    ``s^2 = sum lam_i (w_i^2 - 1) / sum lam_i^2`` (clipped at 0) leans on the directions the prior
    fills most, so that a residual in a direction it barely reaches (a part of the artefact outside
    the model) cannot blow the scale up, as maximum likelihood does. Where the prior dominates the
    noise its variance is ``2 s^4 sum lam^4 / (sum lam^2)^2``, that of a chi-square scale with
    ``nu = (sum lam^2)^2 / sum lam^4`` degrees of freedom. Measured on the hip of ``bench/sta.py``:
    maximum likelihood (weights ``lam_i / (1 + s^2 lam_i)^2``) reads ``nu ~ 25`` directions where this
    fit reads ~3, but then 20 mm of thigh artefact give mean e/3 0.22 and the wobble not tied to the
    angles 0.0004 (the misfit read as scale; 40 trials); equal weights (``nu ~ 5``) 0.92 and 0.20 (20).
    """
    lam, V = np.linalg.eigh(B @ B.T)
    lam = np.maximum(lam, 0.0)
    w2 = (V.T @ u) ** 2
    den = float(np.sum(lam * lam))
    if den <= 0.0:
        return 0.0, float("inf")
    nu = den * den / float(np.sum(lam**4))
    return max(float(np.sum(lam * (w2 - 1.0))) / den, 0.0), nu


def artefact_covariance(
    res: FloatArray,
    J: FloatArray,
    D: FloatArray,
    W: FloatArray,
    features: FloatArray,
    templates: tuple[FloatArray, FloatArray],
    weights: tuple[float, float],
    *,
    weighted: bool = True,
    bread_correction: FloatArray | None = None,
) -> ArtefactCovariance:
    """Statistical and soft-tissue covariance of a two-segment estimate (Gauss-Markov or least squares, linearised).

    Parameters
    ----------
    res : ndarray, shape (N, k)
        Per-frame residuals at the estimate, used frames in time order.
    J : ndarray, shape (N, k, m)
        Their Jacobian with respect to the m fitted parameters.
    D : ndarray, shape (N, k, 12)
        Their Jacobian with respect to a small rigid motion of each cluster on
        its bone, ``(omega_p, u_p, omega_c, u_c)`` in the local frames about
        the local origins (the template centroids).
    W : ndarray, shape (N, k, k)
        White-noise covariance of each frame's residual (rows may be in
        different units: the whitening is by Cholesky factors, which keeps
        every result independent of the units).
    features : ndarray, shape (N, F)
        The functions of the joint angles the artefact follows (:func:`joint_features`).
    templates : (ndarray (Pa, 3), ndarray (Pc, 3))
        The two templates (set the prior's rotation-to-translation ratio).
    weights : (float, float)
        Relative size of the two clusters' artefact (0 for a rigid segment):
        :func:`deformation_weights`. The prior's overall scale is estimated.
    weighted : bool
        ``True`` (default): the estimate solves the Gauss-Markov equations
        ``sum_t J_t^T W_t^-1 r_t = 0``; ``False``: the unweighted ones ``sum_t
        J_t^T r_t = 0`` (an estimate first-order equivalent to unweighted least
        squares, e.g. the hinge closed form). The influence of a residual
        change on the estimate, and so every covariance, follows the equations.
    bread_correction : ndarray, shape (m, m), optional
        Weighted equations solved with the pose noise's expected share of
        ``A = sum J^T W^-1 J`` removed (``A - bread_correction``, e.g. after a
        still stance, see :func:`jointfit_core.segments._debiased_weighted`):
        the influence of a residual is ``(A - bread_correction)^-1 J^T
        W^-1``, and the white floor the sandwich with ``A``. Ignored when
        ``A - bread_correction`` is not positive definite.

    Returns
    -------
    ArtefactCovariance

    Notes
    -----
    A cluster motion ``g_t = G f_t`` on the bone (``G`` 12 x F) changes the
    residuals by ``D_t g_t`` and the Gauss-Markov estimate by ``delta a =
    -sum_t K_t g_t``, ``K_t = A^-1 J_t^T W_t^-1 D_t``; with the entries of
    ``G`` independent, zero-mean, of variance ``s_seg^2 v_j``
    (:func:`_prior_variances`), ``cov_artefact = sum_seg s_seg^2 sum_k sum_j
    v_j C_kj C_kj^T``, ``C_k = sum_t K_t f_tk`` (eq. A1). The same motion
    leaves the whitened residual ``z_t = L_t^-1 (D_t g_t + J_t delta a)``,
    i.e. ``z = B_p gamma_p + L_c gamma_c + eps`` with known columns (eq. A2);
    projected on their span (orthonormal basis ``U``), ``u = U^T z ~ N(0,
    s_p^2 U^T B_p B_p^T U + s_c^2 U^T B_c B_c^T U + I)`` gives ``s_p, s_c`` by
    maximum likelihood (eq. A3; zero where the likelihood cannot tell them
    from zero, and always zero for a rigid segment). The residual
    outside that span feeds the scores ``(L_t^-1 J_t)^T z_t``, whose
    Bartlett long-run covariance ``Omega`` with the bandwidth of twice
    Sokal's window of the residual's integrated autocorrelation gives
    ``cov_statistical = A^-1 Omega A^-1`` (eq. A4), clipped below at
    ``A^-1 = (sum J^T W^-1 J)^-1`` (never more confident than white noise).
    Whitening is by the Cholesky factor ``W_t = L_t L_t^T``, ``z_t = L_t^-1 r_t``.

    **Unweighted equations** (``weighted=False``): ``A = sum J^T J``, ``K_t =
    A^-1 J_t^T D_t``, the scores ``J_t^T r_t`` (the remaining residual) and the floor
    the white-noise sandwich ``A^-1 (sum J^T W J) A^-1``; the scale is read as
    above (the residual's likelihood is the white noise's whatever the
    estimator).

    **The scale's degrees of freedom (eq. A5).** ``s^2`` is read along
    ``nu = (sum lam^2)^2 / sum lam^4`` effective directions (:func:`_moment_scale`),
    ``s_hat^2 / s^2 ~ chi2_nu / nu``. With Jeffreys' prior ``p(s^2) ~ 1 / s^2``
    the posterior of ``s^2`` is scaled-inverse-chi-square ``(nu, s_hat^2)`` and the
    artefact's bias is predicted as a multivariate t with ``nu`` degrees of
    freedom, covariance ``nu / (nu - 2) s_hat^2 C`` (``C`` the unit-scale
    covariance of eq. A1): the factor applied (``nu >= NU_MIN``). Skin fits have
    ``nu ~ 2-3.5``, so ``e/k = delta^T cov^-1 delta / k`` is ``F(k, nu) (nu - 2) / nu``-like:
    mean 1, median ~0.3, and the mean of 30 trials is itself heavy-tailed (its
    median ~0.77). Measured on the model of ``bench/sta.py`` (hip, 200 seeded
    trials per level, 5 / 10 / 20 mm of thigh artefact): mean e/3 0.77 / 0.81 /
    0.92, median 0.42-0.47, e/3 > 3 in 5-6 % of the trials; without the factor
    the mean is 2.4-3.3, as ``nu / (nu - 2) ~ 3`` predicts.

    **A weak literature prior on the scale (eq. A6).** With ``s^2 ~``
    scaled-inverse-chi-square ``(nu_0, s_0^2)`` the posterior is conjugate,
    ``(nu_0 + nu, (nu_0 s_0^2 + nu s_hat^2) / (nu_0 + nu))`` (:func:`posterior_scale2`),
    and the factor becomes ``(nu_0 + nu) / (nu_0 + nu - 2)``. In the units of the weights
    (:func:`deformation_weights`) a literature prior is ``s_0^2 = rho^2 (3 P - 6)
    / (5 P F)`` (:func:`prior_scale2`): ``rho`` the rigid-to-deformation amplitude ratio (rigid ~75 %
    of the artefact, Camomilla et al. 2013: ``rho = 0.75 / sqrt(1 - 0.75^2)``),
    ``5 s^2 w`` the mean square marker motion per unit feature under
    :func:`_prior_variances`, ``w ~ a_d^2 P / (3 P - 6)`` the pose-fit residual
    variance of a deformation of rms amplitude ``a_d`` on ``P`` markers, ``F``
    the features' mean square; the prior is set by the cluster with the larger weight.
    ``nu_0 =`` :data:`PRIOR_NU` ``= 1``. Why: the reading from ``nu ~ 2-3.5`` directions
    has a heavy lower tail, and a trial whose rigid motion happened to leave little
    residual read its scale tens of times below the others and was called identifiable
    many sd off: on the hip of ``bench/sta.py`` (30 seeded trials, 10 mm of thigh
    artefact, 25 deg) one trial read ``s_hat^2 / s_0^2 = 0.024`` (the median trial 0.71)
    and was 20 mm off with an sd of 5.5 mm (e/3 = 24.7); at 8 deg of range one was 54 mm
    off with an sd of 10 mm (e/3 = 72). With the prior these are e/3 3.3 and 3.0. The cost
    is caution where the prior's premise fails: an artefact with no rigid part (the
    deformation-only case) or one not tied to the angles (wobble) has the rigid motion
    the prior expects from its deformation added (mean e/3 ~2e-4 and ~0.09 on
    ``bench/sta.py``, were 0.23 and 0.71); skin clusters in vivo move mostly rigidly
    (Camomilla et al. 2013), so that is the side to err on. ``nu_0 = 2`` (tried) gave the
    same tails with more caution, ``nu_0 ~ 5`` the deformation-only case 0.0002 and the
    hips' mean e/3 0.90 with ``nu ~ 8`` (20 trials).
    """
    n, k, _ = J.shape
    Lw = np.linalg.cholesky(0.5 * (W + np.swapaxes(W, 1, 2)))
    Jw = np.linalg.solve(Lw, J)  # (n, k, m): L^-1 J, so that Jw^T Jw = J^T W^-1 J
    Dw = np.linalg.solve(Lw, D)  # (n, k, 12)
    z = np.linalg.solve(Lw, res[..., None])[..., 0]
    # A and J_t^T V_t D_t (V = W^-1 or I) from plain products: through L^T J and L^-1 J the unweighted ones
    # would lose digits to the conditioning of L (rows in different units)
    Ju, Du = (Jw, Dw) if weighted else (J, D)
    A = np.einsum("nim,nip->mp", Ju, Ju)
    A = 0.5 * (A + A.T)
    A_inv = _inv_scaled(A)
    white = A_inv if weighted else _white_sandwich(A_inv, J, W)
    if weighted and bread_correction is not None:
        A_b = A - 0.5 * (bread_correction + bread_correction.T)
        if np.linalg.eigvalsh(A_b)[0] > 0.0:  # positive definite (so is its diagonal, for _inv_scaled)
            A_inv = _inv_scaled(A_b)
            white = A_inv @ A @ A_inv
            white = 0.5 * (white + white.T)
    # K_t summed against the features: C (F, m, 12)
    JtWD = np.swapaxes(Ju, 1, 2) @ Du  # (n, m, 12)
    C = np.einsum("mp,npj,nf->fmj", A_inv, JtWD, features)
    var = np.concatenate([_prior_variances(templates[0]), _prior_variances(templates[1])])
    var = var * np.repeat(np.asarray(weights, dtype=np.float64), 6)
    cov_unit = np.einsum("fmj,j,fnj->mn", C, var, C)

    # residual columns of a unit prior (eq. A2): (n k, F * 12), scaled by sqrt(var)
    direct = np.einsum("nij,nf->nifj", Dw, features)  # (n, k, F, 12)
    fitted = np.einsum("nim,fmj->nifj", Jw, C)
    cols = ((direct - fitted) * np.sqrt(var)).reshape(n * k, -1)
    zf = z.reshape(-1)
    scale2 = 0.0
    z_rem = zf
    feature_ms = float(np.mean(np.sum(features**2, axis=1)))  # the features' mean energy per frame
    if float(np.max(var)) > 0.0:
        U, sv, _ = np.linalg.svd(cols, full_matrices=False)
        U = U[:, sv > sv[0] * 1e-8]
        u = U.T @ zf
        scale2, nu = _moment_scale(u, U.T @ cols)
        z_rem = zf - U @ u
        # A scale read from nu effective directions: the estimate's error over the estimated covariance is
        # F(3, nu)-like, whose mean is nu / (nu - 2) times the known-scale value (eq. A5); nu >= NU_MIN.
        # With the literature prior tied to the deforming cluster's residual (eq. A6) where that is more
        # cautious: a cluster that does not deform (a plate) says nothing about its rigid motion.
        big = int(np.argmax(np.asarray(weights, dtype=np.float64)))
        post2, nu_post = posterior_scale2(scale2, nu, prior_scale2(templates[big].shape[0], feature_ms))
        scale2 = max(t_widened(scale2, nu), t_widened(post2, nu_post))
    artefact = scale2 * cov_unit
    zr = z_rem.reshape(n, k)
    tau, window = _integrated_time(zr)
    bandwidth = int(min(max(2 * window, 1), n // 4 if n >= 8 else 1))
    scores = np.einsum("nim,ni->nm", Jw, zr) if weighted else np.einsum("nim,ni->nm", J, (Lw @ zr[..., None])[..., 0])
    omega = _hac(scores, bandwidth)
    hac = A_inv @ omega @ A_inv
    statistical = _floor(0.5 * (hac + hac.T), white)
    return ArtefactCovariance(
        statistical=statistical,
        artefact=0.5 * (artefact + artefact.T),
        scale=np.sqrt(scale2 * np.asarray(weights, dtype=np.float64)),
        tau=tau,
        bandwidth=bandwidth,
        cluster_motion=scale2 * feature_ms * var.reshape(2, 6),
    )
