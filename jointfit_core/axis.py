"""Axis of rotation of markers moving on coaxial circles (hinge joint).

Gamage & Lasenby (2002) section 3 (eq. 6-10), computed from per-marker
sufficient statistics, with the point's noise bias removed and linearised
covariances of the direction and the point.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import check_markers, check_noise_std, check_vector3
from .errors import InputError, NotIdentifiableError
from .moments import MarkerMoments, central_moments, moments_from_markers
from .results import AxisFit
from .sphere import NOISE_SNR_MIN, noise_bound_factor, psd_part, rounding_floor

__all__ = ["fit_axis", "axis_from_moments", "orient_direction", "PLANARITY_MAX", "DIRECTION_SD_MAX_DEG"]

FloatArray = NDArray[np.float64]

#: Out-of-plane scatter above this fraction of the smaller in-plane spread
#: (sqrt of lambda_0 / lambda_1 of ``A``) means the markers do not move in
#: parallel planes: the joint is not a clean hinge, or the arc is too short
#: for the noise. (Measured: knee 0.12, elbow in pronation 0.48, a clean
#: 60 deg hinge with 2 mm noise 0.21-0.23.)
PLANARITY_MAX = 0.3
#: With a known ``noise_std``, an out-of-plane rms above this multiple of it
#: means the joint is not a clean hinge.
NOISE_RATIO_MAX = 2.0
#: A direction whose largest standard deviation exceeds this (degrees) is
#: flagged as not identifiable.
DIRECTION_SD_MAX_DEG = 5.0
#: A point whose largest standard deviation exceeds this fraction of the
#: median marker radius is flagged.
POINT_SD_REL_MAX = 0.1
_SINGULAR_REL = 1e-10
_MAX_COMPENSATION = 0.5


def orient_direction(direction: FloatArray, reference: FloatArray | None) -> FloatArray:
    """Give an axis direction a deterministic sign.

    Parameters
    ----------
    direction : ndarray, shape (3,)
        Unit direction whose sign is arbitrary.
    reference : ndarray, shape (3,), optional
        The returned direction has a non-negative dot product with it. When
        None, the component of largest magnitude is made positive (ties go
        to the first such axis, x before y before z).

    Returns
    -------
    ndarray, shape (3,)
        ``direction`` or ``-direction``.
    """
    if reference is not None:
        dot = float(direction @ reference)
        return -direction if dot < 0.0 else direction
    k = int(np.argmax(np.abs(direction)))
    return -direction if direction[k] < 0.0 else direction


def fit_axis(
    markers: ArrayLike, *, noise_std: float | None = None, reference_direction: ArrayLike | None = None
) -> AxisFit:
    """Fit the axis of rotation of markers that move on coaxial circles.

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Marker positions (any length unit) in a frame in which the axis is
        fixed; NaN marks a missing marker, and each marker uses only its
        valid frames.
    noise_std : float, optional
        Marker noise standard deviation per coordinate, input units. None
        (default) estimates it from the out-of-plane residuals and removes
        the noise bias of the point; 0 gives the plain Gamage-Lasenby point.
    reference_direction : array_like, shape (3,), optional
        The returned direction points to the same side as this vector
        (non-negative dot product). When None, the direction's component of
        largest magnitude is positive. The sign is never left to the
        eigen-solver.

    Returns
    -------
    AxisFit
        ``point`` (the point of the axis nearest the centroid of the marker
        means), unit ``direction``, their covariances, the per-marker circle
        centres and radii, and the diagnostics. A motion that is not a clean
        hinge (markers leave their planes) or that determines the axis only
        weakly returns ``identifiable=False`` with a reason.

    Raises
    ------
    InputError
        Wrong shape, infinite values, all-NaN input or too few samples.
    NotIdentifiableError
        The markers did not move, or their motion spans less than a plane
        (the second eigenvalue of ``A`` within the rounding of the moment
        sums, :func:`jointfit_core.sphere.rounding_floor`).

    Notes
    -----
    **Direction**, eq. (6-9): ``A n = 0`` with
    ``A = 2 sum_p sum_k (v_pk - vbar_p)(v_pk - vbar_p)^T``; ``n`` is the
    eigenvector of the smallest eigenvalue ``lambda_0``. The noise variance
    is estimated as ``lambda_0 / (2 (D - 2))``, ``D = sum_p (n_p - 1)``
    (the out-of-plane scatter, two degrees of freedom used by ``n``).
    Noise adds the same multiple of ``I`` to every eigenvalue, so the
    direction needs no bias compensation.

    **Point**, eq. (5) solved with the pseudo-inverse on the plane
    orthogonal to ``n`` (as the paper prescribes), about the centroid of the
    marker means so that the minimum-norm solution is the point nearest it;
    ``A`` and ``b`` are bias-compensated as in :func:`fit_centre`.
    Circle centres and radii follow eq. (10).

    **Covariance** (first order): with ``A+`` the pseudo-inverse of the
    noise-free ``A`` on the plane, ``dn = -A+ (dA n)`` and
    ``dp = -A+ dg + n (p^T A+ dA n)`` (the second term keeps the point the
    nearest one to the centroid when ``n`` tilts), where
    ``cov(dA n) = 2 s2 A``, ``cov(dg) = 2 s2 sum_p (rho_p^2 + tau_p^2) A_p``
    and ``cov(dA n, dg) = -2 s2 sum_p tau_p A_p`` (``rho_p`` the circle
    radius, ``tau_p`` the marker plane's offset along the axis from the
    point). ``cov_direction`` takes ``A`` noise-free on the plane,
    ``A - 2 s2 D I``, its eigenvalues floored at half those of ``A`` (as
    for the point's compensation); ``cov_point`` takes the observed ``A_p``
    in all three terms, so that their joint covariance ``sum_p [[1,
    -tau_p], [-tau_p, rho_p^2 + tau_p^2]] (x) A_p`` is positive
    semi-definite. Both covariances scale with ``s2`` and, for a fixed range
    of motion, as ``1 / N``. ``cov_direction`` has rank 2 (no component along
    ``n``).

    **Verdict**: not a hinge when the out-of-plane scatter exceeds
    :data:`PLANARITY_MAX` of the in-plane spread (or, with ``noise_std``
    given, :data:`NOISE_RATIO_MAX` times it); range of motion too small when
    the smaller in-plane eigenvalue of ``A`` does not exceed the noise's
    share ``2 s2 D`` by ``NOISE_SNR_MIN`` times (``s2`` an upper confidence
    bound of the estimate, which has ``D - 2`` degrees of freedom, as in
    :func:`jointfit_core.sphere.fit_centre`), or when the direction's or the
    point's standard deviation exceeds its limit.
    """
    arr = check_markers(markers, name="markers")
    return axis_from_moments(moments_from_markers(arr), noise_std=noise_std, reference_direction=reference_direction)


def axis_from_moments(
    mom: MarkerMoments, *, noise_std: float | None = None, reference_direction: ArrayLike | None = None
) -> AxisFit:
    """Axis of rotation from per-marker sufficient statistics.

    Parameters
    ----------
    mom : MarkerMoments
        Running sums of the marker positions.
    noise_std, reference_direction
        As in :func:`fit_axis`.

    Returns
    -------
    AxisFit
        Identical to :func:`fit_axis` on the samples the sums were built from.
    """
    sigma_given = check_noise_std(noise_std)
    ref_dir = None if reference_direction is None else check_vector3(
        reference_direction, name="reference_direction", unit=True
    )
    cm = central_moments(mom)
    used = cm.used
    if not used.any():
        raise InputError("markers: no marker has two or more valid frames; an axis needs motion")
    dof_total = float(cm.dof[used].sum())
    if dof_total < 3.0:
        raise InputError(
            f"markers: too few valid samples: need at least P + 3 (here {int(used.sum()) + 3}) to fit an "
            f"axis and judge it, got {round(float(cm.n[used].sum()))}"
        )
    a_p = 2.0 * cm.m2
    a_mat = a_p.sum(axis=0)
    lam, vecs = np.linalg.eigh(a_mat)
    floor = rounding_floor(cm)
    if lam[-1] <= floor or lam[-1] <= 0.0:
        raise NotIdentifiableError("markers: the markers did not move, so the axis is undetermined")
    if lam[1] <= max(_SINGULAR_REL * lam[-1], floor):
        raise NotIdentifiableError(
            "markers: the markers moved along a line only; an axis needs each marker to trace an arc"
        )
    direction = orient_direction(vecs[:, 0], ref_dir)
    s2_est = max(float(lam[0]), 0.0) / (2.0 * (dof_total - 2.0))
    s2_comp = s2_est if sigma_given is None else sigma_given**2
    compensated = s2_comp > 0.0

    # Point: pseudo-inverse on the plane orthogonal to n, about the centroid.
    w_markers = used.astype(np.float64)
    centroid_rel = (cm.mean * w_markers[:, None]).sum(axis=0) / w_markers.sum()
    mean_c = cm.mean - centroid_rel  # marker means about the centroid
    plane = vecs[:, 1:]
    lam_plane = lam[1:]
    lam_j = np.maximum(lam_plane - 2.0 * s2_comp * dof_total, _MAX_COMPENSATION * lam_plane)
    b_vec = (cm.m3 + np.einsum("pij,pj->pi", a_p, mean_c)).sum(axis=0)
    if compensated:
        b_vec = b_vec - 2.0 * s2_comp * np.einsum("p,pi->i", cm.dof, mean_c)
    point_c = plane @ ((plane.T @ b_vec) / lam_j)  # orthogonal to n: nearest point to the centroid

    # Circles (eq. 10).
    tau = (mean_c - point_c) @ direction  # (P,) axial offset of each marker's plane
    circle_c = point_c[None, :] + tau[:, None] * direction[None, :]
    proj = np.eye(3) - np.outer(direction, direction)
    safe_n = np.where(used, cm.n, 1.0)
    off = (mean_c - circle_c) @ proj
    rho2 = np.einsum("ij,pji->p", proj, cm.m2) / safe_n + np.einsum("pi,pi->p", off, off)
    if compensated:
        rho2 = rho2 - 2.0 * s2_comp
    radii = np.where(used, np.sqrt(np.maximum(rho2, 0.0)), np.nan)
    rms = float(np.sqrt(max(float(lam[0]), 0.0) / (2.0 * float(cm.n[used].sum()))))

    # Linearised covariances (see Notes).
    a_pinv = (plane / lam_j) @ plane.T
    # Direction: cov(dA n) = 2 s2 A_sig, A_sig the noise-free in-plane scatter A - 2 s2 D I, its
    # eigenvalues floored like lam_j (a short, noisy arc can have an in-plane eigenvalue below the
    # noise estimate; unfloored, the covariance would be indefinite).
    lam_sig = np.maximum(lam_plane - 2.0 * s2_est * dof_total, _MAX_COMPENSATION * lam_plane)
    c11 = 2.0 * s2_est * (plane * lam_sig) @ plane.T
    # Point: the joint covariance of (dA n, dg) is sum_p K_p x A_p with K_p = [[1, -tau_p], [-tau_p,
    # rho_p^2 + tau_p^2]] (PSD); built from one set of per-marker scatters (the observed ones, as for dg,
    # rounding negatives clipped) it is PSD, and so is cov_point. Mixing in the compensated A_sig for
    # the dA n block would break that (its Schur complement can go negative when the noise is large).
    a_p_psd = psd_part(np.where(used[:, None, None], a_p, 0.0))
    c11_pt = 2.0 * s2_est * (proj @ a_p_psd.sum(axis=0) @ proj)
    r2_p = np.where(used, np.maximum(rho2, 0.0) + tau * tau, 0.0)
    c22 = 2.0 * s2_est * np.einsum("p,pij->ij", r2_p, a_p_psd)
    c12 = -2.0 * s2_est * np.einsum("p,pij->ij", np.where(used, tau, 0.0), a_p_psd)
    cov_dir = a_pinv @ c11 @ a_pinv
    j1 = np.outer(direction, point_c) @ a_pinv
    j2 = -a_pinv
    cov_point = j1 @ c11_pt @ j1.T + j2 @ c22 @ j2.T + j1 @ c12 @ j2.T + j2 @ c12.T @ j1.T
    cov_dir = 0.5 * (cov_dir + cov_dir.T)
    cov_point = 0.5 * (cov_point + cov_point.T)

    sigma_out = float(np.sqrt(s2_est))
    # The in-plane motion is judged against an upper confidence bound of the noise (the estimate has
    # D - 2 degrees of freedom), at least the stated noise, never below the rounding of A.
    s2_bound = s2_est * noise_bound_factor(dof_total - 2.0) if s2_est > 0.0 else 0.0
    if sigma_given is not None:
        s2_bound = max(s2_bound, sigma_given**2)
    noise = max(2.0 * s2_bound * dof_total, floor)
    identifiable, reason = _verdict(lam, cov_dir, cov_point, radii[used], sigma_out, sigma_given, noise)
    return AxisFit(
        point=point_c + centroid_rel + mom.ref,
        direction=direction,
        cov_point=cov_point,
        cov_direction=cov_dir,
        circle_centres=np.where(used[:, None], circle_c + centroid_rel + mom.ref, np.nan),
        radii=radii,
        rms=rms,
        n_frames=round(mom.n_frames),
        identifiable=identifiable,
        reason=reason,
        noise_std=float(np.sqrt(s2_comp)),
        bias_compensated=bool(compensated),
    )


def _verdict(
    lam: FloatArray,
    cov_dir: FloatArray,
    cov_point: FloatArray,
    radii: FloatArray,
    sigma_out: float,
    sigma_given: float | None,
    noise: float,
) -> tuple[bool, str]:
    """Identifiability verdict of an axis fit and a reason a person can act on.

    ``noise`` bounds the noise's contribution to each eigenvalue of ``A``
    (as in :func:`jointfit_core.sphere.centre_from_moments`).
    """
    if sigma_given is not None and sigma_given > 0 and sigma_out > NOISE_RATIO_MAX * sigma_given:
        return False, (
            f"not a clean hinge: the markers leave their planes of rotation by {sigma_out:.3g} rms, "
            f"more than {NOISE_RATIO_MAX:g} x the stated noise ({sigma_given:.3g}); the joint also rotates "
            "about other axes (e.g. pronation, abduction), so no single axis describes it"
        )
    planarity = float(np.sqrt(max(lam[0], 0.0) / lam[1]))
    if planarity > PLANARITY_MAX:
        return False, (
            f"not a clean hinge: the markers leave their planes of rotation (out-of-plane scatter is "
            f"{planarity:.0%} of the in-plane spread, limit {PLANARITY_MAX:.0%}); either the joint also "
            "rotates about other axes (e.g. pronation, abduction) or the arc is too short for the noise: "
            "flex through a larger range, and check the motion is a hinge"
        )
    if lam[1] < (1.0 + NOISE_SNR_MIN) * noise:
        return False, (
            "range of motion too small: the markers' arcs are hardly larger than the noise (or, with few "
            "samples, than what the noise could be); flex the joint through a larger range or record more frames"
        )
    sd_dir = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov_dir)[-1], 0.0))))
    if sd_dir > DIRECTION_SD_MAX_DEG:
        return False, (
            f"range of motion too small: the axis direction's standard deviation is {sd_dir:.1f} deg "
            f"(limit {DIRECTION_SD_MAX_DEG:g} deg); flex the joint through a larger range"
        )
    radius = float(np.median(radii)) if radii.size else 0.0
    sd_point = float(np.sqrt(max(np.linalg.eigvalsh(cov_point)[-1], 0.0)))
    if radius > 0 and sd_point > POINT_SD_REL_MAX * radius:
        return False, (
            f"range of motion too small: the axis position's standard deviation ({sd_point:.3g}) exceeds "
            f"{POINT_SD_REL_MAX:.0%} of the median marker radius ({radius:.3g}); flex through a larger range"
        )
    return True, ""
