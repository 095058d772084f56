"""Joints from minimal marker sets (Pham, Ayusawa, Kubota & Nakamura).

Ball joints from two markers on each link (the paper's S22, sections IV-C and
V-A) or three plus one (S31, IV-A), and hinges from two markers on one link
and one on the other (R21, III-A), as separable nonlinear least squares on
*distance models*:

* **Ball joint.** The centre ``J`` is rigid on both links, so its distance
  ``a_k = |J_t - X_k,t|`` to every marker ``k`` (parent markers first, then
  child markers) is the same in every frame ``t``. With ``M = p + q`` markers
  the per-frame residuals ``|J_t - X_k,t| - a_k`` (``M`` values, ``J_t`` a
  per-frame nuisance of 3) leave ``M - 3`` degrees of freedom per frame: one
  for (2, 2) and (3, 1), none for (2, 1), which is why that case is not
  identifiable (section IV-B).
* **Hinge.** The axis is rigid on both links, so every marker keeps its
  distance ``rho_k`` from the axis and its axial position ``h_k - h_0``
  relative to marker 0. With the per-frame axis line as nuisance (4
  parameters) the ``2 M - 1`` residuals leave ``2 M - 5`` degrees of freedom
  per frame: one for (2, 1), none for (1, 1) (section III-B).

The constants are found by :func:`scipy.optimize.least_squares` (bounded
trust region) over the constants only; for each trial the per-frame nuisances
are solved in closed form and polished by a few batched Gauss-Newton steps
(variable projection; the Jacobian is the Kaufman one, the derivative of the
projected residual). The start comes from the paper's closed forms: the
linear system of section IV-C for S22, a sphere fit in the frame of a link
with 3 markers for S31, and eq. (7)-(13) for R21. The covariance of the
constants is Gauss-Newton: ``sigma^2 (J^T J)^-1`` with ``sigma^2`` the
residual variance per degree of freedom.

Frames
------
Nothing here needs a body frame. The fits report the constants (distances)
and, per frame, the centre or axis in the world frame of the input markers.
For a link with at least two markers the centre is also given in its *pair
frame*: the axial coordinate along the line from its marker 0 towards its
marker 1 (origin at marker 0) and the radial distance from that line -- the
paper's ``(d, r)``. The hinge is also given as the paper's Denavit-Hartenberg
constants ``(d, r, alpha, l, rho)`` relative to the pair.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from .checks import check_markers, valid_mask
from .errors import InputError, NotIdentifiableError
from .identifiability import check_marker_counts
from .pose import poses_from_markers, template_from_markers
from .results import MinimalAxisFit, MinimalCentreFit
from .sphere import fit_centre

__all__ = [
    "fit_centre_minimal",
    "fit_axis_minimal",
    "s22_closed_form",
    "r21_closed_form",
    "SD_REL_MAX",
    "DIRECTION_SD_MAX_DEG",
    "AMBIGUITY_CHI2",
    "KAPPA_MAX",
    "HINT_MAX_DEG",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: A centre (axis point) whose standard deviation exceeds this fraction of
#: the typical marker distance (lever arm) is flagged as not identifiable.
SD_REL_MAX = 0.1
#: A hinge direction whose typical per-frame standard deviation exceeds this
#: many degrees is flagged as not identifiable.
DIRECTION_SD_MAX_DEG = 5.0
#: Two hinge solutions whose costs differ by less than this many residual
#: variances fit the data equally well (a likelihood-ratio threshold).
AMBIGUITY_CHI2 = 30.0
#: Frames whose own centre (axis point) has a standard deviation above this
#: fraction of the median marker distance are not used for the constants:
#: there the linearisation (and the second-order bias correction) fails.
KAPPA_MAX = 0.02
#: With an ``axis_hint``, a hinge whose per-frame directions are on average
#: more than this many degrees from the hint is flagged as not identifiable.
HINT_MAX_DEG = 45.0
#: Gauss-Newton steps of the per-frame nuisance solves.
_INNER_STEPS = 10
_MAX_NFEV = 200
_SUBSAMPLE = 200
_MIN_KEEP = 0.2
_BIAS_STEPS = 1
_MIN_FRAMES = 10
#: The constants are "not determined at all" when the normal matrix's smallest
#: eigenvalue is below this fraction of its largest (numerically singular).
_SINGULAR_REL = 1e-14
#: Medians of chi-square laws with 1..6 degrees of freedom.
_CHI2_MEDIAN = {1: 0.4549, 2: 1.3863, 3: 2.3660, 4: 3.3567, 5: 4.3515, 6: 5.3481}
_TINY = 1e-12


# --------------------------------------------------------------------------- checks


def _check_pair_of_links(parent: ArrayLike, child: ArrayLike, kind: str) -> tuple[FloatArray, FloatArray]:
    """Checked (N, p, 3) and (N, q, 3) float64 arrays with the same N and identifiable counts."""
    yp = check_markers(parent, name="parent")
    yc = check_markers(child, name="child")
    if yp.shape[0] != yc.shape[0]:
        raise InputError(
            f"parent, child: expected the same number of frames, got {yp.shape[0]} (parent) and {yc.shape[0]} (child)"
        )
    check_marker_counts(kind, yp.shape[1], yc.shape[1])
    return yp, yc


def _used_frames(X: FloatArray, min_frames: int, what: str) -> BoolArray:
    """Frames in which every marker is visible; at least ``min_frames`` of them."""
    used = valid_mask(X).all(axis=1)
    if int(used.sum()) < min_frames:
        raise InputError(
            f"parent, child: expected at least {min_frames} frames in which all {X.shape[1]} markers are visible "
            f"({what}), got {int(used.sum())}"
        )
    return np.asarray(used, dtype=bool)


def _check_hint(axis_hint: ArrayLike | None, n_frames: int) -> FloatArray | None:
    """``axis_hint`` as unit vectors of shape (N, 3), or None."""
    if axis_hint is None:
        return None
    try:
        h = np.array(axis_hint, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"axis_hint: expected a 3-vector or an (N, 3) array, got {axis_hint!r}") from None
    if h.shape == (3,):
        h = np.broadcast_to(h, (n_frames, 3)).copy()
    if h.shape != (n_frames, 3):
        raise InputError(f"axis_hint: expected shape (3,) or ({n_frames}, 3), got {h.shape}")
    if not np.isfinite(h).all():
        raise InputError("axis_hint: expected finite values, got NaN or inf")
    norm = np.linalg.norm(h, axis=1)
    if np.any(norm == 0.0):
        raise InputError("axis_hint: expected non-zero directions")
    out: FloatArray = h / norm[:, None]
    return out


# --------------------------------------------------------------------------- small geometry


def _unit(v: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit vectors along the last axis and the norms."""
    n = np.linalg.norm(v, axis=-1)
    return v / np.maximum(n, _TINY)[..., None], n


def _perp_basis(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors (..., 3) completing unit ``n`` to a right-handed orthonormal basis (b1, b2, n)."""
    a = np.zeros_like(n)
    idx = np.argmin(np.abs(n), axis=-1)
    np.put_along_axis(a, idx[..., None], 1.0, axis=-1)
    b1, _ = _unit(np.cross(n, a))
    b2 = np.cross(n, b1)
    return b1, b2


def _solve3(A: FloatArray, b: FloatArray) -> FloatArray:
    """Solve batched symmetric 3x3 systems ``A x = b`` (..., 3, 3), (..., 3) by cofactors (fast when many)."""
    a00, a01, a02 = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    a11, a12, a22 = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    det = np.where(det != 0, det, _TINY)
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out: FloatArray = np.stack(
        [c00 * b0 + c01 * b1 + c02 * b2, c01 * b0 + c11 * b1 + c12 * b2, c02 * b0 + c12 * b1 + c22 * b2], axis=-1
    ) / det[..., None]
    return out


def _sym_inv(A: FloatArray) -> FloatArray:
    """Inverse of symmetric positive semi-definite matrices (...), eigenvalues floored at 1e-12 of the largest."""
    A = 0.5 * (A + np.swapaxes(A, -1, -2))
    lam, V = np.linalg.eigh(A)
    top = np.max(lam, axis=-1, keepdims=True)
    lam = np.maximum(lam, np.where(top > 0, 1e-12 * top, 1.0))
    out: FloatArray = (V / lam[..., None, :]) @ np.swapaxes(V, -1, -2)
    return out


def _max_sd(cov: FloatArray) -> FloatArray:
    """Largest standard deviation of each covariance (...)."""
    lam = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    out: FloatArray = np.sqrt(np.maximum(lam[..., -1], 0.0))
    return out


def _frame_sd(G: FloatArray, s2: float) -> FloatArray:
    """Largest per-frame standard deviation of the nuisance point, ``sqrt(s2 / lambda_min(G^T G))`` (N,)."""
    lam = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", G[..., :3], G[..., :3]))
    out: FloatArray = np.sqrt(s2 / np.maximum(lam[:, 0], _TINY))
    return out


def _rigid_noise_var(links: list[FloatArray]) -> float:
    """Marker noise variance per coordinate from the spread of the intra-link marker distances.

    For isotropic noise ``sigma^2`` the distance between two markers of a rigid
    link varies with variance ``2 sigma^2`` (to first order); the sample
    variances of all intra-link distances are pooled. 0 when no link has 2
    markers. ``links``: arrays (N, k, 3) of complete frames.
    """
    ss, dof = 0.0, 0
    for y in links:
        for i in range(y.shape[1]):
            for j in range(i + 1, y.shape[1]):
                length = np.linalg.norm(y[:, i] - y[:, j], axis=1)
                ss += float(np.sum((length - length.mean()) ** 2))
                dof += length.size - 1
    return ss / (2.0 * dof) if dof > 0 else 0.0


def _pair_coordinates(a0: float, a1: float, length: float, cov2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(axial, radial) of a point at distances a0, a1 from two markers ``length`` apart, with covariance."""
    axial = (a0 * a0 - a1 * a1 + length * length) / (2.0 * length)
    radial = float(np.sqrt(max(a0 * a0 - axial * axial, 0.0)))
    jac = np.array(
        [
            [a0 / length, -a1 / length],
            [(a0 - axial * a0 / length) / max(radial, _TINY), (axial * a1 / length) / max(radial, _TINY)],
        ]
    )
    return np.array([axial, radial]), jac @ cov2 @ jac.T


# --------------------------------------------------------------------------- variable projection driver


@dataclass(frozen=True)
class _Inner:
    """Per-frame nuisance solution at given constants (whitened residuals and Jacobians)."""

    r: FloatArray  # (N, m) whitened residuals
    G: FloatArray  # (N, m, k) whitened Jacobian w.r.t. the nuisance (tangent coordinates)
    state: tuple[FloatArray, ...]  # the nuisances (J) or (c, n)


def _projector(G: FloatArray) -> FloatArray:
    """``I - G (G^T G)^-1 G^T`` per frame (N, m, m)."""
    GtG_inv = _sym_inv(np.swapaxes(G, -1, -2) @ G)
    P: FloatArray = np.eye(G.shape[1]) - G @ GtG_inv @ np.swapaxes(G, -1, -2)
    return P


def _varpro(
    inner: Callable[[FloatArray], _Inner],
    whiten: FloatArray,
    x0: FloatArray,
    lower: FloatArray,
    max_nfev: int = _MAX_NFEV,
) -> tuple[FloatArray, _Inner]:
    """Minimise the sum of squared projected residuals over the constants ``x``.

    Residual ``r(x, nu(x))`` with ``nu`` the per-frame nuisance; the Jacobian of
    each residual w.r.t. the constants is ``-whiten`` (each raw residual is
    ``f - x_j`` for its own constant), projected off the nuisance directions.
    """
    cache: dict[bytes, _Inner] = {}

    def solve(x: FloatArray) -> _Inner:
        key = np.asarray(x, dtype=np.float64).tobytes()
        if key not in cache:
            if len(cache) > 4:
                cache.clear()
            cache[key] = inner(np.asarray(x, dtype=np.float64))
        return cache[key]

    def fun(x: FloatArray) -> FloatArray:
        out: FloatArray = solve(x).r.ravel()
        return out

    def jac(x: FloatArray) -> FloatArray:
        sol = solve(x)
        J = -_projector(sol.G) @ whiten  # (N, m, m)
        out: FloatArray = J.reshape(-1, J.shape[-1])
        return out

    finite = np.isfinite(lower)
    x0 = np.where(finite, np.maximum(x0, np.where(finite, lower, 0.0) * (1.0 + 1e-9) + 1e-12), x0)
    res = least_squares(
        fun,
        x0,
        jac=jac,
        bounds=(lower, np.full_like(lower, np.inf)),
        method="trf",
        x_scale="jac",
        ftol=1e-10,
        xtol=1e-10,
        gtol=1e-10,
        max_nfev=max_nfev,
    )
    x = np.asarray(res.x, dtype=np.float64)
    return x, inner(x)


def _normal_matrix(sol: _Inner, whiten: FloatArray) -> FloatArray:
    """``sum_t (P_t W^-1/2)^T (P_t W^-1/2)``: the Gauss-Newton normal matrix of the constants."""
    J = _projector(sol.G) @ whiten
    H: FloatArray = np.einsum("nki,nkj->ij", J, J)
    return H


def _bias_correction(
    resolve: Callable[[FloatArray], FloatArray],
    X: FloatArray,
    sol: _Inner,
    whiten: FloatArray,
    sigma: float,
    H: FloatArray,
) -> FloatArray:
    """Second-order (Neyman-Scott) bias of the constants, to be subtracted.

    ``resolve(X_perturbed)`` returns the whitened residuals (N', m) after
    re-solving the per-frame nuisances (warm-started) for stacked perturbed
    copies of the frames at the current constants. The expected residual of
    a frame under isotropic noise ``sigma`` is, to second order,
    ``b_t = 1/2 sum_i [r(X + sigma u_i) + r(X - sigma u_i) - 2 r(X)]`` over the
    ``3 M`` coordinate directions ``u_i`` (exact for the quadratic term, in
    any orthonormal basis). The Gauss-Newton equations ``sum_t J_t^T r_t = 0``
    with ``J_t = -P_t W^-1/2`` then give the bias ``H^-1 sum_t W^-1/2 P_t b_t``.
    """
    n, m_markers, _ = X.shape
    d = 3 * m_markers
    eye = np.eye(d).reshape(d, m_markers, 3)
    pert = np.concatenate([X[None] + sigma * eye[:, None], X[None] - sigma * eye[:, None]])  # (2d, N, M, 3)
    r = resolve(pert.reshape(2 * d * n, m_markers, 3)).reshape(2 * d, n, -1)
    b = 0.5 * (r.sum(axis=0) - 2.0 * d * sol.r)  # (N, m)
    Pb = np.einsum("nij,nj->ni", _projector(sol.G), b)
    g = np.einsum("ji,nj->i", whiten, Pb)
    out: FloatArray = _sym_inv(H) @ g
    return out


# --------------------------------------------------------------------------- ball joint: distance model


def _multilaterate(X: FloatArray, a: FloatArray) -> FloatArray:
    """Candidate points at distances ``a`` (M,) from the markers ``X`` (N, M, 3): shape (3, N, 3).

    Differences of the sphere equations give the linear system ``-2 Y J' = b``
    (``Y`` the markers about their centroid). Candidates: its least-squares
    solution and the two points on the sphere-consistent line through the
    in-plane solution along the weakest direction (the mirror pair when the
    markers are nearly coplanar).
    """
    centroid = X.mean(axis=1)
    Y = X - centroid[:, None, :]
    y2 = np.einsum("nki,nki->nk", Y, Y)
    a2 = a * a
    b = (a2 - a2.mean()) - (y2 - y2.mean(axis=1, keepdims=True))
    U, s, Vt = np.linalg.svd(-2.0 * Y, full_matrices=False)  # (N, M, 3), (N, 3), (N, 3, 3)
    coef = np.einsum("nki,nk->ni", U, b)
    keep = s > 1e-9 * s[:, :1]
    z = np.where(keep, coef / np.where(keep, s, 1.0), 0.0)
    full = np.einsum("nji,nj->ni", Vt, z)
    z_in = z.copy()
    z_in[:, 2] = 0.0
    inplane = np.einsum("nji,nj->ni", Vt, z_in)
    weak = Vt[:, 2, :]
    omega = a2.mean() - y2.mean(axis=1)  # |J'|^2 from the mean sphere equation
    t = np.sqrt(np.maximum(omega - np.einsum("ni,ni->n", inplane, inplane), 0.0))
    cands = np.stack([full, inplane + t[:, None] * weak, inplane - t[:, None] * weak])
    out: FloatArray = cands + centroid[None]
    return out


def _sphere_inner(X: FloatArray, a: FloatArray, start: FloatArray | None = None) -> _Inner:
    """Per-frame centre ``J_t`` minimising ``sum_k (|J - X_k| - a_k)^2``.

    From the best of the three multilateration candidates, or from ``start`` (N, 3) when given.
    """
    J = _multilaterate(X, a) if start is None else start[None].copy()
    Xb = np.broadcast_to(X, (J.shape[0], *X.shape))

    def residual(J: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        e, dist = _unit(J[:, :, None, :] - Xb)
        r = dist - a
        return r, e, np.einsum("cnk,cnk->cn", r, r)

    r, e, cost = residual(J)
    lam = np.full(cost.shape, 1e-6)
    tol = 1e-10 * float(np.max(a))
    for _ in range(_INNER_STEPS):  # Levenberg-Marquardt per frame and candidate
        GtG = np.einsum("cnki,cnkj->cnij", e, e)
        damp = lam[..., None, None] * (np.trace(GtG, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) + np.eye(3))
        step = _solve3(GtG + damp, np.einsum("cnki,cnk->cni", e, r))
        J_new = J - step
        r_new, e_new, cost_new = residual(J_new)
        ok = cost_new <= cost
        J = np.where(ok[..., None], J_new, J)
        r = np.where(ok[..., None], r_new, r)
        e = np.where(ok[..., None, None], e_new, e)
        cost = np.where(ok, cost_new, cost)
        lam = np.where(ok, lam * 0.1, lam * 10.0)
        if float(np.max(np.abs(step))) < tol:
            break
    best = np.argmin(cost, axis=0)
    frames = np.arange(X.shape[0])
    return _Inner(r[best, frames], e[best, frames], (J[best, frames],))


def _s22_linear_system(A1: FloatArray, A2: FloatArray, B1: FloatArray, B2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rows of eq. (16) (re-derived) for each frame: M (N, 9), K (N,).

    Unknowns ``(d, Y1', Y2', Y1'^2, Y2'^2, (Y1 Y2)', d Y1, d Y2, r2')`` where the
    primes absorb ``d^2`` (see :func:`s22_closed_form`).
    """
    u, _ = _unit(A2 - A1)
    v1, v2 = B1 - A1, B2 - A1
    z1, z2 = np.einsum("ni,ni->n", v1, u), np.einsum("ni,ni->n", v2, u)
    q1, q2 = np.einsum("ni,ni->n", v1, v1), np.einsum("ni,ni->n", v2, v2)
    p1 = v1 - z1[:, None] * u
    p2 = v2 - z2[:, None] * u
    P1, P2, C = np.einsum("ni,ni->n", p1, p1), np.einsum("ni,ni->n", p2, p2), np.einsum("ni,ni->n", p1, p2)
    D2 = P1 * P2 - C * C
    M = np.stack(
        [
            -4.0 * q1 * z1 * P2 - 4.0 * q2 * z2 * P1 + 4.0 * C * (q1 * z2 + q2 * z1),
            2.0 * q1 * P2 - 2.0 * C * q2,
            2.0 * q2 * P1 - 2.0 * C * q1,
            P2,
            P1,
            -2.0 * C,
            -4.0 * z1 * P2 + 4.0 * C * z2,
            -4.0 * z2 * P1 + 4.0 * C * z1,
            -4.0 * D2,
        ],
        axis=1,
    )
    K = -(q1 * q1 * P2 + q2 * q2 * P1 - 2.0 * q1 * q2 * C)
    return M, K


def s22_closed_form(parent: ArrayLike, child: ArrayLike) -> FloatArray:
    """Closed-form S22 constants from two markers on each link (section IV-C).

    Parameters
    ----------
    parent, child : array_like, shape (N, 2, 3)
        The two markers of each link, world frame, any length unit; frames
        with a NaN marker are skipped. At least 9 complete frames.

    Returns
    -------
    ndarray, shape (4,)
        ``(d, r, rho1, rho2)``: the centre's axial coordinate from parent
        marker 0 towards parent marker 1, its distance from that line, and its
        distances from child markers 0 and 1 (input units). ``r`` or a
        ``rho`` is NaN when its square came out negative (too much noise).

    Raises
    ------
    InputError
        Wrong shapes or fewer than 9 complete frames.

    Notes
    -----
    Eq. (14)-(17) of Pham et al., re-derived: in the pair frame (origin at
    parent marker 0, z along the pair) with ``R_k^2 = |B_k|^2``,
    ``P_k = x_k^2 + y_k^2``, ``C = x_1 x_2 + y_1 y_2``, ``delta^2 = P_1 P_2 - C^2``,
    four times eq. (14) is linear in
    ``(d, d^2, Y1, Y2, Y1^2, Y2^2, Y1 Y2, d Y1, d Y2, r^2)`` with
    ``Y_k = d^2 + r^2 - rho_k^2`` -- ten unknowns, not the nine of eq. (17):
    the ``d^2`` term is missing there. Its column is, however, a combination
    of the others for a rigid child pair (``col(d^2) = 2 col(Y1) + 2 col(Y2)
    - 2 L_B^2 col(Y1 Y2) + 2 col(r^2)``, ``L_B`` the child pair length), so the
    ten are not all determined; dropping ``d^2`` leaves nine unknowns
    ``(d, Y1 + 2 d^2, Y2 + 2 d^2, ..., r^2 + 2 d^2)`` that are. They are solved
    by linear least squares over all frames (columns scaled to unit norm)
    and ``d, r, rho1, rho2`` recovered from the linear unknowns only. This is
    an algebraic fit: with noise it is biased (the paper calls it too
    sensitive to noise); :func:`fit_centre_minimal` uses it as a start.
    """
    yp = check_markers(parent, name="parent")
    yc = check_markers(child, name="child")
    if yp.shape[1] != 2 or yc.shape[1] != 2 or yp.shape[0] != yc.shape[0]:
        raise InputError(f"parent, child: expected shapes (N, 2, 3) and (N, 2, 3), got {yp.shape} and {yc.shape}")
    return _s22_constants(yp, yc, _used_frames(np.concatenate([yp, yc], axis=1), 9, "S22 closed form"))


def _s22_constants(yp: FloatArray, yc: FloatArray, used: BoolArray) -> FloatArray:
    A1, A2, B1, B2 = yp[used, 0], yp[used, 1], yc[used, 0], yc[used, 1]
    scale = float(np.sqrt(np.mean(np.sum((np.concatenate([A2, B1, B2]) - np.tile(A1, (3, 1))) ** 2, axis=1))))
    M, K = _s22_linear_system(A1 / scale, A2 / scale, B1 / scale, B2 / scale)
    norms = np.linalg.norm(M, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    X = np.linalg.lstsq(M / norms, K, rcond=None)[0] / norms
    d = X[0]
    y1, y2, r2 = X[1] - 2 * d * d, X[2] - 2 * d * d, X[8] - 2 * d * d
    rho1_2, rho2_2 = d * d + r2 - y1, d * d + r2 - y2

    def root(v: float) -> float:
        return float(np.sqrt(v)) if v > 0 else float("nan")

    return np.array([d * scale, root(r2) * scale, root(rho1_2) * scale, root(rho2_2) * scale])


def _grid_starts(X: FloatArray, n_keep: int = 3) -> list[FloatArray]:
    """Starting distances from a grid of centre positions in one reference frame, locally refined.

    Knowing the centre in any one frame gives every distance. A 17^3 grid
    spans the markers' bounding box in the frame with the largest marker
    spread, enlarged by half the largest marker separation. Each grid
    point's distances are scored on up to 32 frames by the median squared
    residual of the linear multilateration (the per-frame least-squares
    solution is linear in the squared distances, so all grid points are
    scored at once). The best points (at least two grid steps apart) are
    refined as 3-parameter least-squares problems (the reference-frame
    centre) and the ``n_keep`` best results returned.
    """
    centred = X - X.mean(axis=1, keepdims=True)
    ref = X[int(np.argmax(np.einsum("nki,nki->n", centred, centred)))]
    sep = float(np.max(np.linalg.norm(ref[:, None] - ref[None], axis=2)))
    sub = X[np.linspace(0, X.shape[0] - 1, min(32, X.shape[0])).astype(int)]
    centroid = sub.mean(axis=1)
    Y = sub - centroid[:, None, :]
    y2 = np.einsum("nki,nki->nk", Y, Y)
    pinv = np.linalg.pinv(-2.0 * Y)  # (n, 3, M)

    lo, hi = ref.min(axis=0) - 0.5 * sep, ref.max(axis=0) + 0.5 * sep
    axes = [np.linspace(lo[i], hi[i], 17) for i in range(3)]
    step = float(np.max((hi - lo) / 16.0))
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    scores = np.empty(grid.shape[0])
    for chunk in np.array_split(np.arange(grid.shape[0]), max(1, grid.shape[0] // 1024)):
        a = np.linalg.norm(grid[chunk, None, :] - ref[None], axis=2)  # (G, M)
        a2 = a * a
        b = (a2 - a2.mean(axis=1, keepdims=True))[:, None, :] - (y2 - y2.mean(axis=1, keepdims=True))[None]
        J = np.einsum("nik,gnk->gni", pinv, b) + centroid[None]  # (G, n, 3)
        r = np.linalg.norm(J[:, :, None, :] - sub[None], axis=3) - a[:, None, :]
        scores[chunk] = np.median(np.einsum("gnk,gnk->gn", r, r), axis=1)
    seeds: list[FloatArray] = []
    for i in np.argsort(scores):
        if all(np.max(np.abs(grid[i] - c)) > 2.0 * step for c in seeds):
            seeds.append(grid[i])
        if len(seeds) == n_keep + 1:
            break
    results = []
    for point in seeds:
        J0 = _sphere_inner(sub, np.linalg.norm(point - ref, axis=1)).state[0]

        def fun(x: FloatArray, J0: FloatArray = J0) -> FloatArray:
            out: FloatArray = _sphere_inner(sub, np.linalg.norm(x - ref, axis=1), J0).r.ravel()
            return out

        res = least_squares(fun, point, method="lm", max_nfev=24, xtol=1e-4, ftol=1e-4)
        results.append((float(np.sum(res.fun**2)), np.linalg.norm(res.x - ref, axis=1)))
    results.sort(key=lambda item: item[0])
    return [a for _, a in results[:n_keep]]


def _sphere_starts(yp: FloatArray, yc: FloatArray, used: BoolArray) -> list[FloatArray]:
    """Starting distances (M,) for the ball-joint fit: closed forms, then grid points."""
    p, q = yp.shape[1], yc.shape[1]
    X = np.concatenate([yp, yc], axis=1)[used]
    starts: list[FloatArray] = []
    if p == 2 and q == 2:
        for first, second, swap in ((yp, yc, False), (yc, yp, True)):
            d, r, rho1, rho2 = _s22_constants(first, second, used)
            if not np.isfinite([d, r, rho1, rho2]).all():
                continue
            length = float(np.mean(np.linalg.norm(first[used, 1] - first[used, 0], axis=1)))
            a_first = [np.hypot(d, r), np.hypot(length - d, r)]
            a = np.array([*a_first, rho1, rho2]) if not swap else np.array([rho1, rho2, *a_first])
            starts.append(a)
    if max(p, q) >= 3:
        frame, other = (yp, yc) if p >= 3 else (yc, yp)
        try:
            template = template_from_markers(frame)
            poses = poses_from_markers(frame, template)
            R, dvec = poses.R_world_local, poses.d_world_local
            local = np.einsum("nji,nkj->nki", R, other - dvec[:, None, :])
            centre_local = fit_centre(local).centre
            J = np.einsum("nij,j->ni", R, centre_local) + dvec
            a = np.nanmean(np.linalg.norm(J[used][:, None, :] - X, axis=2), axis=0)
            if np.isfinite(a).all():
                starts.append(a)
        except (InputError, NotIdentifiableError):
            pass
    return starts + _grid_starts(X)


def _sphere_fit(
    X: FloatArray, starts: list[FloatArray], lower: FloatArray, noise_var: float
) -> tuple[FloatArray, _Inner, float, BoolArray]:
    """Least-squares constants: the starts refined on a subsample, the best on the well-conditioned frames.

    Returns the constants, the inner solution and cost on the kept frames, and the kept-frame mask.
    """
    m = X.shape[1]
    whiten = np.eye(m)
    sub_idx = np.linspace(0, X.shape[0] - 1, min(_SUBSAMPLE, X.shape[0])).astype(int)
    sub = X[sub_idx]
    best_a, best_cost = starts[0], np.inf
    for a0 in starts:
        a = a0
        for _ in range(3):  # re-pick each frame's branch at the new constants until they settle
            a_prev = a
            a, sol = _varpro(_warm_sphere_inner(sub, a, lower), whiten, a, lower, max_nfev=30)
            if float(np.max(np.abs(a - a_prev))) < 1e-3 * float(np.median(a)):
                break
        cost = float(np.sum(sol.r**2))
        if cost < best_cost:
            best_a, best_cost = a, cost
    sol_all = _sphere_inner(X, best_a)
    # robust residual variance (median of the per-frame chi-square with m - 3 degrees of freedom)
    s2 = max(float(np.median(np.sum(sol_all.r**2, axis=1))) / _CHI2_MEDIAN[m - 3], noise_var)
    keep = _well_conditioned(sol_all.G, s2, best_a)
    a, sol = _varpro(_warm_sphere_inner(X[keep], best_a, lower), whiten, best_a, lower)
    return a, sol, float(np.sum(sol.r**2)), keep


def _well_conditioned(G: FloatArray, s2: float, const: FloatArray) -> BoolArray:
    """Frames whose own nuisance point is determined to within :data:`KAPPA_MAX` of the median constant.

    At least the best-conditioned max(10, 20 %) of the frames are kept.
    """
    kappa = _frame_sd(G, s2) / float(np.median(np.abs(const)))
    n_min = min(kappa.size, max(_MIN_FRAMES, int(np.ceil(_MIN_KEEP * kappa.size))))
    threshold = max(KAPPA_MAX, float(np.sort(kappa)[n_min - 1]))
    return np.asarray(kappa <= threshold, dtype=bool)


def _warm_sphere_inner(X: FloatArray, a0: FloatArray, lower: FloatArray) -> Callable[[FloatArray], _Inner]:
    """The per-frame centre solve for trial constants, warm-started from the solution at ``a0``.

    Starting every trial from the same per-frame centres keeps each frame on
    one branch, so that the cost is a smooth function of the constants.
    """
    J0 = _sphere_inner(X, np.maximum(a0, lower)).state[0]
    return lambda x: _sphere_inner(X, x, J0)


def fit_centre_minimal(
    parent: ArrayLike, child: ArrayLike, *, initial_distances: ArrayLike | None = None
) -> MinimalCentreFit:
    """Ball-joint centre from as few as 2 + 2 (S22) or 3 + 1 (S31) markers.

    Parameters
    ----------
    parent, child : array_like, shape (N, p, 3) and (N, q, 3)
        Marker positions on the two links, world frame, the same frames, any
        length unit; NaN marks a missing marker (frames missing any marker
        are not used). ``(p, q)`` must be identifiable
        (:func:`jointfit_core.check_marker_counts`): ``p + q >= 4`` with at
        least 2 markers on each link, or 3 + 1. At least 10 complete frames.
    initial_distances : array_like, shape (p + q,), optional
        Starting distances of the centre from the markers (parent first),
        e.g. a previous fit of the same subject; replaces the global start
        search (closed forms and grid) when given.

    Returns
    -------
    MinimalCentreFit
        The constant marker distances with their covariance, the centre in
        each link's pair frame, the per-frame world centre with covariance,
        residuals and the verdict (method ``"S22"`` for 2 + 2, ``"S31"`` when a
        link has 3 or more markers).

    Raises
    ------
    NotIdentifiableError
        The marker counts cannot identify the centre ((2, 1), (1, 1), ...;
        the message says why and what to add), or the motion does not
        determine it at all (singular normal matrix: no relative rotation).
    InputError
        Wrong shapes, different frame counts, too few complete frames.

    Notes
    -----
    **Model.** Section V-A of Pham et al. (S22) searches the four constants
    ``(d, r, rho1, rho2)``: the centre lies on the circle ``(d, r)`` about the
    parent pair's axis and on the circle of points at ``rho1, rho2`` from the
    child markers, and in each frame it is the point nearest both circles;
    the paper's cost is the sum of the variances of the centre's distances to
    the markers. Here the same search is posed as least squares over the
    equivalent constants ``a_k = |J - X_k|`` (``d, r`` follow from the two
    parent distances and the pair length), symmetric in the markers and valid
    for any count: the per-frame centre ``J_t`` minimises
    ``sum_k (|J_t - X_k,t| - a_k)^2``, i.e. it is the point nearest all the
    spheres (for S22: nearest both circles), and the cost is the sum of
    these minima. With isotropic marker noise ``sigma`` per coordinate each
    residual has variance ``sigma^2``, so this is maximum likelihood to first
    order, with ``N (M - 3) - M`` residual degrees of freedom.

    **Search.** ``least_squares`` (trust region reflective, ``a_k > 0``) over
    ``a`` only; for each trial the ``J_t`` come from linear multilateration
    (differences of the sphere equations) and its mirror candidates when the
    markers are nearly coplanar, then 10 batched Levenberg-Marquardt steps,
    keeping the best candidate per frame. Starts: for 2 + 2 the linear
    system of section IV-C (see :func:`s22_closed_form`) with either link as
    the pair, for a link with 3 or more markers the sphere fit of the other
    link's markers in its frame (IV-A, :func:`jointfit_core.fit_centre`),
    and the 3 best points of a coarse grid of centre positions in one frame
    (the closed form alone is too noise-sensitive, as the paper notes). Each
    start is refined on up to 200 frames; the best is refined on all.

    **Frames used.** Frames whose own centre is poorly determined (largest
    per-frame standard deviation above :data:`KAPPA_MAX` times the median
    marker distance: nearly coplanar markers, where the centre and its
    mirror image fit almost equally) are dropped from the constants after a
    first fit: there the second-order expansion below fails and they bias
    the result. Their centres are still reported (with their large
    covariance).

    **Bias.** With a per-frame nuisance the least-squares constants carry a
    bias that does not shrink with N (Neyman-Scott); it is removed to second
    order with one Newton step (see :func:`_bias_correction`: +/- one-sigma
    perturbations of every marker coordinate, re-solving the centres).

    **Covariance.** ``cov(a) = s^2 (sum_t A_t)^-1`` (Gauss-Newton), with
    ``A_t = I - G_t (G_t^T G_t)^-1 G_t^T`` the projection off the per-frame
    centre (``G_t`` rows: unit vectors from the markers to ``J_t``) and
    ``s^2`` the residual sum of squares over its degrees of freedom (model
    error such as skin motion therefore widens it), but at least the noise
    variance implied by the spread of the intra-link marker distances
    (``var |X_i - X_j| = 2 sigma^2`` for a rigid link): in poorly conditioned
    geometries the per-frame centres absorb part of the noise and the
    residual estimate alone runs low. The pair-frame
    coordinates carry it through their Jacobian (the pair length's own small
    error is ignored). The per-frame world centre has ``s^2 (G^T G)^-1``
    (that frame's noise) plus ``(G^T G)^-1 G^T cov(a) G (G^T G)^-1``.
    """
    yp, yc = _check_pair_of_links(parent, child, "spherical")
    p, q = yp.shape[1], yc.shape[1]
    X_all = np.concatenate([yp, yc], axis=1)
    complete = _used_frames(X_all, _MIN_FRAMES, "the minimal ball-joint fit")
    X_complete = X_all[complete]
    m = X_all.shape[1]
    scale = float(np.sqrt(np.mean(np.sum((X_complete - X_complete.mean(axis=1, keepdims=True)) ** 2, axis=2))))
    lower = np.full(m, 0.01 * scale)
    whiten = np.eye(m)

    noise_var = _rigid_noise_var([X_complete[:, :p], X_complete[:, p:]])
    if initial_distances is None:
        starts = _sphere_starts(yp, yc, complete)
    else:
        start = np.asarray(initial_distances, dtype=np.float64)
        if start.shape != (m,) or not np.isfinite(start).all() or np.any(start <= 0):
            raise InputError(
                f"initial_distances: expected {m} finite positive distances (parent markers first), got {initial_distances!r}"
            )
        starts = [start]
    a, sol, cost, keep = _sphere_fit(X_complete, starts, lower, noise_var)
    X = X_complete[keep]
    n_used = X.shape[0]
    dof = n_used * (m - 3) - m
    if dof <= 0:
        raise InputError(f"parent, child: too few frames for the residual degrees of freedom ({dof})")
    s2 = max(cost / dof, noise_var)
    H = _normal_matrix(sol, whiten)
    lam = np.linalg.eigvalsh(H)
    if lam[0] <= _SINGULAR_REL * max(lam[-1], _TINY):
        raise NotIdentifiableError(
            "the motion does not determine the centre: the marker distances are constant for a whole family of "
            "points (no relative rotation between the links, or rotation about one axis only); rotate the child "
            "relative to the parent about at least two axes"
        )
    (J,) = sol.state
    reps = 6 * m

    def resolve(Xp: FloatArray) -> FloatArray:
        return _sphere_inner(Xp, a, np.tile(J, (reps, 1))).r

    a_hat = a.copy()
    for _ in range(_BIAS_STEPS):
        a = np.maximum(a_hat - _bias_correction(resolve, X, sol, whiten, float(np.sqrt(s2)), H), lower)
        sol = _sphere_inner(X, a, J)
        (J,) = sol.state
        H = _normal_matrix(sol, whiten)
    cov = s2 * _sym_inv(H)

    # Per-frame centres of every complete frame (the dropped ones too).
    sol_all = _sphere_inner(X_complete, a)
    sol_all.state[0][keep] = sol.state[0]
    sol_all = _sphere_inner(X_complete, a, sol_all.state[0])
    G = sol_all.G
    GtG_inv = _sym_inv(np.einsum("nki,nkj->nij", G, G))
    Kt = GtG_inv @ np.swapaxes(G, -1, -2)  # (N, 3, m)
    cov_J = s2 * GtG_inv + Kt @ cov @ np.swapaxes(Kt, -1, -2)
    n_frames = X_all.shape[0]
    centre_world = np.full((n_frames, 3), np.nan)
    centre_world[complete] = sol_all.state[0]
    cov_world = np.full((n_frames, 3, 3), np.nan)
    cov_world[complete] = cov_J
    residual = np.full(n_frames, np.nan)
    residual[complete] = np.sqrt(np.sum(sol_all.r**2, axis=1))
    res_norm = np.sqrt(np.sum(sol.r**2, axis=1))

    def pair_frame(idx0: int, markers: FloatArray) -> tuple[FloatArray, FloatArray]:
        if markers.shape[1] < 2:
            return np.full(2, np.nan), np.full((2, 2), np.nan)
        length = float(np.mean(np.linalg.norm(markers[complete, 1] - markers[complete, 0], axis=1)))
        sl = slice(idx0, idx0 + 2)
        return _pair_coordinates(float(a[idx0]), float(a[idx0 + 1]), length, cov[sl, sl])

    centre_parent, cov_parent = pair_frame(0, yp)
    centre_child, cov_child = pair_frame(p, yc)

    sd = float(_max_sd(cov))
    lever = float(np.median(a))
    identifiable, reason = True, ""
    if not np.isfinite(sd) or sd > SD_REL_MAX * lever:
        identifiable = False
        reason = (
            f"centre poorly determined: the standard deviation of its marker distances ({sd:.3g}) exceeds "
            f"{SD_REL_MAX:.0%} of the lever arm ({lever:.3g}); rotate the child relative to the parent through a "
            "larger range about at least two axes, record more frames, or add a marker (3 on one link fixes its "
            "frame)"
        )
    return MinimalCentreFit(
        distances=a,
        cov=cov,
        centre_parent=centre_parent,
        cov_parent=cov_parent,
        centre_child=centre_child,
        cov_child=cov_child,
        centre_world=centre_world,
        cov_world=cov_world,
        residual=residual,
        rms=float(np.sqrt(np.mean(res_norm**2))),
        n_frames=int(n_used),
        identifiable=identifiable,
        reason=reason,
        noise_std=float(np.sqrt(s2)),
        method="S22" if (p == 2 and q == 2) else "S31",
    )


# --------------------------------------------------------------------------- hinge: closed form (section III-A)


def _r21_frame(A1: FloatArray, A2: FloatArray, B: FloatArray) -> dict[str, FloatArray]:
    """Pair-frame quantities: u, e1, e2 (N, 3), B's x, y, z and R^2 (N,)."""
    u, _ = _unit(A2 - A1)
    e1, e2 = _perp_basis(u)
    v = B - A1
    return {
        "u": u,
        "e1": e1,
        "e2": e2,
        "x": np.einsum("ni,ni->n", v, e1),
        "y": np.einsum("ni,ni->n", v, e2),
        "z": np.einsum("ni,ni->n", v, u),
        "R2": np.einsum("ni,ni->n", v, v),
    }


def _r21_dh(A1: FloatArray, A2: FloatArray, B: FloatArray) -> FloatArray:
    """DH candidates (K, 5) ``(d, r, alpha, l, rho)``, alpha in (0, pi/2], from eq. (7)-(13) on all frames."""
    f = _r21_frame(A1, A2, B)
    scale = float(np.sqrt(np.mean(f["R2"])))
    z, R2 = f["z"] / scale, f["R2"] / scale**2
    M = np.stack([-4.0 * R2 * z, 2.0 * R2, -4.0 * z, np.ones_like(z), 4.0 * z * z], axis=1)
    K = -R2 * R2
    norms = np.linalg.norm(M, axis=0)
    Z = np.linalg.lstsq(M / norms, K, rcond=None)[0] / norms
    Z1, Z2, Z3, Z4, Z5 = Z
    d = Z1
    a = 2.0 * (Z5 - Z1**2) + Z2 + 2.0 * Z1**2
    b = -4.0 * Z1 * Z3 + Z4
    c = 2.0 * Z3**2 - Z4 * (2.0 * (Z5 - Z1**2) + Z2)
    roots = np.roots([-1.0, a, b, c])
    den = Z5 - d * d
    out = []
    fallback = []
    for root in roots:
        if abs(root.imag) > 1e-6 * max(1.0, abs(root.real)):
            continue
        Q = float(root.real)
        r2 = (Q - Z2) / 2.0
        s2 = r2 / den if den > 0 else np.nan
        if not (r2 > 0 and 0.0 < s2 < 1.0):
            fallback.append((Q, r2, s2))
            continue
        cos_a = np.sqrt(1.0 - s2)
        lpdc = np.sign(Z3 - Q * d) * np.sqrt(max(Z4 - Q * Q, 0.0) / (4.0 * den))
        l = lpdc - d * cos_a
        rho2 = r2 + d * d - l * l - Q
        if rho2 <= 0:
            fallback.append((Q, r2, s2))
            continue
        out.append([d * scale, np.sqrt(r2) * scale, np.arcsin(np.sqrt(s2)), l * scale, np.sqrt(rho2) * scale])
    if not out:  # noise pushed every root out of range: clip the most plausible one
        Q, r2, s2 = min(fallback, key=lambda t: abs(np.clip(t[2], 0.05, 0.95) - t[2]) if np.isfinite(t[2]) else 9)
        s2 = float(np.clip(s2 if np.isfinite(s2) else 0.5, 0.05, 0.95))
        r2 = max(r2, 1e-4)
        cos_a = np.sqrt(1.0 - s2)
        lpdc = np.sign(Z3 - Q * d) * np.sqrt(max(Z4 - Q * Q, 0.0) / (4.0 * max(den, 1e-6)))
        l = lpdc - d * cos_a
        rho2 = max(r2 + d * d - l * l - Q, 1e-4)
        out.append([d * scale, np.sqrt(r2) * scale, np.arcsin(np.sqrt(s2)), l * scale, np.sqrt(rho2) * scale])
    return np.array(out)


def r21_closed_form(parent: ArrayLike, child: ArrayLike) -> FloatArray:
    """Closed-form hinge candidates from two markers on one link and one on the other (section III-A).

    Parameters
    ----------
    parent : array_like, shape (N, 2, 3)
        The two markers of the pair link, world frame, any length unit.
    child : array_like, shape (N, 1, 3)
        The single marker of the other link. Frames with a NaN marker are
        skipped; at least 5 complete frames.

    Returns
    -------
    ndarray, shape (K, 5)
        Denavit-Hartenberg constants ``(d, r, alpha, l, rho)`` of each
        admissible root of eq. (13) (usually K = 2): the hinge's common
        perpendicular with the pair line starts at axial coordinate ``d``
        (from marker 0 towards marker 1) and has length ``r``, ``alpha`` (rad,
        in (0, pi/2] here) is the twist between the two lines, ``l`` the axial
        position on the hinge of the centre of the single marker's circle and
        ``rho`` its radius. Each row also stands for its mirror image
        (``alpha -> -alpha``), which fits the data equally.

    Raises
    ------
    InputError
        Wrong shapes or fewer than 5 complete frames.

    Notes
    -----
    Eq. (7)-(9), re-derived and confirmed: with ``R^2 = |B - A_1|^2`` and
    ``z`` the axial coordinate of ``B``, ``(-4 R^2 z, 2 R^2, -4 z, 1, 4 z^2) . Y =
    -R^4`` with ``Y`` of eq. (9). All frames are stacked and solved by linear
    least squares (lengths scaled to unit rms, columns to unit norm) for
    ``Z``; ``d = Z_1`` and ``Q`` solves the cubic (13) with the paper's
    ``a, b, c``. For each real root ``r^2 = (Q - Z_2) / 2``,
    ``sin^2 alpha = r^2 / (Z_5 - d^2)``, ``l + d cos alpha`` from ``Z_4``
    (magnitude ``sqrt((Z_4 - Q^2) / (4 (Z_5 - d^2)))``) with the sign of
    ``Z_3 - Q d`` (the paper divides by ``cos alpha`` instead, which fails for
    hinges nearly perpendicular to the pair, e.g. the knee) and
    ``rho^2 = r^2 + d^2 - l^2 - Q``. A root is admissible when ``r^2 > 0``,
    ``0 < sin^2 alpha < 1`` and ``rho^2 > 0``. Contrary to the paper's claim
    that one root remains, in noise-free tests two roots are admissible
    and both hinges pass through every sample exactly (see
    :mod:`jointfit_core.identifiability`). With noise the algebraic fit is
    biased; :func:`fit_axis_minimal` refines it. When noise leaves no
    admissible root, the most plausible one is clipped into range.
    """
    yp = check_markers(parent, name="parent")
    yc = check_markers(child, name="child")
    if yp.shape[1] != 2 or yc.shape[1] != 1 or yp.shape[0] != yc.shape[0]:
        raise InputError(f"parent, child: expected shapes (N, 2, 3) and (N, 1, 3), got {yp.shape} and {yc.shape}")
    used = _used_frames(np.concatenate([yp, yc], axis=1), 5, "R21 closed form")
    return _r21_dh(yp[used, 0], yp[used, 1], yc[used, 0])


def _dh_lines(
    A1: FloatArray, A2: FloatArray, B: FloatArray, dh: FloatArray, chirality: float
) -> tuple[FloatArray, FloatArray]:
    """Per-frame hinge lines ``(point, direction)`` (N, 3) from DH constants, eq. (4)-(5) for theta.

    ``chirality`` (+1 or -1) is the sign given to ``sin alpha`` (the mirror image).
    """
    d, r, alpha, l, rho = (float(v) for v in dh)
    f = _r21_frame(A1, A2, B)
    s = chirality * max(abs(np.sin(alpha)), 1e-3)
    c = float(np.cos(alpha))
    r = max(r, _TINY)
    Q = r * r + d * d - l * l - rho * rho
    A = (l + d * c - f["z"] * c) / s
    Bv = (f["R2"] + Q - 2.0 * f["z"] * d) / (2.0 * r)
    sin_t = f["x"] * A + f["y"] * Bv
    cos_t = f["x"] * Bv - f["y"] * A
    norm = np.hypot(sin_t, cos_t)
    sin_t = np.where(norm > 0, sin_t / np.maximum(norm, _TINY), 0.0)
    cos_t = np.where(norm > 0, cos_t / np.maximum(norm, _TINY), 1.0)
    e1, e2, u = f["e1"], f["e2"], f["u"]
    point = A1 + r * (cos_t[:, None] * e1 + sin_t[:, None] * e2) + d * u
    direction = s * (sin_t[:, None] * e1 - cos_t[:, None] * e2) + c * u
    direction, _ = _unit(direction)
    return point, direction


# --------------------------------------------------------------------------- hinge: distance model


def _offset_whitening(m_markers: int) -> FloatArray:
    """``W^-1/2`` of the residual noise: distances independent, offsets (vs marker 0) correlated via marker 0."""
    k = m_markers - 1
    W = np.eye(m_markers + k)
    W[m_markers:, m_markers:] = np.eye(k) + np.ones((k, k))
    lam, V = np.linalg.eigh(W)
    out: FloatArray = (V / np.sqrt(lam)) @ V.T
    return out


def _line_residuals(
    X: FloatArray, const: FloatArray, c: FloatArray, n: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Raw residuals (N, m), nuisance Jacobian (N, m, 4), basis b1, b2, radial units e (N, M, 3), axial h (N, M)."""
    m_markers = X.shape[1]
    b1, b2 = _perp_basis(n)
    w = X - c[:, None, :]
    h = np.einsum("nki,ni->nk", w, n)
    wperp = w - h[..., None] * n[:, None, :]
    e, dist = _unit(wperp)
    rel = X[:, 1:, :] - X[:, :1, :]
    r = np.concatenate([dist - const[:m_markers], np.einsum("nki,ni->nk", rel, n) - const[m_markers:]], axis=1)
    eb1, eb2 = np.einsum("nki,ni->nk", e, b1), np.einsum("nki,ni->nk", e, b2)
    G_dist = np.stack([-eb1, -eb2, -h * eb1, -h * eb2], axis=-1)
    zero = np.zeros(rel.shape[:2])
    G_off = np.stack([zero, zero, np.einsum("nki,ni->nk", rel, b1), np.einsum("nki,ni->nk", rel, b2)], axis=-1)
    return r, np.concatenate([G_dist, G_off], axis=1), b1, b2, e, h


def _line_inner(X: FloatArray, const: FloatArray, c0: FloatArray, n0: FloatArray, whiten: FloatArray) -> _Inner:
    """Per-frame axis line minimising the whitened distance-model residuals, from (c0, n0)."""
    c, n = c0.copy(), n0.copy()
    for _ in range(_INNER_STEPS):
        r, G, b1, b2, _, _ = _line_residuals(X, const, c, n)
        rt = r @ whiten.T
        Gt = whiten @ G
        GtG = np.einsum("nki,nkj->nij", Gt, Gt) + 1e-12 * np.eye(4)
        step = -np.linalg.solve(GtG, np.einsum("nki,nk->ni", Gt, rt)[..., None])[..., 0]
        c = c + step[:, 0:1] * b1 + step[:, 1:2] * b2
        n, _ = _unit(n + step[:, 2:3] * b1 + step[:, 3:4] * b2)
        c = c + np.einsum("ni,ni->n", X[:, 0] - c, n)[:, None] * n  # the point nearest marker 0
    r, G, *_ = _line_residuals(X, const, c, n)
    return _Inner(r @ whiten.T, whiten @ G, (c, n))


def _line_constants(X: FloatArray, c: FloatArray, n: FloatArray) -> FloatArray:
    """Mean distances from the axis and axial offsets (vs marker 0) of the markers, given per-frame lines."""
    w = X - c[:, None, :]
    h = np.einsum("nki,ni->nk", w, n)
    dist = np.linalg.norm(w - h[..., None] * n[:, None, :], axis=2)
    out: FloatArray = np.concatenate([dist.mean(axis=0), (h[:, 1:] - h[:, :1]).mean(axis=0)])
    return out


def _const_to_dh(const: FloatArray, pair: tuple[int, int], single: int, m_markers: int, length: float) -> FloatArray:
    """DH constants ``(d, r, alpha, l, rho)`` of the hinge relative to the pair and the single marker.

    Uses ``p1^2 = r^2 + d^2 s^2``, ``p2^2 = r^2 + (L - d)^2 s^2``, ``h_A = L cos(alpha)``,
    ``h_B = l + d cos(alpha)`` (``p1, p2`` the pair markers' distances from the axis,
    ``h_A, h_B`` the axial offsets of the second pair marker and of the single
    marker from the first, ``L`` the pair length); alpha in (0, pi).
    """
    radii = const[:m_markers]
    off = np.concatenate([[0.0], const[m_markers:]])
    p1, p2, rho = radii[pair[0]], radii[pair[1]], radii[single]
    h_a = off[pair[1]] - off[pair[0]]
    h_b = off[single] - off[pair[0]]
    cos_a = float(np.clip(h_a / length, -1.0 + 1e-9, 1.0 - 1e-9))
    s2 = 1.0 - cos_a * cos_a
    d = ((p1 * p1 - p2 * p2) / s2 + length * length) / (2.0 * length)
    r = float(np.sqrt(max(p1 * p1 - d * d * s2, 0.0)))
    l = h_b - d * cos_a
    return np.array([d, r, float(np.arccos(cos_a)), l, rho])


@dataclass(frozen=True)
class _HingeCandidate:
    const: FloatArray
    sol: _Inner
    cost: float
    chirality: float


def fit_axis_minimal(parent: ArrayLike, child: ArrayLike, *, axis_hint: ArrayLike | None = None) -> MinimalAxisFit:
    """Hinge axis from two markers on one link and one (or two) on the other (R21).

    Parameters
    ----------
    parent, child : array_like, shape (N, p, 3) and (N, q, 3)
        Marker positions on the two links, world frame, the same frames, any
        length unit; NaN marks a missing marker (frames missing any marker
        are not used). ``(p, q)`` is (2, 1), (1, 2) or (2, 2); with 3 or more
        markers on a link use :func:`jointfit_core.fit_axis` in its frame or
        :func:`jointfit_core.fit_axis_two_segments`. At least 6 complete
        frames.
    axis_hint : array_like, shape (3,) or (N, 3), optional
        A world direction the hinge roughly points along (sign irrelevant),
        e.g. the lab's medio-lateral axis for a knee. It picks one of the
        hinges that fit the data equally well (see Notes). Without it an
        ambiguous fit is returned with ``identifiable=False``.

    Returns
    -------
    MinimalAxisFit
        The constants (marker distances from the axis, axial offsets) with
        their covariance, the paper's DH constants, the per-frame world axis
        with covariances, residuals, the number of equally good solutions and
        the verdict.

    Raises
    ------
    NotIdentifiableError
        (1, 1) markers (the message says why and what to add), or a motion
        that does not determine the hinge at all.
    InputError
        Wrong shapes, unsupported counts, too few complete frames, a bad
        ``axis_hint``.

    Notes
    -----
    **Model** (section III-A of Pham et al., in distance form). Each marker
    ``k`` keeps its distance ``rho_k`` from the axis and its axial offset
    ``h_k - h_0`` from marker 0 (parent markers first); per frame the axis
    line (4 parameters) is a nuisance. The raw residuals are the
    ``2 M - 1`` differences from these constants; with isotropic noise
    ``sigma`` they have covariance ``sigma^2 diag(I_M, I + 1 1^T)`` (offsets
    share marker 0's noise), which is whitened. ``N (2 M - 5) - (2 M - 1)``
    degrees of freedom remain.

    **Start and search.** The paper's closed form (eq. 7-13) on the pair
    and the single marker with all frames in least squares
    (:func:`r21_closed_form`) gives the candidate DH constants; per frame
    ``theta`` follows from eq. (4)-(5) (``x sin theta - y cos theta = A``,
    ``x cos theta + y sin theta = B``). Each candidate is refined by
    ``least_squares`` over the constants (variable projection as in
    :func:`fit_centre_minimal`; each trial re-solves the per-frame lines from
    the DH form of the trial constants and polishes them by 8 Gauss-Newton
    steps), then each refined hinge and its mirror image are compared.

    **Ambiguity.** For (2, 1) two different hinges (the two admissible roots
    of eq. 13) and their mirror images (reflection in the plane of the three
    markers, ``alpha -> -alpha``) fit the data exactly; the paper's
    uniqueness claim misses this. Solutions whose costs differ by less than
    :data:`AMBIGUITY_CHI2` residual variances and whose per-frame axes differ
    by more than 3 standard deviations count as distinct (``n_solutions``).
    ``axis_hint`` picks the one whose per-frame directions are best aligned
    with it (largest mean ``|n_t . hint_t|``); a fourth marker (2, 2)
    usually leaves one solution.

    **Verdict.** ``identifiable`` is False when the solutions stay
    ambiguous, when the chosen hinge is on average more than
    :data:`HINT_MAX_DEG` from the hint (with 2 + 1 markers and realistic
    noise the least-squares optimum can be a wrong, locally well-conditioned
    hinge), when the constants' largest standard deviation exceeds
    :data:`SD_REL_MAX` of the median marker distance from the axis, or when
    the typical per-frame direction sd exceeds :data:`DIRECTION_SD_MAX_DEG`
    (or the point sd :data:`SD_REL_MAX` of that distance). The 2 + 1 hinge is
    very noise-sensitive: the data are one point per frame on a quartic
    curve in the pair's meridian plane, and five constants are fitted to
    the arc the motion traces; on a knee-like geometry the weakest
    combination of constants has a standard deviation of several hundred
    times the marker noise.

    **Covariance.** Constants: ``s^2 (sum_t W^-1/2 P_t W^-1/2)^-1``
    (Gauss-Newton, ``P_t`` the projection off the line's nuisance
    directions, ``s^2`` the residual variance per degree of freedom). Per
    frame the line's tangent error is ``s^2 (G^T G)^-1`` plus the constants'
    error carried through ``(G^T G)^-1 G^T``, mapped to the direction (rank
    2) and to the point, including the single marker's own noise along the
    axis. DH constants: the constants' covariance through a numerical
    Jacobian of the conversion (the pair length's error ignored).
    """
    yp, yc = _check_pair_of_links(parent, child, "revolute")
    p, q = yp.shape[1], yc.shape[1]
    if max(p, q) != 2:
        raise InputError(
            f"parent, child: fit_axis_minimal takes (2, 1), (1, 2) or (2, 2) markers, got ({p}, {q}); with 3 or "
            "more markers on a link express the other link's markers in its frame and use fit_axis, or use "
            "fit_axis_two_segments"
        )
    X_all = np.concatenate([yp, yc], axis=1)
    m_markers = p + q
    used = _used_frames(X_all, 6, "the minimal hinge fit")
    n_frames = X_all.shape[0]
    hint = _check_hint(axis_hint, n_frames)
    X = X_all[used]
    n_used = X.shape[0]
    if p == 2:
        pair, single = (0, 1), 2
    else:
        pair, single = (1, 2), 0
    A1, A2, B = X[:, pair[0]], X[:, pair[1]], X[:, single]
    length = float(np.mean(np.linalg.norm(A2 - A1, axis=1)))
    whiten = _offset_whitening(m_markers)
    m = 2 * m_markers - 1
    scale = float(np.sqrt(np.mean(np.sum((X - X.mean(axis=1, keepdims=True)) ** 2, axis=2))))
    lower = np.concatenate([np.full(m_markers, 1e-6 * scale), np.full(m_markers - 1, -np.inf)])

    def inner_for(chirality: float) -> Callable[[FloatArray], _Inner]:
        def inner(const: FloatArray) -> _Inner:
            dh = _const_to_dh(const, pair, single, m_markers, length)
            c0, n0 = _dh_lines(A1, A2, B, dh, chirality)
            return _line_inner(X, const, c0, n0, whiten)

        return inner

    candidates: list[_HingeCandidate] = []
    for dh in _r21_dh(A1, A2, B):
        chiralities = (1.0, -1.0) if m_markers > 3 else (1.0,)
        for chi in chiralities:
            c0, n0 = _dh_lines(A1, A2, B, dh, chi)
            const0 = _line_constants(X, c0, n0)
            const, sol = _varpro(inner_for(chi), whiten, const0, lower)
            candidates.append(_HingeCandidate(const, sol, float(np.sum(sol.r**2)), chi))
            if m_markers == 3:  # the mirror image fits exactly as well with the same constants
                twin = inner_for(-chi)(const)
                candidates.append(_HingeCandidate(const, twin, float(np.sum(twin.r**2)), -chi))

    dof = n_used * (m - 4) - m
    if dof <= 0:
        raise InputError(f"parent, child: too few frames for the residual degrees of freedom ({dof})")
    order = sorted(range(len(candidates)), key=lambda i: candidates[i].cost)
    best = candidates[order[0]]
    s2 = max(best.cost / dof, (1e-9 * scale) ** 2)

    def world_outputs(cand: _HingeCandidate, cov: FloatArray) -> tuple[FloatArray, ...]:
        c, n = cand.sol.state
        _, _, b1, b2, e, h = _line_residuals(X, cand.const, c, n)
        Gt = cand.sol.G
        GtG_inv = _sym_inv(np.einsum("nki,nkj->nij", Gt, Gt))
        K = GtG_inv @ np.swapaxes(Gt, -1, -2) @ whiten  # (N, 4, m): tangent error per raw residual error
        cov_l = s2 * GtG_inv + K @ cov @ np.swapaxes(K, -1, -2)
        Bn = np.stack([b1, b2], axis=-1)  # (N, 3, 2)
        cov_dir = Bn @ cov_l[:, 2:, 2:] @ np.swapaxes(Bn, -1, -2)
        hs = h[:, single]
        dist_s = np.linalg.norm(X[:, single] - c - hs[:, None] * n, axis=1)
        es = e[:, single]
        # point = c + h_s n: d point = dc + h_s dn + (dist_s e_s . dn) n + (n . eps_s) n
        Jp = np.concatenate(
            [Bn, hs[:, None, None] * Bn + n[:, :, None] * (dist_s[:, None] * np.einsum("ni,nij->nj", es, Bn))[:, None, :]],
            axis=2,
        )  # (N, 3, 4)
        # noise of marker `single` in the raw residuals: distance row (e_s), offset rows (+n if not marker 0, -n if 0)
        D_s = np.zeros((n_used, m, 3))
        D_s[:, single] = es
        if single == 0:
            D_s[:, m_markers:] = -n[:, None, :]
        else:
            D_s[:, m_markers + single - 1] = n
        cross = -s2 * (Jp @ K @ D_s @ (n[:, :, None] * n[:, None, :]))  # cov(Jp dl, n n^T eps_s)
        nn = n[:, :, None] * n[:, None, :]
        cov_pt = Jp @ cov_l @ np.swapaxes(Jp, -1, -2) + s2 * nn + cross + np.swapaxes(cross, -1, -2)
        point = c + hs[:, None] * n
        return point, n, cov_pt, cov_dir

    H = _normal_matrix(best.sol, whiten)
    lam = np.linalg.eigvalsh(H)
    if lam[0] <= _SINGULAR_REL * max(lam[-1], _TINY):
        raise NotIdentifiableError(
            "the motion does not determine the hinge: the constants are not fixed by the data (no relative "
            "rotation between the links, or a hinge parallel to the line of the two markers); flex the joint "
            "through a range of angles, or add a marker"
        )
    cov = s2 * _sym_inv(H)
    outputs = [world_outputs(cand, cov) for cand in candidates]

    # Equally good, geometrically distinct solutions.
    _, _, cov_pt0, cov_dir0 = outputs[order[0]]
    sd_pt = float(np.median(_max_sd(cov_pt0)))
    sd_dir = float(np.median(_max_sd(cov_dir0)))
    good: list[int] = []
    for i in order:
        if candidates[i].cost - best.cost > AMBIGUITY_CHI2 * s2:
            continue
        pt, dr = outputs[i][0], outputs[i][1]
        distinct = all(
            float(np.median(np.linalg.norm(pt - outputs[j][0], axis=1))) > 3.0 * sd_pt
            or float(np.median(np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", dr, outputs[j][1])), 0.0, 1.0))))
            > 3.0 * sd_dir
            for j in good
        )
        if distinct:
            good.append(i)
    chosen = good[0]
    identifiable, reason = True, ""
    if hint is not None and len(good) > 1:
        align = [float(np.mean(np.abs(np.einsum("ni,ni->n", outputs[i][1], hint[used])))) for i in good]
        ranked = sorted(range(len(good)), key=lambda k: -align[k])
        chosen = good[ranked[0]]
        margin = align[ranked[0]] - align[ranked[1]]
        if margin < 3.0 * sd_dir:
            identifiable = False
            reason = (
                f"{len(good)} hinges fit the data equally well and axis_hint does not separate them (mean "
                f"|cos| to the hint {align[ranked[0]]:.3f} vs {align[ranked[1]]:.3f}); give a hint closer to the "
                "true axis or add a marker (2 + 2)"
            )
    elif len(good) > 1:
        identifiable = False
        reason = (
            f"{len(good)} different hinges fit the data equally well: with 2 + 1 markers the constants are fixed "
            "only up to a discrete choice (two roots of the paper's eq. 13, each with its mirror image); give "
            "axis_hint (a world direction the hinge roughly points along) or add a marker (2 + 2)"
        )
    if hint is not None:
        agree = float(np.mean(np.abs(np.einsum("ni,ni->n", outputs[chosen][1], hint[used]))))
        if identifiable and agree < np.cos(np.deg2rad(HINT_MAX_DEG)):
            identifiable = False
            reason = (
                f"no hinge that fits the data agrees with axis_hint (best mean angle "
                f"{np.rad2deg(np.arccos(min(agree, 1.0))):.0f} deg > {HINT_MAX_DEG:.0f} deg): the data do not "
                "determine the hinge (2 + 1 markers are very noise-sensitive) or the hint is wrong; add a marker"
            )
    cand = candidates[chosen]
    point, direction, cov_pt, cov_dir = outputs[chosen]
    if cand.const is not best.const:
        H = _normal_matrix(cand.sol, whiten)
        cov = s2 * _sym_inv(H)
        point, direction, cov_pt, cov_dir = world_outputs(cand, cov)

    # DH constants and their covariance (numerical Jacobian of the conversion).
    dh = _const_to_dh(cand.const, pair, single, m_markers, length)
    dh[2] = cand.chirality * dh[2]
    jac = np.empty((5, m))
    for j in range(m):
        step = 1e-6 * max(scale, 1.0)
        dp = cand.const.copy()
        dm = cand.const.copy()
        dp[j] += step
        dm[j] -= step
        jac[:, j] = (_const_to_dh(dp, pair, single, m_markers, length) - _const_to_dh(dm, pair, single, m_markers, length)) / (2 * step)
    jac[2] *= cand.chirality
    cov_dh = jac @ cov @ jac.T

    sd_point = float(np.median(_max_sd(cov_pt)))
    sd_direction = float(np.rad2deg(np.median(_max_sd(cov_dir))))
    lever = float(np.median(cand.const[:m_markers]))
    sd_const = float(_max_sd(cov))
    if identifiable and (not np.isfinite(sd_const) or sd_const > SD_REL_MAX * lever):
        identifiable = False
        reason = (
            f"hinge constants poorly determined: their largest standard deviation ({sd_const:.3g}) exceeds "
            f"{SD_REL_MAX:.0%} of the marker distance from the axis ({lever:.3g}); with 2 + 1 markers the hinge is "
            "very sensitive to noise unless the markers are far from the axis and the joint moves through a large "
            "range: add a marker (3 on one link gives a frame)"
        )
    elif identifiable and sd_direction > DIRECTION_SD_MAX_DEG:
        identifiable = False
        reason = (
            f"axis direction poorly determined (typical sd {sd_direction:.3g} deg > {DIRECTION_SD_MAX_DEG} deg); "
            "flex the joint through a larger range, record more frames or add a marker"
        )
    elif identifiable and sd_point > SD_REL_MAX * lever:
        identifiable = False
        reason = (
            f"axis position poorly determined (typical sd {sd_point:.3g} > {SD_REL_MAX:.0%} of the marker "
            f"distance from the axis, {lever:.3g}); flex the joint through a larger range, record more frames or "
            "add a marker"
        )

    def full(values: FloatArray) -> FloatArray:
        out = np.full((n_frames, *values.shape[1:]), np.nan)
        out[used] = values
        return out

    res_norm = np.sqrt(np.sum(cand.sol.r**2, axis=1))
    return MinimalAxisFit(
        radii=cand.const[:m_markers],
        offsets=cand.const[m_markers:],
        cov=cov,
        dh=dh,
        cov_dh=cov_dh,
        point_world=full(point),
        direction_world=full(direction),
        cov_point_world=full(cov_pt),
        cov_direction_world=full(cov_dir),
        residual=full(res_norm),
        rms=float(np.sqrt(np.mean(res_norm**2))),
        n_frames=int(n_used),
        identifiable=identifiable,
        reason=reason,
        noise_std=float(np.sqrt(s2)),
        n_solutions=len(good),
        method="R21",
    )
