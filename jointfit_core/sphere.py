"""Centre of rotation of markers moving on concentric spheres (ball joint).

Gamage & Lasenby (2002) eq. (5), computed from per-marker sufficient
statistics (:mod:`jointfit_core.moments`), with the noise bias of ``A`` and
``b`` removed in the manner of Halvorsen (2003) and a linearised (sandwich)
covariance.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import gammaincinv

from .checks import check_markers, check_noise_std
from .errors import InputError, NotIdentifiableError
from .moments import CentralMoments, MarkerMoments, central_moments, moments_from_markers
from .results import CentreFit

__all__ = [
    "fit_centre",
    "centre_from_moments",
    "NOISE_SNR_MIN",
    "SD_REL_MAX",
    "SINGULAR_REL",
    "NOISE_BOUND_ALPHA",
    "ROUNDING_ULPS",
    "noise_bound_factor",
    "psd_part",
    "rounding_floor",
]

FloatArray = NDArray[np.float64]

#: A direction of ``A`` whose signal spread is below this multiple of the
#: noise spread is "not excited" by the motion (the compensation is also
#: limited there, so that it stays stable).
NOISE_SNR_MIN = 3.0
#: A centre whose largest standard deviation exceeds this fraction of the
#: median marker radius is flagged as not identifiable.
SD_REL_MAX = 0.1
#: Eigenvalues of ``A`` below this fraction of the largest count as zero.
SINGULAR_REL = 1e-10
#: The verdict judges the motion against an upper confidence bound of the
#: noise variance (:func:`noise_bound_factor`) that the truth exceeds with
#: this probability: the residual noise estimate has only ``D - 3`` degrees
#: of freedom (one, with ``P + 4`` samples), and a chance underestimate must
#: not make noise look like motion.
NOISE_BOUND_ALPHA = 1e-3
#: Eigenvalues of ``A`` within this many units of rounding of the moment
#: sums (:func:`rounding_floor`) are indistinguishable from zero.
ROUNDING_ULPS = 8.0
#: Bias compensation never removes more than this fraction of an eigenvalue.
_MAX_COMPENSATION = 0.5
#: Fixed-point iterations between the noise estimate and the compensated centre.
_NOISE_ITERATIONS = 4


def fit_centre(markers: ArrayLike, *, noise_std: float | None = None) -> CentreFit:
    """Fit the centre of rotation of markers that move on concentric spheres.

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Marker positions (any length unit; results are in the same unit) in a
        frame in which the centre is fixed (e.g. child markers expressed in
        the parent segment's frame). NaN marks a missing marker; each marker
        uses only its valid frames.
    noise_std : float, optional
        Standard deviation of the marker noise per coordinate, input units.
        ``None`` (default) estimates it from the residuals and removes the
        noise bias; ``0`` gives the plain Gamage-Lasenby solution; a positive
        value removes the bias of that noise level.

    Returns
    -------
    CentreFit
        ``centre``, ``cov``, ``radii`` and the diagnostics. When the motion
        only weakly determines the centre, ``identifiable`` is False and
        ``reason`` says which movement is missing.

    Raises
    ------
    InputError
        Wrong shape, infinite values, all-NaN input, or fewer valid samples
        than ``P + 4`` (no residual degree of freedom is left to judge the
        fit).
    NotIdentifiableError
        The motion cannot determine the centre at all (``A`` is singular,
        or its smallest eigenvalue is within the rounding of the moment
        sums, :func:`rounding_floor`: markers that did not move, or
        noise-free rotation about one axis).

    See Also
    --------
    centre_from_moments : the same fit from running sums (used online).

    Notes
    -----
    Implements eq. (5) of Gamage & Lasenby (2002), ``A m = b`` with, per
    marker p and its valid frames k (the sums weighted by frame, so that the
    solution minimises their cost eq. (1) also with missing samples)::

        A = 2 sum_p sum_k (v_pk - vbar_p)(v_pk - vbar_p)^T
        b = sum_p sum_k (v_pk - vbar_p) |v_pk|^2

    **Bias compensation** (Halvorsen 2003): isotropic noise of variance
    ``s2`` per coordinate adds ``2 s2 (n_p - 1) I`` to the expected ``A_p``
    and ``2 s2 (n_p - 1) vbar_p`` to ``b_p``; both are subtracted. ``s2`` is
    estimated from the algebraic residuals ``d = |v - m|^2 - r_p^2`` at the
    compensated centre (iterated from the plain solution), whose expectation
    is ``sum_p (n_p - 1)(4 s2 r_p^2 - 6 s2^2)`` (corrected for the 3 fitted
    coordinates); at the plain solution, which the noise pulls toward the
    markers, they understate the noise when still frames fill ``A``. To stay stable when
    ``A`` is poorly conditioned, the compensation removes at most half of
    any eigenvalue of ``A``; such directions are flagged as not excited.

    **Covariance** (sandwich / delta method): the estimating equation
    ``g(m) = A_c m - b_c`` has, to first order in the noise, variance
    ``2 s2 sum_p R_p^2 A_p`` (``R_p`` the sphere radius, ``A_p`` the
    noise-free scatter of marker p), so ``cov = A_c^-1 (2 s2 sum_p R_p^2 A_p)
    A_c^-1``, plus the term of the estimated ``s2`` when it is used for the
    compensation. ``s2`` in the covariance is always the residual estimate,
    so model error (skin motion) widens it. The covariance scales with
    ``s2`` and, for a fixed range of motion, as ``1 / N``; it grows as the
    range of motion shrinks (``A`` scales with the square of the arc
    length).

    **Verdict**: each eigenvalue of ``A`` must exceed the noise's share
    ``2 s2 D`` by :data:`NOISE_SNR_MIN` times, with ``s2`` an upper
    confidence bound of the residual estimate (``D - 3`` degrees of freedom,
    :func:`noise_bound_factor`; at least the stated ``noise_std``) and
    ``2 s2 D`` never below the rounding floor of ``A``, so that few samples
    or a noise estimate that cancels to zero do not make noise or rounding
    look like motion. The centre's largest standard deviation must also stay
    below :data:`SD_REL_MAX` of the median marker radius.
    """
    arr = check_markers(markers, name="markers")
    return centre_from_moments(moments_from_markers(arr), noise_std=noise_std)


def psd_part(mats: FloatArray) -> FloatArray:
    """The positive semi-definite part of symmetric matrices, shape (..., 3, 3): negative eigenvalues set to 0.

    A scatter matrix is PSD, but one computed from shifted raw sums (far from
    the origin, little motion) can lose its small eigenvalues to cancellation
    and come out slightly indefinite; the covariances built from it must not.
    """
    sym = 0.5 * (mats + np.swapaxes(mats, -1, -2))
    lam, vecs = np.linalg.eigh(sym)
    negative = np.asarray((lam < 0.0).any(axis=-1), dtype=bool)
    if not negative.any():
        return sym
    clipped = (vecs * np.maximum(lam, 0.0)[..., None, :]) @ np.swapaxes(vecs, -1, -2)
    out: FloatArray = np.where(negative[..., None, None], clipped, sym)
    return out


def noise_bound_factor(nu: float) -> float:
    """Factor from a variance estimate to its upper confidence bound.

    Parameters
    ----------
    nu : float
        Degrees of freedom of the estimate (``s2_hat ~ s2 chi2_nu / nu``).

    Returns
    -------
    float
        ``nu / chi2_nu^-1(NOISE_BOUND_ALPHA)``: ``s2 <= factor * s2_hat`` with
        probability ``1 - NOISE_BOUND_ALPHA`` (inf for ``nu <= 0``). About
        6e5 for one degree of freedom, 1.3 for 400, 1 in the limit.
    """
    if not nu > 0.0:
        return float("inf")
    q = 2.0 * float(gammaincinv(0.5 * nu, NOISE_BOUND_ALPHA))
    return nu / q if q > 0.0 else float("inf")


def rounding_floor(cm: CentralMoments) -> float:
    """Eigenvalue of ``A = 2 sum_p m2_p`` that rounding of the moment sums alone can produce.

    Parameters
    ----------
    cm : CentralMoments

    Returns
    -------
    float
        ``ROUNDING_ULPS * eps * sqrt(n_max) * K`` with ``K = 2 sum_p (tr m2_p
        + n_p |mean_p - c|^2)`` (c the mean of all samples): the scale of the
        raw sums about the data's mean from which the central moments are
        obtained by cancellation, and ``sqrt(n_max)`` for the accumulated
        rounding of long sums. Noise-free markers that turn about a single
        axis have a zero eigenvalue that comes out as rounding of about
        ``eps K``; a real motion of ``theta`` radians gives ``K theta^2``.
    """
    n = np.where(cm.used, cm.n, 0.0)
    total = float(n.sum())
    if total <= 0.0:
        return 0.0
    c = (n[:, None] * cm.mean).sum(axis=0) / total
    d = cm.mean - c
    k = 2.0 * float((np.einsum("pii->p", cm.m2) + n * np.einsum("pi,pi->p", d, d))[cm.used].sum())
    return ROUNDING_ULPS * float(np.finfo(np.float64).eps) * float(np.sqrt(max(float(n.max()), 1.0))) * k


def _sphere_residuals(cm: CentralMoments, centre_rel: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per-marker residual sums and mean squared distances at a centre.

    Returns ``(ss_p, r2_p)``: the sum of squared algebraic residuals
    ``(|v - m|^2 - r_p^2)^2`` with ``r_p^2`` the mean of ``|v - m|^2`` (eq. 2),
    and that ``r_p^2``, for each marker.
    """
    u = cm.used
    c = centre_rel[None, :] - cm.mean  # centre relative to each marker's mean
    tr2 = np.einsum("pii->p", cm.m2)
    safe_n = np.where(u, cm.n, 1.0)
    ss_p = cm.m4 - tr2 * tr2 / safe_n - 4.0 * np.einsum("pi,pi->p", c, cm.m3)
    ss_p = ss_p + 4.0 * np.einsum("pi,pij,pj->p", c, cm.m2, c)
    ss_p = np.where(u, np.maximum(ss_p, 0.0), 0.0)
    r2 = np.where(u, tr2 / safe_n + np.einsum("pi,pi->p", c, c), 0.0)
    return ss_p, r2


def _noise_from_residuals(cm: CentralMoments, ss_fit: float, r2: FloatArray, n_fitted: int) -> float:
    """Noise variance per coordinate from the algebraic residual sum at a fitted centre.

    Solves ``6 D s2^2 - 4 T s2 + SS D / (D - n_fitted) = 0`` for its smaller
    root, where ``D = sum_p (n_p - 1)`` and ``T = sum_p (n_p - 1) r_p^2``:
    to first order the residual ``d = 2 (u - m).e + |e|^2 - mean`` has
    variance ``4 s2 R^2 + 6 s2^2`` with ``R^2 = r^2 - 3 s2``.
    """
    dof_total = float(cm.dof[cm.used].sum())
    t_sum = float((cm.dof * r2)[cm.used].sum())
    if t_sum <= 0.0:
        return 0.0
    ss = ss_fit * dof_total / (dof_total - n_fitted)
    disc = 16.0 * t_sum * t_sum - 24.0 * dof_total * ss
    s2 = (4.0 * t_sum - np.sqrt(max(disc, 0.0))) / (12.0 * dof_total)
    return max(float(s2), 0.0)


def _weak_direction_reason(direction: FloatArray, what: str) -> str:
    d = np.round(direction * np.sign(direction[np.argmax(np.abs(direction))]), 2)
    return (
        f"{what}: the motion is nearly a rotation about a single axis (direction ~ {d.tolist()}), "
        "which leaves the centre undetermined along that axis; also rotate the segment about a second, "
        "different axis (e.g. abduction as well as flexion)"
    )


def centre_from_moments(mom: MarkerMoments, *, noise_std: float | None = None) -> CentreFit:
    """Centre of rotation from per-marker sufficient statistics.

    Parameters
    ----------
    mom : MarkerMoments
        Running sums of the marker positions (see
        :func:`jointfit_core.moments.moments_from_markers`).
    noise_std : float, optional
        As in :func:`fit_centre`.

    Returns
    -------
    CentreFit
        Identical to :func:`fit_centre` on the samples the sums were built
        from.

    Raises
    ------
    InputError, NotIdentifiableError
        As in :func:`fit_centre`.
    """
    sigma_given = check_noise_std(noise_std)
    cm = central_moments(mom)
    used = cm.used
    if not used.any():
        raise InputError("markers: no marker has two or more valid frames; a centre needs motion")
    dof_total = float(cm.dof[used].sum())
    if dof_total < 4.0:
        raise InputError(
            f"markers: too few valid samples: need at least P + 4 (here {int(used.sum()) + 4}) "
            f"to fit a centre and judge it, got {round(float(cm.n[used].sum()))}"
        )
    a_p = 2.0 * cm.m2
    a_mat = a_p.sum(axis=0)
    b_vec = (cm.m3 + np.einsum("pij,pj->pi", a_p, cm.mean)).sum(axis=0)
    lam, vecs = np.linalg.eigh(a_mat)
    if lam[-1] <= 0.0:
        raise NotIdentifiableError("markers: the markers did not move, so the centre is undetermined")
    floor = rounding_floor(cm)
    if lam[-1] <= floor:
        raise NotIdentifiableError(
            "markers: the markers did not move (their motion is at the rounding level of the coordinates), "
            "so the centre is undetermined"
        )
    if lam[0] <= max(SINGULAR_REL * lam[-1], floor):
        raise NotIdentifiableError(_weak_direction_reason(vecs[:, 0], "A is singular"))

    centre_plain = vecs @ ((vecs.T @ b_vec) / lam)
    # The plain solution minimises the algebraic residuals (eq. 1) and is pulled toward the markers by
    # the noise, so its minimum understates the noise: by 2 d^T A d for the pull d, which is most of the
    # residual when still frames fill the window (2400 still frames and 60 moving ones: the noise read
    # 7 % low and 4 of 60 centres came out identifiable with mean e/3 15). The noise is read at the
    # compensated centre, iterated from the plain one.
    dof_mean = np.einsum("p,pi->i", cm.dof, cm.mean)
    centre_rel = centre_plain
    lam_j = lam
    s2_est = 0.0
    for _ in range(_NOISE_ITERATIONS):
        ss_c, r2_c = _sphere_residuals(cm, centre_rel)
        s2_est = _noise_from_residuals(cm, float(ss_c.sum()), r2_c, 3)
        s2_comp = s2_est if sigma_given is None else sigma_given**2
        if s2_comp <= 0.0:
            break
        lam_j = np.maximum(lam - 2.0 * s2_comp * dof_total, _MAX_COMPENSATION * lam)
        centre_rel = vecs @ ((vecs.T @ (b_vec - 2.0 * s2_comp * dof_mean)) / lam_j)
    s2_comp = s2_est if sigma_given is None else sigma_given**2
    compensated = s2_comp > 0.0

    # Radii and residuals at the final centre.
    ss_p, r2 = _sphere_residuals(cm, centre_rel)
    used_r2 = used & (r2 > 0)
    radius2 = np.maximum(r2 - 3.0 * s2_comp, 0.0) if compensated else r2
    radii = np.where(used, np.sqrt(radius2), np.nan)
    radial_ss = np.where(used_r2, ss_p / (4.0 * np.where(used_r2, r2, 1.0)), 0.0)
    rms = float(np.sqrt(radial_ss.sum() / max(float(cm.n[used].sum()), 1.0)))

    # Sandwich covariance with the residual noise estimate. To second order
    # the estimating equation's noise has variance
    # 4 s2 sum R^2 x x^T + 4 s2^2 sum (R^2 I + (v - m)(v - m)^T); the
    # observed scatter A_p already carries the 4 s2^2 R^2 I part.
    # Every term is PSD, and so is the covariance, given PSD scatters: those from shifted sums can lose
    # their small eigenvalues to cancellation (far from the origin, little motion), so they are clipped.
    c = centre_rel[None, :] - cm.mean
    a_p_psd = psd_part(a_p)
    big_r2 = np.where(used, np.maximum(r2 - 3.0 * s2_est, 0.0), 0.0)
    meat = 2.0 * s2_est * np.einsum("p,pij->ij", big_r2, a_p_psd)
    spread = 0.5 * a_p_psd.sum(axis=0) + np.einsum("p,pi,pj->ij", cm.n * used, c, c)
    meat = meat + 4.0 * s2_est**2 * spread
    if compensated and sigma_given is None:
        k = -2.0 * (dof_total * centre_rel - dof_mean)
        meat = meat + (2.0 * s2_est**2 / (dof_total - 3.0)) * np.outer(k, k)
    j_inv = (vecs / lam_j) @ vecs.T
    cov = j_inv @ meat @ j_inv
    cov = 0.5 * (cov + cov.T)

    # The verdict's noise: an upper confidence bound of the residual estimate (it has D - 3 degrees of
    # freedom), at least the stated noise, and never below the rounding of A (a noise estimate that
    # cancels to zero is not infinite precision).
    factor = noise_bound_factor(dof_total - 3.0)
    s2_bound = s2_est * factor if s2_est > 0.0 else 0.0
    if sigma_given is not None:
        s2_bound = max(s2_bound, sigma_given**2)
    noise = max(2.0 * s2_bound * dof_total, floor)
    identifiable, reason = _verdict(lam, vecs, noise, cov, radii[used])
    return CentreFit(
        centre=centre_rel + mom.ref,
        cov=cov,
        radii=radii,
        rms=rms,
        n_frames=round(mom.n_frames),
        identifiable=identifiable,
        reason=reason,
        noise_std=float(np.sqrt(s2_comp if sigma_given is not None else s2_est)),
        bias_compensated=bool(compensated),
    )


def _verdict(
    lam: FloatArray, vecs: FloatArray, noise: float, cov: FloatArray, radii: FloatArray
) -> tuple[bool, str]:
    """Identifiability verdict of a centre fit and a reason a person can act on.

    ``noise`` bounds the noise's contribution to each eigenvalue of ``A``
    (``2 s2 D`` with ``s2`` the bound of the noise variance, at least the
    rounding floor of ``A``).
    """
    snr = (lam - noise) / noise if noise > 0 else np.full(3, np.inf)
    weak = np.flatnonzero(snr < NOISE_SNR_MIN)
    sd_max = float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))
    radius = float(np.median(radii)) if radii.size else 0.0
    if weak.size >= 2:
        return False, (
            "range of motion too small: the marker motion is hardly larger than the noise in two or more "
            "directions; move the segment through a larger range, in at least two planes"
        )
    if weak.size == 1:
        return False, _weak_direction_reason(vecs[:, int(weak[0])], "centre poorly determined")
    if radius > 0 and sd_max > SD_REL_MAX * radius:
        return False, (
            f"range of motion too small: the centre's standard deviation ({sd_max:.3g}) exceeds "
            f"{SD_REL_MAX:.0%} of the median marker radius ({radius:.3g}); move through a larger range "
            "or record more frames"
        )
    return True, ""
