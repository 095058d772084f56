"""Rigid poses of marker clusters, body-fixed templates and pose uncertainty.

Section 5 of Stoddart et al. (1999): the pose of a rigid segment in each
frame is the least-squares fit (their eq. 4) of a body-fixed *template* of
marker coordinates to the measured markers, and the template itself is
estimated from the same data by alternating pose and template updates
(their eq. 5). The pose covariance follows Pennec & Thirion (1997), as cited
by Stoddart, for isotropic marker noise.

Conventions
-----------
A pose maps local (template) coordinates to the world:
``world = R_world_local @ local + d_world_local``. Markers are ``(N, P, 3)``
float64 arrays, NaN for a missing marker; units are whatever the input uses.

The local frame of an estimated template (see :func:`template_from_markers`)
has its origin at the template centroid and its axes parallel to the world
axes at the reference frame, so that the pose of the reference frame is a
pure translation (Stoddart's ``f(0) = I`` up to the centroid shift).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import check_markers, valid_mask
from .errors import InputError
from .quaternion_fit import rotations_from_correlations

__all__ = [
    "Poses",
    "poses_from_markers",
    "template_from_markers",
    "noise_std_from_fit",
    "pose_covariance",
    "pose_covariance_local",
    "point_covariance_local",
    "pose_noise_local",
    "skew",
    "lever_jacobian",
    "kabsch",
    "COLLINEAR_RTOL",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: A frame is posed only if the second singular value of its centred visible
#: template points exceeds this fraction of the first. Below it the rotation
#: about the (nearly common) line is fixed by a lever shorter than 1 % of the
#: cluster size, i.e. it is ``100 sigma / size`` radians noisy: meaningless
#: for any realistic cluster, and outside the small-error linearisation.
COLLINEAR_RTOL = 1e-2
#: At least this many visible markers are needed to pose a frame.
MIN_POSE_MARKERS = 3


@dataclass(frozen=True, eq=False)
class Poses:
    """Per-frame rigid poses of one segment.

    Attributes
    ----------
    R_world_local : ndarray, shape (N, 3, 3)
        Rotation from the local (template) frame to the world; NaN where the
        frame could not be posed.
    d_world_local : ndarray, shape (N, 3)
        Translation, input units: ``world = R_world_local @ local + d_world_local``.
        NaN where the frame could not be posed.
    valid : ndarray of bool, shape (N,)
        Frames that were posed (at least 3 visible, non-collinear markers).
    rms : ndarray, shape (N,)
        Rms distance between the measured and the posed template markers over
        the visible markers of each frame, input units; NaN where not posed.
    n_visible : ndarray of int, shape (N,)
        Number of visible (non-NaN) markers in each frame.
    visible : ndarray of bool, shape (N, P)
        Which markers were visible (and used) in each frame.
    """

    R_world_local: FloatArray
    d_world_local: FloatArray
    valid: BoolArray
    rms: FloatArray
    n_visible: NDArray[np.int_]
    visible: BoolArray

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value = np.array(value, copy=True)
                value.setflags(write=False)
                object.__setattr__(self, f.name, value)

    @property
    def n_frames(self) -> int:
        """Number of frames N (posed or not)."""
        return int(self.valid.shape[0])


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrices ``[v]x`` with ``[v]x @ u = v x u``.

    Parameters
    ----------
    v : array_like, shape (..., 3)

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def lever_jacobian(point: ArrayLike) -> FloatArray:
    """``J = [-[p]x, I]`` (3, 6): the error of a body-fixed point ``p`` carried by a pose with local error ``(omega, u)``.

    Parameters
    ----------
    point : array_like, shape (3,)
        The point in the local frame (input units).

    Returns
    -------
    ndarray, shape (3, 6)
        ``J`` such that the point's covariance is ``J W J^T`` for a local pose covariance ``W``
        (:func:`pose_covariance_local`, Notes).
    """
    out: FloatArray = np.concatenate([-skew(point), np.eye(3)], axis=-1)
    return out


def kabsch(y: FloatArray, x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Least-squares pose ``y ~ R x + d`` of fully visible points ``(n, 3)``: ``R`` (3, 3), ``d`` (3,)."""
    xb = x.mean(axis=0)
    yb = y.mean(axis=0)
    U, _, Vt = np.linalg.svd((x - xb).T @ (y - yb))
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0.0:
        Vt[2] = -Vt[2]
        R = Vt.T @ U.T
    return R, yb - R @ xb


def _check_template(template: ArrayLike, n_markers: int | None = None) -> FloatArray:
    """Return the template as finite float64 (P, 3), P >= 3 (and == n_markers when given)."""
    try:
        x = np.array(template, dtype=np.float64, copy=True)
    except (TypeError, ValueError):
        raise InputError(
            f"template: expected a numeric array of shape (P, 3), got {type(template).__name__}"
        ) from None
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"template: expected shape (P, 3), got shape {x.shape}")
    if n_markers is not None and x.shape[0] != n_markers:
        raise InputError(f"template: expected {n_markers} points (one per marker), got {x.shape[0]}")
    if x.shape[0] < MIN_POSE_MARKERS:
        raise InputError(f"template: expected at least {MIN_POSE_MARKERS} points, got {x.shape[0]}")
    if not np.isfinite(x).all():
        raise InputError("template: expected finite coordinates, got NaN or inf")
    return x


def _centred_scatter(points: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted centroid, centred points and scatter per frame.

    ``points`` is (P, 3) (a template, shared by all frames) or (N, P, 3);
    ``w`` is (N, P) of 0/1. Returns ``(mean (N, 3), centred (N, P, 3), scatter (N, 3, 3))``;
    the centred points are zero where ``w`` is 0, the mean is 0 where a frame has no weight.
    """
    n = w.sum(axis=1)
    safe_n = np.where(n > 0, n, 1.0)
    pts = np.broadcast_to(points, (w.shape[0], *points.shape[-2:])) if points.ndim == 2 else points
    pts = np.where(w[..., None] > 0, pts, 0.0)
    mean = np.einsum("np,npi->ni", w, pts) / safe_n[:, None]
    centred = (pts - mean[:, None, :]) * w[..., None]
    scatter = np.einsum("npi,npj->nij", centred, centred)
    return mean, centred, scatter


def _non_collinear(scatter: FloatArray, n: FloatArray) -> BoolArray:
    """Frames with >= 3 points whose second singular value exceeds COLLINEAR_RTOL times the first."""
    lam = np.linalg.eigvalsh(scatter)  # ascending, squares of the singular values
    lam = np.maximum(lam, 0.0)
    return (n >= MIN_POSE_MARKERS) & (lam[:, 2] > 0.0) & (lam[:, 1] > COLLINEAR_RTOL**2 * lam[:, 2])


def _fit_poses(y: FloatArray, vis: BoolArray, x: FloatArray) -> Poses:
    """Batched least-squares fit of template ``x`` (P, 3) to ``y`` (N, P, 3) on the ``vis`` markers (no checks).

    The rotation is Horn's (:func:`~jointfit_core.quaternion_fit.rotations_from_correlations`),
    the same optimum as Kabsch's SVD with the reflection excluded.
    """
    w = vis.astype(np.float64)
    n = w.sum(axis=1)
    xbar, xc, scat_x = _centred_scatter(x, w)
    ok = _non_collinear(scat_x, n)
    yz = np.where(vis[..., None], y, 0.0)
    ybar = (w[:, None, :] @ yz)[:, 0] / np.where(n > 0, n, 1.0)[:, None]
    x_ok, y_ok, ybar_ok = xc[ok], yz[ok], ybar[ok]
    # Correlation sum_i x_i y_i^T: x is centred (and zero where unused), so y needs no centring.
    S = np.swapaxes(x_ok, 1, 2) @ y_ok
    yy = np.einsum("npi,npi->n", y_ok, y_ok) - n[ok] * np.einsum("ni,ni->n", ybar_ok, ybar_ok)
    xx = np.einsum("npi,npi->n", x_ok, x_ok)
    R = np.full((y.shape[0], 3, 3), np.nan)
    R[ok] = rotations_from_correlations(S, 0.5 * (xx + yy))[0]
    d = ybar - (R @ xbar[:, :, None])[:, :, 0]
    pred = R @ x.T + d[:, :, None]  # (N, 3, P)
    res = np.where(vis[..., None], y - np.swapaxes(pred, 1, 2), 0.0)
    ss = np.einsum("npi,npi->n", res, res)
    rms = np.sqrt(ss / np.where(n > 0, n, 1.0))
    d[~ok] = np.nan
    rms[~ok] = np.nan
    return Poses(
        R_world_local=R,
        d_world_local=d,
        valid=ok,
        rms=rms,
        n_visible=vis.sum(axis=1).astype(np.int_),
        visible=vis,
    )


def poses_from_markers(markers: ArrayLike, template: ArrayLike) -> Poses:
    """Least-squares rigid pose of a template in every frame (Stoddart eq. 4).

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Measured marker positions, world frame, any length unit; NaN marks a
        missing marker.
    template : array_like, shape (P, 3)
        Body-fixed marker coordinates (local frame, same unit), e.g. from
        :func:`template_from_markers`.

    Returns
    -------
    Poses
        ``R_world_local`` (N, 3, 3) and ``d_world_local`` (N, 3) with
        ``world = R @ local + d``, the per-frame ``valid`` flag, fit ``rms``
        (input units) and visibility.

    Raises
    ------
    InputError
        Wrong shapes, fewer than 3 markers, a template that does not match
        the markers, infinite values or all-NaN markers.

    Notes
    -----
    Implements Stoddart et al. (1999) eq. (4), solved in closed form
    (Kanatani 1994; Umeyama's SVD with the determinant correction so that
    ``R`` is a proper rotation) on the visible markers of each frame, all
    frames at once with a batched SVD of the (N, 3, 3) cross-covariances.
    A frame is posed only with at least 3 visible markers whose template
    points are not collinear: the second singular value of the centred
    visible template points must exceed :data:`COLLINEAR_RTOL` (1 %) of the
    first. Other frames get ``valid=False`` and NaN poses.

    The pose uncertainty is given by :func:`pose_covariance`.
    """
    y = check_markers(markers, name="markers", min_markers=MIN_POSE_MARKERS)
    x = _check_template(template, y.shape[1])
    return _fit_poses(y, valid_mask(y), x)


def _reference_frame(y: FloatArray, vis: BoolArray) -> int:
    """First frame with the most visible markers among frames that can be posed (non-collinear)."""
    w = vis.astype(np.float64)
    _, _, scat = _centred_scatter(y, w)
    n = w.sum(axis=1)
    ok = _non_collinear(scat, n)
    if not ok.any():
        raise InputError(
            "markers: no frame has at least 3 visible, non-collinear markers; a rigid template needs one"
        )
    score = np.where(ok, n, -1.0)
    return int(np.argmax(score))


def _back_projected_mean(y: FloatArray, vis: BoolArray, poses: Poses) -> tuple[FloatArray, FloatArray]:
    """Mean over posed frames of ``R^T (y_i - d)`` per marker (Stoddart eq. 5) and the sample counts."""
    use = vis & poses.valid[:, None]
    R = np.where(poses.valid[:, None, None], poses.R_world_local, 0.0)
    d = np.where(poses.valid[:, None], poses.d_world_local, 0.0)
    diff = np.where(use[..., None], y - d[:, None, :], 0.0)
    local = np.einsum("nji,npj->npi", R, diff)  # R^T (y - d)
    count = use.sum(axis=0).astype(np.float64)
    total = local.sum(axis=0)
    mean = total / np.where(count > 0, count, 1.0)[:, None]
    return mean, count


def _anchor(x: FloatArray, y: FloatArray, vis: BoolArray, ref: int) -> FloatArray:
    """Re-anchor a template: centroid at the origin, axes parallel to the world at frame ``ref``.

    ``ref`` is a frame with at least 3 visible non-collinear markers; the template is rotated by the
    Kabsch rotation of that frame, so that the frame's pose becomes a pure translation.
    """
    x = x - x.mean(axis=0)
    sel = vis[ref]
    xv = x[sel] - x[sel].mean(axis=0)
    yv = y[ref, sel] - y[ref, sel].mean(axis=0)
    U, _, Vt = np.linalg.svd(xv.T @ yv)
    D = np.diag([1.0, 1.0, 1.0 if np.linalg.det(Vt.T @ U.T) >= 0.0 else -1.0])
    R_ref = Vt.T @ D @ U.T
    result: FloatArray = x @ R_ref.T  # R_ref x_i: then the reference pose has R = I
    return result


def template_from_markers(markers: ArrayLike, *, max_iter: int = 20, tol: float = 1e-10) -> FloatArray:
    """Estimate the body-fixed marker template of a rigid segment (Stoddart eq. 4-5).

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Marker positions of one rigid segment, world frame, any length unit;
        NaN marks a missing marker.
    max_iter : int
        Maximum number of accelerated cycles (each makes two or three pose
        <-> template steps).
    tol : float
        Convergence tolerance, relative: stop when a step moves no template
        point by more than ``tol`` times the template's rms radius.

    Returns
    -------
    ndarray, shape (P, 3)
        Template (local coordinates, input units).

    Raises
    ------
    InputError
        Wrong shape, fewer than 3 markers, all-NaN input, a marker that is
        never visible (or never in a frame that can be posed), or no frame
        with 3 visible non-collinear markers.

    Notes
    -----
    Implements Stoddart et al. (1999) section 5. The template starts as the
    markers of the *reference frame*: the first frame in which all markers
    are visible or, if there is none, the first frame with the most visible
    (non-collinear) markers; markers missing there are filled in from the
    frames posed with the known ones. Then, until converged, (1) every frame
    is posed with the current template (eq. 4, :func:`poses_from_markers`),
    (2) each template point becomes the mean over the posed frames where the
    marker is visible of ``R^T (y_i - d)`` (eq. 5). This alternation is a
    block-coordinate descent of the joint least-squares cost of all poses
    and the template, so it never increases it. With all markers visible it
    converges in a few steps (as Stoddart reports); with occlusions the
    convergence is linear and slower (a factor ~0.3 per step at 15 %
    occlusion), so the steps are accelerated with SQUAREM (Varadhan &
    Roland 2008), an extrapolation that is kept only if it lowers the cost.

    **Local frame convention.** After every iteration the template is
    re-anchored: shifted so that its centroid is the origin, and rotated so
    that the pose of the reference frame has ``R_world_local = I``. The
    local axes are therefore parallel to the world axes at the reference
    frame, Stoddart's ``f(0) = I`` up to the centroid shift (Stoddart puts
    the origin at the world origin; a centroid origin keeps the pose
    rotation and translation errors uncorrelated, see
    :func:`pose_covariance`). Applying a rigid transform ``(R_g, d_g)`` to
    all markers therefore maps the template to ``R_g @ template``.
    """
    y = check_markers(markers, name="markers", min_markers=MIN_POSE_MARKERS)
    if not (isinstance(max_iter, int | np.integer) and max_iter >= 1):
        raise InputError(f"max_iter: expected an integer >= 1, got {max_iter!r}")
    if not (np.isfinite(tol) and tol >= 0.0):
        raise InputError(f"tol: expected a finite number >= 0, got {tol!r}")
    vis = valid_mask(y)
    never = np.flatnonzero(~vis.any(axis=0))
    if never.size:
        raise InputError(
            f"markers: marker(s) {never.tolist()} are never visible (all NaN); remove them or give data"
        )
    ref = _reference_frame(y, vis)

    # Initial template from the reference frame; fill markers missing there from frames posed with the others.
    known = vis[ref].copy()
    x = np.where(known[:, None], y[ref], 0.0)
    while not known.all():
        poses = _fit_poses(y, vis & known[None, :], x)
        mean, count = _back_projected_mean(y, vis, poses)
        new = ~known & (count > 0)
        if not new.any():
            missing = np.flatnonzero(~known).tolist()
            raise InputError(
                f"markers: marker(s) {missing} are never visible in a frame that also shows 3 non-collinear "
                "markers of the rest of the segment, so their template position cannot be estimated"
            )
        x[new] = mean[new]
        known |= new

    x = _anchor(x, y, vis, ref)
    for _ in range(max_iter):
        # One SQUAREM cycle (Varadhan & Roland 2008) around the pose <-> template step.
        x1, _ = _template_step(y, vis, x, ref)
        r = x1 - x
        scale = float(np.sqrt(np.mean(np.sum(x1 * x1, axis=1))))
        if float(np.max(np.abs(r))) <= tol * scale:
            x = x1
            break
        x2, cost1 = _template_step(y, vis, x1, ref)
        v = x2 - 2.0 * x1 + x
        norm_v = float(np.linalg.norm(v))
        alpha = min(-float(np.linalg.norm(r)) / norm_v, -1.0) if norm_v > 0.0 else -1.0
        x_next = x2
        if alpha < -1.0:
            x3, cost_extra = _template_step(y, vis, x - 2.0 * alpha * r + alpha * alpha * v, ref)
            if cost_extra <= cost1:  # keep the descent: accept the extrapolation only if it helped
                x_next = x3
        x = x_next
    return x


def _template_step(y: FloatArray, vis: BoolArray, x: FloatArray, ref: int) -> tuple[FloatArray, float]:
    """Stoddart's eq. (4) then (5) and the re-anchoring; returns the new template and the cost at ``x``."""
    poses = _fit_poses(y, vis, x)
    cost = float(np.sum((poses.rms**2 * poses.n_visible)[poses.valid]))
    mean, count = _back_projected_mean(y, vis, poses)
    x_new = np.where(count[:, None] > 0, mean, x)
    return _anchor(x_new, y, vis, ref), cost


def noise_std_from_fit(
    markers: ArrayLike, template: ArrayLike, poses: Poses | None = None, *, template_estimated: bool = True
) -> float:
    """Pooled marker noise standard deviation per coordinate from pose-fit residuals.

    Parameters
    ----------
    markers : array_like, shape (N, P, 3)
        Marker positions, world frame, input units; NaN for missing.
    template : array_like, shape (P, 3)
        The template the poses were fitted with.
    poses : Poses, optional
        Poses of ``template`` to ``markers``; computed when not given.
    template_estimated : bool
        Whether ``template`` was estimated from these same markers
        (:func:`template_from_markers`); its ``3 P - 6`` free shape
        parameters are then removed from the degrees of freedom.

    Returns
    -------
    float
        ``sigma`` in input units (per coordinate; ``sqrt(tr W_y) = sqrt(3) sigma``).

    Raises
    ------
    InputError
        No residual degree of freedom is left (too few posed frames).

    Notes
    -----
    ``sigma^2 = SS / dof`` with ``SS`` the sum of squared residuals
    ``|y_i - R x_i - d|^2`` over the visible markers of the posed frames and
    ``dof = sum_t (3 n_t - 6) - (3 P - 6)``: each pose uses 6 parameters and
    an estimated template ``3 P - 6`` more (its 6 rigid degrees of freedom
    are fixed by the frame convention). Unbiased to first order for
    isotropic Gaussian noise; skin motion or a non-rigid cluster inflates it.
    """
    y = check_markers(markers, name="markers", min_markers=MIN_POSE_MARKERS)
    x = _check_template(template, y.shape[1])
    p = _fit_poses(y, valid_mask(y), x) if poses is None else poses
    if p.valid.shape[0] != y.shape[0]:
        raise InputError(f"poses: expected {y.shape[0]} frames (as markers), got {p.valid.shape[0]}")
    use = p.visible & p.valid[:, None]
    R = np.where(p.valid[:, None, None], p.R_world_local, 0.0)
    d = np.where(p.valid[:, None], p.d_world_local, 0.0)
    pred = np.einsum("nij,pj->npi", R, x) + d[:, None, :]
    res = np.where(use[..., None], y - pred, 0.0)
    ss = float(np.sum(res * res))
    n_vis = use.sum(axis=1)[p.valid]
    dof = float(np.sum(3 * n_vis - 6)) - (3.0 * x.shape[0] - 6.0 if template_estimated else 0.0)
    if dof <= 0.0:
        raise InputError(
            f"markers: too few posed frames to estimate the marker noise (residual degrees of freedom {dof:g}); "
            "give more frames"
        )
    return float(np.sqrt(ss / dof))


def _visible_template_inertia(x: FloatArray, visible: BoolArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Centroid (..., 3), count (...) and inertia-like tensor (..., 3, 3) of the visible template points."""
    w = visible.astype(np.float64)
    n = w.sum(axis=-1)
    safe_n = np.where(n > 0, n, 1.0)
    xbar = np.einsum("...p,pi->...i", w, x) / safe_n[..., None]
    xc = (x - xbar[..., None, :]) * w[..., None]
    sq = np.einsum("...pi,...pi->...", xc, xc)
    inertia = sq[..., None, None] * np.eye(3) - np.einsum("...pi,...pj->...ij", xc, xc)
    return xbar, n, inertia


def _pose_ok(x: FloatArray, visible: BoolArray) -> BoolArray:
    w = visible.reshape(-1, visible.shape[-1]).astype(np.float64)
    _, _, scat = _centred_scatter(x, w)
    ok: BoolArray = _non_collinear(scat, w.sum(axis=1)).reshape(visible.shape[:-1])
    return ok


def _check_noise(noise_std: float) -> float:
    try:
        s = float(noise_std)
    except (TypeError, ValueError):
        raise InputError(f"noise_std: expected a number >= 0, got {noise_std!r}") from None
    if not (np.isfinite(s) and s >= 0.0):
        raise InputError(f"noise_std: expected a finite number >= 0, got {noise_std!r}")
    return s


def pose_noise_local(
    template: ArrayLike, noise_std: float, visible: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Pose noise about the visible template centroid, local frame.

    Parameters
    ----------
    template : array_like, shape (P, 3)
        Template (local frame, input units).
    noise_std : float
        Marker noise standard deviation per coordinate, input units.
    visible : array_like of bool, shape (..., P), optional
        Markers used in the fit (default: all).

    Returns
    -------
    centroid_local : ndarray, shape (..., 3)
        Centroid ``xbar`` of the visible template points (input units).
    cov_rot_local : ndarray, shape (..., 3, 3)
        ``sigma^2 I_vis^-1``: covariance of the small local rotation
        ``omega`` (radians) about that centroid, ``R_est = R exp([omega]x)``.
    var_translation : ndarray, shape (...)
        ``sigma^2 / n_vis``: variance per coordinate of the centroid's
        translation, independent of ``omega`` (input units squared).

    Notes
    -----
    The estimated pose carries a body-fixed point ``p`` to
    ``R exp([omega]x) (p - xbar) + R xbar + d + R u`` with ``omega`` and ``u``
    independent and zero-mean (Pennec & Thirion; see
    :func:`pose_covariance`). NaN where the visible markers cannot be posed.
    """
    x = _check_template(template)
    s2 = _check_noise(noise_std) ** 2
    vis = np.ones(x.shape[0], dtype=bool) if visible is None else np.asarray(visible, dtype=bool)
    if vis.shape[-1] != x.shape[0]:
        raise InputError(f"visible: expected a last axis of {x.shape[0]} (markers), got shape {vis.shape}")
    xbar, n, inertia = _visible_template_inertia(x, vis)
    ok = _pose_ok(x, vis)
    inertia = np.where(ok[..., None, None], inertia, np.eye(3))
    cov_rot = np.asarray(s2 * np.linalg.inv(inertia), dtype=np.float64)
    var_u = s2 / np.where(ok, n, 1.0)
    cov_rot[~ok] = np.nan
    xbar = np.where(ok[..., None], xbar, np.nan)
    var_u = np.where(ok, var_u, np.nan)
    return xbar, cov_rot, var_u


def pose_covariance_local(
    template: ArrayLike, noise_std: float, visible: ArrayLike | None = None
) -> FloatArray:
    """Pose covariance in the local frame, about the local origin.

    Parameters
    ----------
    template : array_like, shape (P, 3)
        Template (local frame, input units).
    noise_std : float
        Marker noise standard deviation per coordinate, input units.
    visible : array_like of bool, shape (..., P), optional
        Markers used in the fit (default: all). A leading frame axis gives
        one covariance per frame.

    Returns
    -------
    ndarray, shape (..., 6, 6)
        Covariance of ``(omega, u)``, where the estimated pose is the true one
        followed by a small local rotation and translation,
        ``R_est = R exp([omega]x)``, ``world = R_est @ local + d + R @ u``:
        ``omega`` in radians (local frame), ``u`` in input units (local
        frame). NaN where the visible markers cannot be posed.

    Notes
    -----
    A body-fixed point ``p`` (local) is then carried to the world with the
    error ``R (-[p]x omega + u)``, i.e. covariance ``J Sigma J^T`` with
    ``J = [-[p]x, I]`` in the local frame (see
    :func:`point_covariance_local`). Derived from :func:`pose_covariance`
    (Pennec & Thirion): about the visible centroid ``xbar`` the rotation and
    translation are independent, ``cov(omega) = sigma^2 I_vis^-1`` with
    ``I_vis = sum_i (|x_i - xbar|^2 I - (x_i - xbar)(x_i - xbar)^T)`` and
    ``cov(u_centroid) = sigma^2 / n_vis I``; moving the reference point to
    the origin gives ``u = u_centroid + [xbar]x omega``. Scales with
    ``sigma^2``; the rotation part with the inverse square of the cluster size.
    """
    x = _check_template(template)
    s2 = _check_noise(noise_std) ** 2
    vis = np.ones(x.shape[0], dtype=bool) if visible is None else np.asarray(visible, dtype=bool)
    if vis.shape[-1] != x.shape[0]:
        raise InputError(f"visible: expected a last axis of {x.shape[0]} (markers), got shape {vis.shape}")
    xbar, n, inertia = _visible_template_inertia(x, vis)
    ok = _pose_ok(x, vis)
    inertia = np.where(ok[..., None, None], inertia, np.eye(3))
    cov_rot = s2 * np.linalg.inv(inertia)
    cov_u0 = s2 / np.where(ok, n, 1.0)[..., None, None] * np.eye(3)
    K = skew(xbar)
    out = np.empty((*vis.shape[:-1], 6, 6))
    out[..., :3, :3] = cov_rot
    out[..., :3, 3:] = cov_rot @ np.swapaxes(K, -1, -2)
    out[..., 3:, :3] = K @ cov_rot
    out[..., 3:, 3:] = K @ cov_rot @ np.swapaxes(K, -1, -2) + cov_u0
    out[~ok] = np.nan
    return out


def point_covariance_local(
    template: ArrayLike, point_local: ArrayLike, noise_std: float, visible: ArrayLike | None = None
) -> FloatArray:
    """Covariance of a body-fixed point carried to the world by the estimated pose, local frame.

    Parameters
    ----------
    template : array_like, shape (P, 3)
        Template, local frame, input units.
    point_local : array_like, shape (3,)
        The body-fixed point (e.g. a joint centre), local frame, input units.
    noise_std : float
        Marker noise standard deviation per coordinate, input units.
    visible : array_like of bool, shape (..., P), optional
        Markers used in the pose fit (default all).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``W = sigma^2 ([a]x I_vis^-1 [a]x^T + I / n_vis)`` with
        ``a = point_local - xbar_vis``, expressed in the local frame
        (rotate with ``R_world_local`` for the world frame). NaN where the
        visible markers cannot be posed.

    Notes
    -----
    Pennec & Thirion's pose covariance (see :func:`pose_covariance_local`)
    propagated to the point: the error of the carried point is
    ``-[a]x omega + u_centroid``. It grows with the square of the lever
    ``|a|`` from the visible template centroid to the point.
    """
    p = np.asarray(point_local, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise InputError(f"point_local: expected a finite 3-vector, got {point_local!r}")
    cov6 = pose_covariance_local(template, noise_std, visible)
    J = lever_jacobian(p)
    out: FloatArray = J @ cov6 @ J.T
    return out


def pose_covariance(template: ArrayLike, poses: Poses, noise_std: float) -> FloatArray:
    """Per-frame pose covariance in the world frame (Pennec & Thirion 1997).

    Parameters
    ----------
    template : array_like, shape (P, 3)
        Template used for the poses (local frame, input units).
    poses : Poses
        Poses from :func:`poses_from_markers`.
    noise_std : float
        Marker noise standard deviation per coordinate (isotropic), input units.

    Returns
    -------
    ndarray, shape (N, 6, 6)
        Covariance of ``(r, u)``: ``r`` the small world-frame rotation vector
        (radians) with ``R_est = exp([r]x) R``, the rotation being about the
        centroid of the visible markers, and ``u`` the translation of that
        centroid (world, input units). NaN for frames that were not posed.

    Notes
    -----
    Linearised least squares of eq. (4) of Stoddart et al. (1999) for
    isotropic noise ``sigma^2`` per coordinate, as in Pennec & Thirion (1997):
    with ``z_i = R (x_i - xbar_vis)`` over the visible markers,
    ``cov(r) = sigma^2 (sum_i |z_i|^2 I - z_i z_i^T)^-1`` and
    ``cov(u) = sigma^2 / n_vis I``, independent (the normal matrix is block
    diagonal because ``sum_i z_i = 0``). Scales with ``sigma^2``, the rotation
    part with the inverse square of the cluster size. The template error
    (``~ sigma / sqrt(N)``) is ignored.
    """
    x = _check_template(template)
    s2 = _check_noise(noise_std) ** 2
    if poses.visible.shape[1] != x.shape[0]:
        raise InputError(
            f"poses: expected {x.shape[0]} markers (as the template), got {poses.visible.shape[1]}"
        )
    cov_local = pose_covariance_local(x, noise_std, poses.visible)
    # Rotation about the centroid: cov(omega) in local; world r = R omega.
    R = np.where(poses.valid[:, None, None], poses.R_world_local, 0.0)
    out = np.zeros((poses.n_frames, 6, 6))
    cov_rot_local = np.where(poses.valid[:, None, None], cov_local[:, :3, :3], 0.0)
    out[:, :3, :3] = R @ cov_rot_local @ np.swapaxes(R, -1, -2)
    n = np.where(poses.valid, poses.n_visible, 1).astype(np.float64)
    out[:, 3:, 3:] = (s2 / n)[:, None, None] * np.eye(3)
    out[~poses.valid] = np.nan
    return out
