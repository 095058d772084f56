"""Joint angles from relative segment poses: a hinge's turn about its axis, a ball joint's Cardan angles.

Every function takes the relative rotation ``Q`` of a frame, child template
frame to parent template frame (``x_parent = Q x_child + t``, the relative
pose the estimators keep; ``Q = R_world_parent^T R_world_child``), and is
vectorised over any leading axes (frames, joints).

**Reference pose.** Every angle is zero at ``Q = I``: where the child's
template frame has the parent's orientation. A segment's template frame has
the world axes at the segment's first template frame (the first fully
visible frame; :class:`~jointfit_core.estimator.OnlineJoint`), so when both
segments' templates start with the same frame (the usual case: all markers
visible at the start) the angles are zero at that frame's posture.

**Hinge.** The twist of ``Q`` about the unit axis ``a`` (parent frame, the
direction the node publishes on ``<joint>/axis``, sign as configured): the
angle of the rotation about ``a`` in the swing-twist decomposition
``Q = Q_swing Rot(a, theta)``-like, ``theta = 2 atan2(a . vee(Q - Q^T), 1 + tr Q)``
in ``(-pi, pi]``; positive is a right-handed turn of the child about ``a``.
For a pure rotation about ``a`` it is that rotation's angle; a rotation off
the axis (noise, a tilted estimate) leaves it unchanged to first order.

**Ball.** Intrinsic X-Y-Z Cardan angles ``(alpha, beta, gamma)`` of ``Q``,
``Q = Rx(alpha) Ry(beta) Rz(gamma)`` about the parent template frame's x,
then the new y, then the new z (the URDF chain of
:mod:`jointfit_core.urdf`); ``beta`` in ``[-pi/2, pi/2]``, the others in
``(-pi, pi]``. Gimbal lock at ``beta = +-pi/2``: ``alpha`` and ``gamma`` are
then not separable (only their sum or difference is), and near it they
change fast and are poorly determined.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .checks import as_real_array
from .errors import InputError

__all__ = [
    "hinge_angle",
    "hinge_angle_sd",
    "cardan_xyz",
    "rotation_from_cardan_xyz",
    "angle_rates",
    "relative_rotation_cov",
]

FloatArray = NDArray[np.float64]


def _check_rotations(Q: ArrayLike) -> FloatArray:
    q = as_real_array(Q, name="Q", expected="rotations of shape (..., 3, 3)")
    if q.ndim < 2 or q.shape[-2:] != (3, 3):
        raise InputError(f"Q: expected rotations of shape (..., 3, 3), got shape {q.shape}")
    return q


def _vee_antisym(Q: FloatArray) -> FloatArray:
    """``vee(Q - Q^T)``, shape (..., 3): ``2 sin(theta) a`` for a rotation by ``theta`` about ``a``."""
    return np.stack(
        [Q[..., 2, 1] - Q[..., 1, 2], Q[..., 0, 2] - Q[..., 2, 0], Q[..., 1, 0] - Q[..., 0, 1]], axis=-1
    )


def hinge_angle(Q: ArrayLike, direction: ArrayLike) -> FloatArray:
    """Turn of the child about a hinge axis (rad), zero at ``Q = I``.

    Parameters
    ----------
    Q : array_like, shape (..., 3, 3)
        Relative rotation, child template frame to parent template frame.
    direction : array_like, shape (..., 3)
        Unit hinge axis in the parent template frame (broadcast against ``Q``).

    Returns
    -------
    ndarray, shape (...)
        Twist angle about ``direction``, in ``(-pi, pi]``, right-handed.
    """
    q = _check_rotations(Q)
    a = as_real_array(direction, name="direction", expected="unit axes of shape (..., 3)")
    s = _vee_antisym(q)
    c = 1.0 + q[..., 0, 0] + q[..., 1, 1] + q[..., 2, 2]
    out: FloatArray = 2.0 * np.arctan2((a * s).sum(axis=-1), c)
    return out


def relative_rotation_cov(
    Q: ArrayLike, cov_rot_parent: ArrayLike, cov_rot_child: ArrayLike
) -> FloatArray:
    """Covariance (rad^2) of the relative rotation's error, as a left perturbation in the parent template frame.

    Parameters
    ----------
    Q : array_like, shape (..., 3, 3)
    cov_rot_parent, cov_rot_child : array_like, shape (..., 3, 3)
        Covariances of each segment pose's rotation error ``omega`` in its own
        template frame (``R_est = R exp([omega]x)``; the rotation block of
        :func:`~jointfit_core.pose.pose_covariance_local` times the noise variance).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``cov_rot_parent + Q cov_rot_child Q^T``: ``Q_est = exp([Q omega_c - omega_p]x) Q``
        to first order, the two poses' errors independent.
    """
    q = _check_rotations(Q)
    out: FloatArray = np.asarray(cov_rot_parent, dtype=np.float64) + q @ np.asarray(
        cov_rot_child, dtype=np.float64
    ) @ np.swapaxes(q, -1, -2)
    return out


def hinge_angle_sd(
    Q: ArrayLike, direction: ArrayLike, cov_direction: ArrayLike, cov_rotation: ArrayLike
) -> FloatArray:
    """Standard deviation (rad) of :func:`hinge_angle` from the axis estimate and the frame's pose noise.

    Parameters
    ----------
    Q : array_like, shape (..., 3, 3)
        Relative rotation, child template frame to parent template frame.
    direction : array_like, shape (..., 3)
        Unit axis, parent template frame.
    cov_direction : array_like, shape (..., 3, 3)
        Its covariance (rank 2, tangent to the unit sphere).
    cov_rotation : array_like, shape (..., 3, 3)
        Covariance of this frame's relative rotation (:func:`relative_rotation_cov`).

    Returns
    -------
    ndarray, shape (...)
        ``sqrt(g^T C_a g + a^T C_Q a)``: first-order propagation of both.

    Notes
    -----
    With ``theta = 2 atan2(a . s, c)`` (``s = vee(Q - Q^T)``, ``c = 1 + tr Q``),
    ``d theta / d a = 2 c s / (c^2 + (a . s)^2)``, projected on the plane
    normal to ``a`` (the axis covariance has no radial part). For a pure
    rotation about ``a``, ``s`` is along ``a`` and the axis term vanishes: the
    axis error only matters as far as the motion leaves the axis (it then
    mixes swing into the angle). A left perturbation ``exp([delta]x) Q``
    changes the twist by ``a . delta`` to first order at a pure hinge rotation,
    giving the pose term. The two errors are taken as independent (the
    estimate comes from a whole window, the pose noise from one frame).
    """
    q = _check_rotations(Q)
    a = as_real_array(direction, name="direction", expected="unit axes of shape (..., 3)")
    s = _vee_antisym(q)
    c = 1.0 + q[..., 0, 0] + q[..., 1, 1] + q[..., 2, 2]
    y = (a * s).sum(axis=-1)
    grad = 2.0 * c[..., None] * s / (c * c + y * y)[..., None]
    grad = grad - a * (grad * a).sum(axis=-1, keepdims=True)
    Ca = np.asarray(cov_direction, dtype=np.float64)
    CQ = np.asarray(cov_rotation, dtype=np.float64)
    var = np.einsum("...i,...ij,...j->...", grad, Ca, grad) + np.einsum("...i,...ij,...j->...", a, CQ, a)
    out: FloatArray = np.sqrt(np.maximum(var, 0.0))
    return out


def cardan_xyz(Q: ArrayLike) -> FloatArray:
    """Intrinsic X-Y-Z Cardan angles (rad) of the relative rotation: ``Q = Rx(a) Ry(b) Rz(c)``.

    Parameters
    ----------
    Q : array_like, shape (..., 3, 3)
        Relative rotation, child template frame to parent template frame.

    Returns
    -------
    ndarray, shape (..., 3)
        ``(alpha, beta, gamma)``: about the parent's x, the once-turned y, the
        twice-turned z (the child's z); ``beta`` in ``[-pi/2, pi/2]``. At gimbal
        lock (``|beta| = pi/2``) ``alpha`` and ``gamma`` are not separable; the
        formula then still returns finite numbers whose product ``Rx Ry Rz``
        is ``Q`` only up to rounding.
    """
    q = _check_rotations(Q)
    beta = np.arcsin(np.clip(q[..., 0, 2], -1.0, 1.0))
    alpha = np.arctan2(-q[..., 1, 2], q[..., 2, 2])
    gamma = np.arctan2(-q[..., 0, 1], q[..., 0, 0])
    out: FloatArray = np.stack([alpha, beta, gamma], axis=-1)
    return out


def rotation_from_cardan_xyz(angles: ArrayLike) -> FloatArray:
    """``Rx(alpha) Ry(beta) Rz(gamma)`` of intrinsic X-Y-Z Cardan angles (rad), shape (..., 3) -> (..., 3, 3)."""
    ang = as_real_array(angles, name="angles", expected="angles of shape (..., 3)")
    if ang.shape[-1:] != (3,):
        raise InputError(f"angles: expected shape (..., 3), got {ang.shape}")
    ca, sa = np.cos(ang[..., 0]), np.sin(ang[..., 0])
    cb, sb = np.cos(ang[..., 1]), np.sin(ang[..., 1])
    cc, sc = np.cos(ang[..., 2]), np.sin(ang[..., 2])
    out = np.empty((*ang.shape[:-1], 3, 3))
    out[..., 0, 0] = cb * cc
    out[..., 0, 1] = -cb * sc
    out[..., 0, 2] = sb
    out[..., 1, 0] = ca * sc + sa * sb * cc
    out[..., 1, 1] = ca * cc - sa * sb * sc
    out[..., 1, 2] = -sa * cb
    out[..., 2, 0] = sa * sc - ca * sb * cc
    out[..., 2, 1] = sa * cc + ca * sb * sc
    out[..., 2, 2] = ca * cb
    return out


def angle_rates(angles: ArrayLike, stamps: ArrayLike) -> FloatArray:
    """Angular velocities (rad/s) by backward differences over the stamps, across the +-pi wrap.

    Parameters
    ----------
    angles : array_like, shape (N, ...)
        Angles per frame (rad); NaN where a frame has none.
    stamps : array_like, shape (N,)
        Frame times (s), increasing.

    Returns
    -------
    ndarray, shape (N, ...)
        ``(angle_k - angle_{k-1}) / (t_k - t_{k-1})`` with the difference
        wrapped into ``(-pi, pi]``; NaN in the first frame and wherever
        either frame's angle is NaN (the online node does the same from the
        last frame it had).
    """
    ang = np.asarray(angles, dtype=np.float64)
    t = np.asarray(stamps, dtype=np.float64)
    if t.ndim != 1 or ang.shape[:1] != t.shape:
        raise InputError(f"stamps: expected shape ({ang.shape[0] if ang.ndim else 0},), got {t.shape}")
    out = np.full(ang.shape, np.nan)
    if t.size < 2:
        return out
    dt = np.diff(t).reshape((-1,) + (1,) * (ang.ndim - 1))
    step = np.diff(ang, axis=0)
    step = (step + np.pi) % (2.0 * np.pi) - np.pi
    with np.errstate(invalid="ignore", divide="ignore"):
        out[1:] = np.where(dt > 0.0, step / np.where(dt > 0.0, dt, 1.0), np.nan)
    return out
