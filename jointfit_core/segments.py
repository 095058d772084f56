"""Joints between two moving segments from their rigid poses (Stoddart et al. 1999).

Each segment (at least 3 markers) gets a template and per-frame poses
(:mod:`jointfit_core.pose`). With the parent pose ``(R_p, d_p)`` and the child
pose ``(R_c, d_c)`` of frame t (``world = R @ local + d``), the relative pose is

``Q_t = R_p^T R_c`` (child-to-parent rotation) and ``t_t = R_p^T (d_c - d_p)``.

A ball joint at ``c_p`` (parent local frame) and ``c_c`` (child local frame)
satisfies ``R_p c_p + d_p = R_c c_c + d_c``, i.e. ``c_p = Q_t c_c + t_t``. This
is Stoddart's eq. (2)/(9) with two distinct local frames; Stoddart chooses both
body frames equal to the world at t = 0, which makes ``c_p = c_c`` and halves
the unknowns. Here each local frame is its template's frame (origin at the
template centroid, axes parallel to the world at its reference frame, see
:func:`jointfit_core.pose.template_from_markers`), so the two centres differ
and the unknown is the 6-vector ``a = (c_p, c_c)``.

The closed form needs only running sums of the relative poses
(:class:`PoseSums`, :func:`centre_from_pose_sums`), so an online estimator can
add and remove frames in O(1).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .artefact import (
    ArtefactCovariance,
    artefact_covariance,
    check_attachment,
    deformation_weights,
    joint_features,
    white_noise_std,
)
from .checks import check_markers, check_vector3
from .errors import InputError, NotIdentifiableError
from .identifiability import check_marker_counts
from .model_error import Inflation, residual_inflation
from .pose import (
    Poses,
    lever_jacobian,
    noise_std_from_fit,
    point_covariance_local,
    pose_covariance_local,
    pose_noise_local,
    poses_from_markers,
    skew,
    template_from_markers,
)
from .results import SegmentsAxisFit, SegmentsCentreFit

__all__ = [
    "PoseSums",
    "PoseSumsCentre",
    "relative_poses",
    "pose_sums_from_relative",
    "centre_from_pose_sums",
    "debiased_sums",
    "first_order_bias_step",
    "gauge_free_pinv",
    "normal_matrix",
    "noise_bias_matrices",
    "svd3",
    "fit_centre_two_segments",
    "fit_axis_two_segments",
    "SINGULAR_REL",
    "CENTRE_SD_REL_MAX",
    "centre_sd_limit",
    "SD_REL_MAX",
    "AXIS_SD_MAX_DEG",
    "SINGLE_AXIS_RATIO",
    "NOISE_SNR_MIN",
    "POSE_VAR_RATIO_MAX",
    "POSE_ROT_SD_MAX",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: The joint is "not determined at all" (NotIdentifiableError) when the
#: smallest eigenvalue of the normal matrix is below this fraction of N, i.e.
#: when ``1 - s_1 / N < SINGULAR_REL`` for the top singular value of ``sum Q``.
SINGULAR_REL = 1e-10
#: An axis point whose largest standard deviation exceeds this fraction of the
#: lever arm (distance from a template centroid to the joint, at least the
#: cluster's rms radius) is flagged as not identifiable.
SD_REL_MAX = 0.1
#: A ball joint's centre whose largest standard deviation exceeds this fraction
#: of the lever arm is flagged as not identifiable. The linearised covariance
#: holds while the centre is well determined and not beyond: on the first 6 s of
#: 40 random rigs (3 or 4 markers a cluster, 50-200 Hz, 0.3-1.5 mm noise; an
#: estimate every 25 ms) the estimates with sd/lever below 0.02 had mean e/3
#: 0.97-1.08 and 2.5-5.6 % above 3, those at 0.03-0.10 mean e/3 2.2-2.7 and
#: 23-29 % above 3 (4.5-7 % above 9): the node's first estimates on the fake hip
#: were published 55-93 mm off with an sd of 13-18 mm (10 % was the limit until
#: 2026-12-03; ``test/test_first_estimates.py``). Skin markers' estimates are
#: judged on their statistical part, which holds the artefact's correlated
#: residuals as well as the pose noise (the real right-hip trial: 6.5 mm at a
#: 230 mm lever for its closed form), against :data:`SD_REL_MAX`; they also wait
#: for 2 s of movement (:data:`~jointfit_core.window_solve.SKIN_MIN_MOVEMENT_S`).
CENTRE_SD_REL_MAX = 0.02


def centre_sd_limit(skin: bool) -> float:
    """The centre verdict's limit on its largest sd, as a fraction of the lever arm.

    :data:`CENTRE_SD_REL_MAX`; skin markers' estimates (judged on their statistical part):
    :data:`SD_REL_MAX` (see :data:`CENTRE_SD_REL_MAX`).
    """
    return SD_REL_MAX if skin else CENTRE_SD_REL_MAX
#: A hinge direction whose largest standard deviation exceeds this many
#: degrees is flagged as not identifiable.
AXIS_SD_MAX_DEG = 5.0
#: Relative motion counts as "about a single axis" when the rotation spread
#: about the best axis, ``1 - s_1 / N``, is below this fraction of the spread
#: about the other axes, ``1 - s_2 / N`` (s_k: singular values of ``sum Q``).
#: For a hinge fit, a larger ratio means the motion is not a hinge.
SINGLE_AXIS_RATIO = 0.1
#: A direction of relative rotation is "excited" when its spread (deficit
#: ``1 - s_k / N``) exceeds the spread that the pose noise alone would cause by
#: more than this multiple of the latter; otherwise the first-order
#: covariance is meaningless there and the joint is flagged.
NOISE_SNR_MIN = 1.0
#: Frames in which a segment's visible markers give a rotation variance more
#: than this multiple of the full template's (a nearly collinear or tight
#: subset of a larger cluster) are not used by the two-segment fits: their
#: pose errors can reach tens of degrees, far outside the linearised model.
POSE_VAR_RATIO_MAX = 10.0
#: Frames whose rotation standard deviation (largest, radians) exceeds this
#: are not used either (clusters too small for the marker noise).
POSE_ROT_SD_MAX = 0.1
#: Gauss-Markov (reweighting) iterations.
_GM_ITERATIONS = 6
_METHODS = ("poses", "sphere")


class _FrozenArrays:
    def __post_init__(self) -> None:
        for f in fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value = np.array(value, copy=True)
                value.setflags(write=False)
                object.__setattr__(self, f.name, value)


# --------------------------------------------------------------------------- running sums


@dataclass(frozen=True, eq=False)
class PoseSums(_FrozenArrays):
    """Running sums of relative poses: all the unweighted closed form needs.

    Attributes
    ----------
    n : float
        Number of frames summed.
    S : ndarray, shape (3, 3)
        ``sum_t Q_t`` (dimensionless).
    sum_t : ndarray, shape (3,)
        ``sum_t t_t`` (input units).
    sum_qt_t : ndarray, shape (3,)
        ``sum_t Q_t^T t_t`` (input units).
    sum_tt : float
        ``sum_t |t_t|^2`` (input units squared).
    K : ndarray, shape (9, 9)
        ``sum_t kron(Q_t, Q_t)``, so that ``sum_t Q_t W Q_t^T`` is
        ``(K @ W.ravel()).reshape(3, 3)`` and ``sum_t Q_t^T W Q_t`` is
        ``(K.T @ W.ravel()).reshape(3, 3)`` for any fixed 3x3 ``W``.

    Sums of disjoint frame sets add (``a + b``); removing frames subtracts
    (``a - b``).
    """

    n: float
    S: FloatArray
    sum_t: FloatArray
    sum_qt_t: FloatArray
    sum_tt: float
    K: FloatArray

    @classmethod
    def zeros(cls) -> PoseSums:
        """Sums over no frame."""
        return cls(0.0, np.zeros((3, 3)), np.zeros(3), np.zeros(3), 0.0, np.zeros((9, 9)))

    def __add__(self, other: PoseSums) -> PoseSums:
        return PoseSums(
            self.n + other.n,
            self.S + other.S,
            self.sum_t + other.sum_t,
            self.sum_qt_t + other.sum_qt_t,
            self.sum_tt + other.sum_tt,
            self.K + other.K,
        )

    def __sub__(self, other: PoseSums) -> PoseSums:
        return PoseSums(
            self.n - other.n,
            self.S - other.S,
            self.sum_t - other.sum_t,
            self.sum_qt_t - other.sum_qt_t,
            self.sum_tt - other.sum_tt,
            self.K - other.K,
        )


def relative_poses(poses_parent: Poses, poses_child: Poses) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Child pose relative to the parent, per frame.

    Parameters
    ----------
    poses_parent, poses_child : Poses
        Poses of the two segments over the same N frames.

    Returns
    -------
    Q_parent_child : ndarray, shape (N, 3, 3)
        ``R_p^T R_c``: rotates child-local vectors into the parent frame.
    t_parent_child : ndarray, shape (N, 3)
        ``R_p^T (d_c - d_p)``: the child origin in the parent frame (input units).
    both : ndarray of bool, shape (N,)
        Frames where both segments were posed (elsewhere the outputs are NaN).
    """
    if poses_parent.n_frames != poses_child.n_frames:
        raise InputError(
            f"poses: expected the same number of frames, got {poses_parent.n_frames} (parent) and "
            f"{poses_child.n_frames} (child)"
        )
    both = poses_parent.valid & poses_child.valid
    Rp = np.where(both[:, None, None], poses_parent.R_world_local, 0.0)
    Rc = np.where(both[:, None, None], poses_child.R_world_local, 0.0)
    dd = np.where(both[:, None], poses_child.d_world_local - poses_parent.d_world_local, 0.0)
    Q = np.einsum("nji,njk->nik", Rp, Rc)
    t = np.einsum("nji,nj->ni", Rp, dd)
    Q[~both] = np.nan
    t[~both] = np.nan
    return Q, t, both


def pose_sums_from_relative(Q_parent_child: ArrayLike, t_parent_child: ArrayLike) -> PoseSums:
    """Running sums of relative poses; frames with NaN are skipped.

    Parameters
    ----------
    Q_parent_child : array_like, shape (N, 3, 3)
        Child-to-parent rotations ``R_p^T R_c``.
    t_parent_child : array_like, shape (N, 3)
        ``R_p^T (d_c - d_p)``, input units.

    Returns
    -------
    PoseSums
    """
    Q = np.asarray(Q_parent_child, dtype=np.float64)
    t = np.asarray(t_parent_child, dtype=np.float64)
    if Q.ndim != 3 or Q.shape[1:] != (3, 3) or t.shape != (Q.shape[0], 3):
        raise InputError(
            f"pose sums: expected Q of shape (N, 3, 3) and t of shape (N, 3), got {Q.shape} and {t.shape}"
        )
    ok = np.isfinite(Q).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    Q = Q[ok]
    t = t[ok]
    K = np.einsum("nij,nkl->ikjl", Q, Q).reshape(9, 9)
    return PoseSums(
        n=float(ok.sum()),
        S=Q.sum(axis=0),
        sum_t=t.sum(axis=0),
        sum_qt_t=np.einsum("nji,nj->i", Q, t),
        sum_tt=float(np.einsum("ni,ni->", t, t)),
        K=K,
    )


# --------------------------------------------------------------------------- helpers


def _spd_inv(W: FloatArray) -> FloatArray:
    """Inverse of a batch of symmetric positive definite matrices, never raising.

    A plain batched inverse; if any matrix is singular (or the result not
    finite), each matrix is scaled to unit diagonal (so that the floor does
    not depend on the units of its rows, e.g. radians and lengths) and its
    eigenvalues below 1e-12 of the largest are floored.
    """
    Ws = 0.5 * (W + np.swapaxes(W, -1, -2))
    try:
        out: FloatArray = np.asarray(np.linalg.inv(Ws), dtype=np.float64)
        if np.isfinite(out).all():
            return out
    except np.linalg.LinAlgError:
        pass
    diag = np.diagonal(Ws, axis1=-2, axis2=-1)
    d = np.where(diag > 0, 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    lam, V = np.linalg.eigh(d[..., :, None] * Ws * d[..., None, :])
    top = np.max(lam, axis=-1, keepdims=True)
    floor = np.where(top > 0, 1e-12 * top, 1.0)
    lam = np.maximum(lam, floor)
    out = (V / lam[..., None, :]) @ np.swapaxes(V, -1, -2)
    out = d[..., :, None] * out * d[..., None, :]
    return out


def _sym_solve(A: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """Solve a symmetric positive semi-definite system; return (x, A^-1, conditioning).

    The system is first scaled to unit diagonal (Jacobi: ``A_s = D A D``, ``D = diag(A)^-1/2``), so
    that the conditioning ``lam_min / lam_max`` of ``A_s`` does not depend on the units of the
    parameters (a normal matrix of angles and lengths changes its plain eigenvalue ratio with the
    length unit, and a singularity test on it with the unit). ``A^-1 = D A_s^-1 D``; a parameter with
    a non-positive diagonal (not constrained at all) makes the conditioning 0.
    """
    A = 0.5 * (A + A.T)
    diag = np.diag(A).copy()
    if not (np.isfinite(A).all() and (diag > 0.0).all()):
        return np.zeros_like(b), np.full_like(A, np.nan), 0.0
    d = 1.0 / np.sqrt(diag)
    lam, V = np.linalg.eigh(d[:, None] * A * d[None, :])
    top = float(lam[-1])
    ratio = float(lam[0] / top) if top > 0 else 0.0
    safe = np.where(lam > 0, lam, np.inf)
    inv = d[:, None] * ((V / safe) @ V.T) * d[None, :]
    return inv @ b, inv, ratio


def _max_sd(cov: FloatArray) -> float:
    if not np.isfinite(cov).all():
        return float("inf")
    return float(np.sqrt(max(float(np.linalg.eigvalsh(0.5 * (cov + cov.T))[-1]), 0.0)))


def _spread_deg(deficit: float) -> float:
    """Rms rotation angle (deg) matching a deficit ``1 - s/N`` (``1 - cos(theta) ~ theta^2 / 2``)."""
    return float(np.rad2deg(np.sqrt(2.0 * max(deficit, 0.0))))


def _fmt_dir(v: FloatArray) -> str:
    v = v * np.sign(v[int(np.argmax(np.abs(v)))])
    return "[" + ", ".join(f"{c:.2f}" for c in v) + "]"


@dataclass(frozen=True)
class _Motion:
    """Relative-rotation spread from ``S = sum Q`` against the spread the pose noise alone would cause."""

    axes: FloatArray  # (3, 3) columns: left singular vectors of S (parent frame), best axis first
    deficit: FloatArray  # (3,) 1 - s_k / N, ascending
    noise: FloatArray  # (3,) expected deficit from the pose noise alone

    @property
    def excited(self) -> NDArray[np.bool_]:
        """Directions whose spread exceeds the noise spread by more than NOISE_SNR_MIN times the latter."""
        return (self.deficit > SINGULAR_REL) & (self.deficit - self.noise > NOISE_SNR_MIN * self.noise)


def _motion(S: FloatArray, n: float, rot_parent: FloatArray, mean_rot_child: FloatArray) -> _Motion:
    """Analyse the relative rotations.

    ``rot_parent`` is the parent's local rotation-noise covariance and ``mean_rot_child`` the mean over
    the frames of ``Q_t Sigma_rot,c Q_t^T`` (the child's, in the parent frame). A small noise rotation
    ``omega`` lowers ``u^T Q v`` by ``(|omega|^2 - (u . omega)^2) / 2`` on average, so the noise alone gives
    the deficit ``(tr Sigma - u^T Sigma u) / 2`` along ``u`` with ``Sigma = rot_parent + mean_rot_child``.
    """
    U, s, _ = np.linalg.svd(S / n)
    deficit = np.clip(1.0 - s, 0.0, None)
    sigma = rot_parent + mean_rot_child
    noise = 0.5 * (np.trace(sigma) - np.einsum("ik,ij,jk->k", U, sigma, U))
    return _Motion(U, deficit, np.maximum(noise, 0.0))


def _motion_diagnosis(mo: _Motion) -> tuple[str, str]:
    """Classify the relative rotation: ("none" | "single" | "ok", message a person can act on)."""
    deficit, excited = mo.deficit, mo.excited
    if not excited[2]:
        return "none", (
            "no relative rotation between the child and the parent beyond the pose noise (rms spread "
            f"~{_spread_deg(deficit[2]):.2g} deg, noise alone ~{_spread_deg(mo.noise[2]):.2g} deg): the joint is "
            "undetermined; move the joint, rotating the child relative to the parent about at least two "
            "different axes"
        )
    if not excited[0] or deficit[0] < SINGLE_AXIS_RATIO * SINGULAR_REL:
        return "single", (
            f"the child rotated about a single axis relative to the parent (axis ~ {_fmt_dir(mo.axes[:, 0])} "
            f"in the parent frame; rms spread about it ~{_spread_deg(deficit[1]):.2g} deg, about the other axes "
            f"~{_spread_deg(deficit[0]):.2g} deg, the pose noise alone ~{_spread_deg(mo.noise[0]):.2g} deg), "
            "which leaves the centre undetermined along that axis: also rotate about a second axis (e.g. "
            "abduction as well as flexion)"
        )
    if deficit[0] < SINGLE_AXIS_RATIO * deficit[1]:
        return "single", (
            f"the child rotated mostly about a single axis relative to the parent (axis ~ "
            f"{_fmt_dir(mo.axes[:, 0])} in the parent frame; rms spread about it ~{_spread_deg(deficit[1]):.2g} "
            f"deg, about the other axes ~{_spread_deg(deficit[0]):.2g} deg): also rotate more about a second "
            "axis (e.g. abduction as well as flexion), or record more frames"
        )
    return "ok", (
        f"the relative rotation (rms spread >= ~{_spread_deg(deficit[0]):.2g} deg about every axis) is too "
        "small for the marker noise and lever arms: move the joint through a larger range about at least two "
        "axes, record more frames, or use larger marker clusters"
    )


def _centre_verdict(
    mo: _Motion,
    cov_parent: FloatArray,
    cov_child: FloatArray,
    centre_parent: FloatArray,
    centre_child: FloatArray,
    length_scale: float,
    limit: float = CENTRE_SD_REL_MAX,
) -> tuple[bool, str]:
    """Whether a centre is identifiable: motion about two axes, and its largest sd at most ``limit`` of the lever arm."""
    kind, message = _motion_diagnosis(mo)
    if kind == "none" or (kind == "single" and not mo.excited[0]):
        return False, message
    sd = max(_max_sd(cov_parent), _max_sd(cov_child))
    lever = max(float(np.linalg.norm(centre_parent)), float(np.linalg.norm(centre_child)), length_scale)
    if not np.isfinite(sd) or sd > limit * lever:
        return False, (
            f"centre poorly determined: its standard deviation ({sd:.3g}) exceeds {limit:.0%} of the lever "
            f"arm ({lever:.3g}); {message}"
        )
    return True, ""


# --------------------------------------------------------------------------- closed form from sums


@dataclass(frozen=True, eq=False)
class PoseSumsCentre(_FrozenArrays):
    """Ball joint from running sums (unweighted closed form, sandwich covariance).

    Attributes
    ----------
    centre_parent, centre_child : ndarray, shape (3,)
        Joint centre in the parent and the child local frame (input units).
    cov : ndarray, shape (6, 6)
        Joint covariance of ``(centre_parent, centre_child)``.
    cov_parent, cov_child : ndarray, shape (3, 3)
        Its diagonal blocks.
    rms : float
        Rms of the constraint residual ``|c_p - Q_t c_c - t_t|`` over the frames.
    n_frames : int
    identifiable : bool
    reason : str
    """

    centre_parent: FloatArray
    centre_child: FloatArray
    cov: FloatArray
    cov_parent: FloatArray
    cov_child: FloatArray
    rms: float
    n_frames: int
    identifiable: bool
    reason: str


def _check_cov6(W: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(W, dtype=np.float64)
    if arr.shape != (6, 6) or not np.isfinite(arr).all():
        raise InputError(f"{name}: expected a finite (6, 6) local pose covariance, got shape {arr.shape}")
    return arr


def normal_matrix(S: FloatArray, n: float) -> FloatArray:
    """``H = [[n I, -S], [-S^T, n I]]`` (6, 6): the normal matrix of Stoddart et al.'s eq. 9 from ``S = sum Q`` over ``n`` frames."""
    H = np.empty((6, 6))
    H[:3, :3] = n * np.eye(3)
    H[3:, 3:] = n * np.eye(3)
    H[:3, 3:] = -S
    H[3:, :3] = -S.T
    return H


def _sums_meat(sums: PoseSums, c_p: FloatArray, c_c: FloatArray, Wp6: FloatArray, Wc6: FloatArray) -> FloatArray:
    """``sum_t M_t^T W_t M_t`` (6, 6) of the constraint ``c_p - Q_t c_c - t_t`` from the sums.

    ``W_t = W_p + Q_t W_c Q_t^T`` with the local pose covariances carried to the levers ``c_p``, ``c_c``
    (the sandwich's middle; see :func:`centre_from_pose_sums`).
    """
    n = float(sums.n)
    S = np.asarray(sums.S)
    K = np.asarray(sums.K)
    Jp = lever_jacobian(c_p)
    Jc = lever_jacobian(c_c)
    W_p = Jp @ Wp6 @ Jp.T
    W_c = Jc @ Wc6 @ Jc.T
    B = np.empty((6, 6))
    B[:3, :3] = n * W_p + (K @ W_c.ravel()).reshape(3, 3)
    B[:3, 3:] = -(W_p @ S + S @ W_c)
    B[3:, :3] = B[:3, 3:].T
    B[3:, 3:] = (K.T @ W_p.ravel()).reshape(3, 3) + n * W_c
    return B


def _sums_rms(sums: PoseSums, c_p: FloatArray, c_c: FloatArray) -> float:
    """Rms over the summed frames of ``|c_p - Q_t c_c - t_t|``, from the sums."""
    n = float(sums.n)
    ss = (
        n * (c_p @ c_p + c_c @ c_c)
        + sums.sum_tt
        - 2.0 * c_p @ np.asarray(sums.S) @ c_c
        - 2.0 * c_p @ sums.sum_t
        + 2.0 * c_c @ sums.sum_qt_t
    )
    return float(np.sqrt(max(float(ss), 0.0) / n))


def svd3(S: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``U, s, V`` of 3x3 matrices ``S`` (..., 3, 3) (``S = U diag(s) V^T``, singular values descending)."""
    U, s, Vt = np.linalg.svd(S)
    return U, s, np.swapaxes(Vt, -1, -2)


#: :func:`gauge_free_pinv`'s eigenpairs of ``H``: singular pair ``k`` and sign (``+``: ``N - s_k``, ``-``: ``N + s_k``),
#: every pair but the gauge ``(u_0, v_0)``.
_GAUGE_FREE_K = np.array([0, 1, 1, 2, 2])
_GAUGE_FREE_SIGN = np.array([-1.0, 1.0, -1.0, 1.0, -1.0])


def gauge_free_pinv(U: FloatArray, s: FloatArray, V: FloatArray, n: float) -> FloatArray:
    """Pseudo-inverse (..., 6, 6) of ``H = [[N I, -S], [-S^T, N I]]`` without the gauge direction ``(u_0, v_0) / sqrt 2``.

    ``H``'s eigenpairs are ``N -/+ s_k`` with ``(u_k, +/-v_k) / sqrt 2`` for ``S = U diag(s) V^T``
    (:func:`svd3`: ``U``, ``V`` (..., 3, 3), ``s`` (..., 3); any leading axes).
    """
    k, sign = _GAUGE_FREE_K, _GAUGE_FREE_SIGN
    Em = np.concatenate([U[..., :, k], V[..., :, k] * sign], axis=-2) / np.sqrt(2.0)  # (..., 6, 5)
    lam = n - sign * s[..., k]
    out: FloatArray = (Em / lam[..., None, :]) @ np.swapaxes(Em, -1, -2)
    return out


def first_order_bias_step(
    a: FloatArray, H_inv: FloatArray, S: FloatArray, n: float, A_p: FloatArray, A_c: FloatArray
) -> FloatArray:
    """``a`` (6,) shifted by ``H_inv`` times the estimating equation's second-order noise bias.

    The bias is ``-(1/2) [N A_p c_p + S A_c c_c; S^T A_p c_p + N A_c c_c]`` (see
    :func:`centre_from_pose_sums`); right to first order, used only where the corrected
    normal equations of :func:`debiased_sums` have no rotation beyond the noise to solve.
    """
    D_p, D_c = A_p @ a[:3], A_c @ a[3:]
    out: FloatArray = a + H_inv @ (-0.5 * np.concatenate([n * D_p + S @ D_c, S.T @ D_p + n * D_c]))
    return out


def noise_bias_matrices(
    Wp6: FloatArray, Wc6: FloatArray, W_bias: tuple[ArrayLike, ArrayLike] | None = None
) -> tuple[FloatArray, FloatArray]:
    """``A = Sigma - tr(Sigma) I`` (3, 3) of each segment's rotation noise (``W_bias``'s when given, else ``W``'s).

    A small rotation noise ``w`` (covariance ``Sigma``) lowers a rotation on average:
    ``E[exp([w]x)] = I + A / 2`` to second order.
    """
    Sp, Sc = Wp6[:3, :3], Wc6[:3, :3]
    if W_bias is not None:
        Sp = _check_cov6(W_bias[0], "W_bias[0]")[:3, :3]
        Sc = _check_cov6(W_bias[1], "W_bias[1]")[:3, :3]
    return Sp - np.trace(Sp) * np.eye(3), Sc - np.trace(Sc) * np.eye(3)


def debiased_sums(sums: PoseSums, A_p: FloatArray, A_c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``S`` (3, 3) and ``g = [sum t; -sum Q^T t]`` (6,) with the pose noise's second-order bias removed.

    With the parent's rotation noise on the left of ``Q_t = R_p^T R_c`` and the child's on the
    right, ``E[Q] = (I + A_p / 2) Q (I + A_c / 2)``, ``E[t] = (I + A_p / 2) t`` and
    ``E[Q^T t] = (I + A_c / 2) Q^T t`` to second order (the local origins are the templates'
    centroids, whose translation errors are uncorrelated with the rotation's), so
    ``S - (A_p S + S A_c) / 2`` and ``[(I - A_p / 2) sum t; -(I - A_c / 2) sum Q^T t]`` have the
    noise-free sums' expectations (Stoddart et al. 1999, eq. 9, errors in variables).
    """
    S = np.asarray(sums.S)
    S_c: FloatArray = S - 0.5 * (A_p @ S + S @ A_c)
    g_c: FloatArray = np.concatenate(
        [sums.sum_t - 0.5 * A_p @ sums.sum_t, -(sums.sum_qt_t - 0.5 * A_c @ sums.sum_qt_t)]
    )
    return S_c, g_c


def centre_from_pose_sums(
    sums: PoseSums,
    W_parent_local: ArrayLike,
    W_child_local: ArrayLike,
    *,
    length_scale: float = 0.0,
    compensate_bias: bool = True,
    W_bias: tuple[ArrayLike, ArrayLike] | None = None,
    sd_limit: float = CENTRE_SD_REL_MAX,
) -> PoseSumsCentre:
    """Ball-joint centres from running sums of relative poses (unweighted Stoddart eq. 9).

    Parameters
    ----------
    sums : PoseSums
        Sums over the frames (:func:`pose_sums_from_relative`).
    W_parent_local, W_child_local : array_like, shape (6, 6)
        Pose covariance of each segment in its local frame, about its local
        origin (rotation vector in radians, translation in input units),
        averaged over the summed frames:
        the mean of :func:`jointfit_core.pose.pose_covariance_local` with
        each frame's visible markers (for the full template when no marker
        is occluded). :func:`fit_centre_two_segments` passes that mean; an
        online estimator reproduces it with a running sum of the unit-noise
        covariances times the current ``noise_std**2``.
    length_scale : float
        Lower bound of the lever arm used in the identifiability check
        (input units; e.g. the cluster's rms radius). Default 0.
    compensate_bias : bool
        Remove the second-order bias caused by the pose noise (default True).
    W_bias : (array_like, array_like), shapes (6, 6), optional
        The pose covariances (parent, child) of the bias compensation when
        they are not the covariance's: on skin markers, those of the white
        marker noise (:mod:`jointfit_core.white_noise_sums`), since the
        cluster's deformation, which ``W_parent_local`` and ``W_child_local``
        hold, is not pose noise of that kind and would over-correct the
        estimate by the square of its ratio to the noise. Default: those two.
    sd_limit : float
        The verdict's limit on the centre's largest sd, as a fraction of the
        lever arm (default :data:`CENTRE_SD_REL_MAX`; skin markers'
        estimates: :data:`SD_REL_MAX`, see there).

    Returns
    -------
    PoseSumsCentre
        The centres in both local frames, their 6x6 covariance, the rms
        residual and the verdict.

    Raises
    ------
    InputError
        Fewer than 3 frames or badly shaped covariances.
    NotIdentifiableError
        The normal matrix is singular: no relative rotation, or noise-free
        rotation about a single axis. The message says which movement is missing.

    Notes
    -----
    Minimises ``sum_t |c_p - Q_t c_c - t_t|^2`` (Stoddart et al. 1999, eq. 6-9
    with distinct parent and child frames): the normal equations are
    ``H a = g`` with ``H = [[N I, -S], [-S^T, N I]]``, ``S = sum Q_t`` and
    ``g = [sum t_t; -sum Q_t^T t_t]``. Its eigenvalues are ``N -/+ s_k`` for
    the singular values ``s_k`` of ``S``; it is solved by eigen-decomposition.

    **Covariance** (sandwich, first order in the pose noise): the residual
    ``h_t = c_p - Q_t c_c - t_t`` has covariance
    ``W_t = W_p + Q_t W_c Q_t^T`` (parent frame), with ``W_p = J_p
    W_parent_local J_p^T`` and ``J_p = [-[c_p]x, I]`` the error of the
    parent-carried centre (likewise for the child), so
    ``cov(a) = H^-1 (sum_t M_t^T W_t M_t) H^-1`` with ``M_t = [I, -Q_t]``.
    The middle sum needs only ``N``, ``S`` and ``K = sum Q (x) Q`` when
    ``W_p`` and ``W_c`` are the same in every frame; with occlusions they
    vary, and the mean covariances are used: exact for the ``sum W_p`` and
    ``sum W_c`` blocks, an approximation (visibility independent of
    ``Q_t``) for the terms with ``K``.
    The covariance scales with the marker noise variance and, for a fixed
    range of motion, as ``1 / N``.

    **Bias compensation.** The relative poses are noisy in both ``M_t``
    (through ``Q_t``) and ``t_t`` (errors in variables), so to second order
    in the rotation noise the estimating equation ``sum M_t^T h_t`` has the
    expectation ``-(1/2) [N D_p + S D_c; S^T D_p + N D_c]`` with
    ``D_p = (Sigma_p - tr(Sigma_p) I) c_p``, ``Sigma_p`` the rotation block of
    ``W_parent_local`` (likewise ``D_c``; levers from the local origin, the
    template centroid). The bias does not shrink with N (here about 0.4 sd
    per coordinate at N = 1200 on a Stoddart-like rig), so without it the
    error would be dominated by it for long recordings. It is removed by
    solving the corrected normal equations ``H_c a = g_c`` of
    :func:`debiased_sums` (their expectations are the noise-free ones), which
    to first order is the estimate shifted by ``H^-1`` times the expectation
    above; unlike that shift, it stays right when the noise's part of ``H``'s
    small eigenvalues is as large as the motion's (a long still stance and a
    short movement: 1160 still frames and 40 moving ones put a centre 5 sd
    off with the shift). The covariance's sandwich uses ``H_c``. Without
    rotation beyond the noise (``H_c`` not positive definite) the shift is
    used, and the verdict says not identifiable.
    """
    Wp6 = _check_cov6(W_parent_local, "W_parent_local")
    Wc6 = _check_cov6(W_child_local, "W_child_local")
    n = float(sums.n)
    if n < 3:
        raise InputError(f"sums: expected at least 3 frames, got {n:g}")
    S = np.asarray(sums.S)
    H = normal_matrix(S, n)
    g = np.concatenate([sums.sum_t, -np.asarray(sums.sum_qt_t)])
    K = np.asarray(sums.K)
    mo = _motion(S, n, Wp6[:3, :3], (K @ Wc6[:3, :3].ravel()).reshape(3, 3) / n)
    lam, V = np.linalg.eigh(H)
    if lam[0] <= SINGULAR_REL * n:
        kind, message = _motion_diagnosis(mo)
        raise NotIdentifiableError(
            message if kind != "ok" else "the joint centre is undetermined: " + message
        )
    H_inv = (V / lam) @ V.T
    a = H_inv @ g
    if compensate_bias:
        A_p, A_c = noise_bias_matrices(Wp6, Wc6, W_bias)
        S_c, g_c = debiased_sums(sums, A_p, A_c)
        lam_c, V_c = np.linalg.eigh(normal_matrix(S_c, n))
        if lam_c[0] > SINGULAR_REL * n:  # the corrected normal equations (see Notes)
            H_inv = (V_c / lam_c) @ V_c.T
            a = H_inv @ g_c
        else:  # no rotation beyond the noise: the first-order step (the verdict says not identifiable)
            a = first_order_bias_step(a, H_inv, S, n, A_p, A_c)
    c_p, c_c = a[:3], a[3:]

    cov = H_inv @ _sums_meat(sums, c_p, c_c, Wp6, Wc6) @ H_inv
    cov = 0.5 * (cov + cov.T)

    rms = _sums_rms(sums, c_p, c_c)
    identifiable, reason = _centre_verdict(mo, cov[:3, :3], cov[3:, 3:], c_p, c_c, length_scale, sd_limit)
    return PoseSumsCentre(
        centre_parent=c_p,
        centre_child=c_c,
        cov=cov,
        cov_parent=cov[:3, :3],
        cov_child=cov[3:, 3:],
        rms=rms,
        n_frames=round(n),
        identifiable=identifiable,
        reason=reason,
    )


# --------------------------------------------------------------------------- shared preparation


@dataclass(frozen=True)
class _Prepared:
    markers_parent: FloatArray
    markers_child: FloatArray
    template_parent: FloatArray
    template_child: FloatArray
    poses_parent: Poses
    poses_child: Poses
    sigma_parent: float
    sigma_child: float
    Q: FloatArray  # (N, 3, 3), NaN where not both posed
    t: FloatArray  # (N, 3)
    both: BoolArray  # (N,) frames used: both segments posed, and well enough
    pooled: tuple[float, float]  # pooled pose-fit residual noise (parent, child), deformation included

    @property
    def length_scale(self) -> float:
        """The larger rms radius of the two templates."""
        return max(
            float(np.sqrt(np.mean(np.sum(self.template_parent**2, axis=1)))),
            float(np.sqrt(np.mean(np.sum(self.template_child**2, axis=1)))),
        )

    @property
    def noisy(self) -> bool:
        """Whether the marker noise estimates are above the rounding of the coordinates.

        Noise-free data give sigmas of float64 rounding (eps times the largest
        coordinate); weights built from them are arbitrary, so the weighted
        fits fall back to the unweighted solution (found by the unit-change
        property test: the weighted hinge moved when the data were scaled).
        """
        big = max(float(np.nanmax(np.abs(self.markers_parent))), float(np.nanmax(np.abs(self.markers_child))))
        floor = 1e3 * np.finfo(np.float64).eps * big
        return bool(self.sigma_parent > floor or self.sigma_child > floor)


def _check_segment(arr: FloatArray, name: str, kind: str) -> FloatArray:
    if arr.shape[1] < 3:
        fit = "fit_centre_minimal (ball: 2 + 2 or 3 + 1)" if kind == "ball" else "fit_axis_minimal (hinge: 2 + 1)"
        raise InputError(
            f"{name}: expected at least 3 markers per segment for the pose-based two-segment methods, got "
            f"{arr.shape[1]}; these marker counts identify the joint with the minimal-marker methods: use {fit}"
        )
    return arr


def _prepare(parent: ArrayLike, child: ArrayLike, kind: str, white: bool = False) -> _Prepared:
    yp = check_markers(parent, name="parent")
    yc = check_markers(child, name="child")
    # Marker counts that cannot identify the joint at all (Pham et al., sections III-IV) raise with the reason.
    check_marker_counts(kind, yp.shape[1], yc.shape[1])
    yp = _check_segment(yp, "parent", kind)
    yc = _check_segment(yc, "child", kind)
    if yp.shape[0] != yc.shape[0]:
        raise InputError(
            f"parent, child: expected the same number of frames, got {yp.shape[0]} (parent) and {yc.shape[0]} (child)"
        )
    try:
        tp = template_from_markers(yp)
    except InputError as exc:
        raise InputError(f"parent: {exc}") from None
    try:
        tc = template_from_markers(yc)
    except InputError as exc:
        raise InputError(f"child: {exc}") from None
    pp = poses_from_markers(yp, tp)
    pc = poses_from_markers(yc, tc)
    Q, t, both = relative_poses(pp, pc)
    if int(both.sum()) < 3:
        raise InputError(
            "parent, child: expected at least 3 frames in which both segments show 3 non-collinear markers, "
            f"got {int(both.sum())}"
        )
    sp = noise_std_from_fit(yp, tp, pp)
    sc = noise_std_from_fit(yc, tc, pc)
    pooled = (sp, sc)
    if white:  # skin markers: the pooled residual holds the cluster's deformation; keep only the white noise
        wp = white_noise_std(yp, tp, pp.R_world_local, pp.d_world_local, pp.valid)
        wc = white_noise_std(yc, tc, pc.R_world_local, pc.d_world_local, pc.valid)
        sp = min(sp, wp) if np.isfinite(wp) else sp
        sc = min(sc, wc) if np.isfinite(wc) else sc
    good_p = _well_posed(tp, pp, sp)
    good_c = _well_posed(tc, pc, sc)
    used = both & good_p & good_c
    if int(used.sum()) < 3:
        raise InputError(
            f"parent, child: expected at least 3 frames in which both segments are well posed, got "
            f"{int(used.sum())} of {int(both.sum())} posed frames (well posed: parent {int(good_p.sum())}, "
            f"child {int(good_c.sum())}); the visible markers are nearly collinear or too close together for "
            "the marker noise: use larger, non-collinear marker clusters"
        )
    return _Prepared(yp, yc, tp, tc, pp, pc, sp, sc, Q, t, used, pooled)


def _well_posed(template: FloatArray, poses: Poses, sigma: float) -> BoolArray:
    """Posed frames whose rotation noise (visible markers) is within the limits of the linearised model.

    The largest eigenvalue of the frame's rotation covariance must be at most :data:`POSE_VAR_RATIO_MAX`
    times that of the full template and its square root at most :data:`POSE_ROT_SD_MAX` radians.
    """
    cov_rot = pose_noise_local(template, sigma, poses.visible)[1]
    cov_rot = np.where(poses.valid[:, None, None], cov_rot, 0.0)
    worst = np.linalg.eigvalsh(cov_rot)[:, -1]
    full = float(np.linalg.eigvalsh(pose_noise_local(template, sigma)[1])[-1])
    limit = min(POSE_VAR_RATIO_MAX * full, POSE_ROT_SD_MAX**2)
    ok: BoolArray = poses.valid & (worst <= limit)
    return ok


def _motion_of(prep: _Prepared, Q: FloatArray) -> _Motion:
    """Relative-rotation analysis of the used frames with the full-template rotation noise."""
    rot_p = pose_noise_local(prep.template_parent, prep.sigma_parent)[1]
    rot_c = pose_noise_local(prep.template_child, prep.sigma_child)[1]
    mean_rot_c = (Q @ rot_c @ np.swapaxes(Q, -1, -2)).mean(axis=0)
    return _motion(Q.sum(axis=0), float(Q.shape[0]), rot_p, mean_rot_c)


def _constraint_cov(
    Q: FloatArray, c_p: FloatArray, c_c: FloatArray, Wp6: FloatArray, Wc6: FloatArray
) -> FloatArray:
    """Per-frame covariance (..., 3, 3) of ``h_t = c_p - Q_t c_c - t_t`` in the parent frame."""
    Jp = lever_jacobian(c_p)
    Jc = lever_jacobian(c_c)
    W_p = Jp @ Wp6 @ Jp.T
    W_c = Jc @ Wc6 @ Jc.T
    out: FloatArray = W_p + Q @ W_c @ np.swapaxes(Q, -1, -2)
    return out


def _sqrt_columns(S: FloatArray) -> FloatArray:
    """``L`` with ``L L^T = S`` (batched, symmetric square root via eigh)."""
    lam, V = np.linalg.eigh(0.5 * (S + np.swapaxes(S, -1, -2)))
    out: FloatArray = V * np.sqrt(np.maximum(lam, 0.0))[..., None, :]
    return out


def _expm_so3(w: FloatArray) -> FloatArray:
    """Rotation matrices ``exp([w]x)`` for rotation vectors of shape (..., 3)."""
    mats = Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix()
    out: FloatArray = mats.reshape(*w.shape[:-1], 3, 3)
    return out


def _sigma_relative_poses(
    Q: FloatArray,
    t: FloatArray,
    noise_p: tuple[FloatArray, FloatArray, FloatArray],
    noise_c: tuple[FloatArray, FloatArray, FloatArray],
) -> tuple[FloatArray, FloatArray]:
    """Relative poses under +/- one-sigma pose perturbations (24 per frame).

    Each segment's pose is perturbed along the columns of the square root of
    its noise covariance (rotation ``omega`` about the visible centroid
    ``xbar`` and centroid translation ``u``, see
    :func:`jointfit_core.pose.pose_noise_local`), one at a time, with both
    signs. For a function ``f`` of the relative pose,
    ``E f - f = (1/2) sum_k (f(+s_k) + f(-s_k) - 2 f)`` to second order.

    Returns ``Q`` of shape (m, 24, 3, 3) and ``t`` of shape (m, 24, 3).
    """
    xbar_p, rot_p, var_p = noise_p
    xbar_c, rot_c, var_c = noise_c
    m = Q.shape[0]
    om_p = np.zeros((m, 12, 3))
    u_p = np.zeros((m, 12, 3))
    om_c = np.zeros((m, 12, 3))
    u_c = np.zeros((m, 12, 3))
    om_p[:, 0:3] = np.swapaxes(_sqrt_columns(rot_p), -1, -2)
    u_p[:, 3:6] = np.sqrt(var_p)[:, None, None] * np.eye(3)
    om_c[:, 6:9] = np.swapaxes(_sqrt_columns(rot_c), -1, -2)
    u_c[:, 9:12] = np.sqrt(var_c)[:, None, None] * np.eye(3)
    om_p, u_p, om_c, u_c = (np.concatenate([v, -v], axis=1) for v in (om_p, u_p, om_c, u_c))
    E_p = _expm_so3(om_p)
    E_c = _expm_so3(om_c)
    # R_p' = R_p E_p, d_p' = d_p + R_p (xbar_p - E_p xbar_p + u_p); likewise the child.
    Qx = np.swapaxes(E_p, -1, -2) @ Q[:, None] @ E_c
    shift_c = xbar_c[:, None] - np.einsum("nkij,nj->nki", E_c, xbar_c) + u_c
    inner = (
        t[:, None]
        + np.einsum("nij,nkj->nki", Q, shift_c)
        - xbar_p[:, None]
        + np.einsum("nkij,nj->nki", E_p, xbar_p)
        - u_p
    )
    tx = np.einsum("nkji,nkj->nki", E_p, inner)
    return Qx, tx


def _gauss_markov_centre(
    Q: FloatArray,
    t: FloatArray,
    noise_p: tuple[FloatArray, FloatArray, FloatArray],
    noise_c: tuple[FloatArray, FloatArray, FloatArray],
    Wp6: FloatArray,
    Wc6: FloatArray,
    a0: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Stoddart's appendix eq. (22)-(23), reweighted from ``a0`` and bias-compensated.

    Returns ``(a, cov, bread)``: ``bread`` is the noise's expected share of the normal matrix that was
    removed (None when the first-order shift was used), see :func:`_debiased_weighted`.
    """
    a = a0.copy()
    Qt = np.swapaxes(Q, -1, -2)
    cov = np.full((6, 6), np.nan)
    scale = max(float(np.linalg.norm(a0)), 1e-300)
    for it in range(_GM_ITERATIONS + 1):
        Winv = _spd_inv(_constraint_cov(Q, a[:3], a[3:], Wp6, Wc6))
        WQ = Winv @ Q
        A = np.empty((6, 6))
        A[:3, :3] = Winv.sum(axis=0)
        A[:3, 3:] = -WQ.sum(axis=0)
        A[3:, :3] = A[:3, 3:].T
        A[3:, 3:] = (Qt @ WQ).sum(axis=0)
        Wt = np.einsum("nij,nj->ni", Winv, t)
        b = np.concatenate([Wt.sum(axis=0), -np.einsum("nji,nj->i", Q, Wt)])
        a_new, cov, ratio = _sym_solve(A, b)
        if ratio <= SINGULAR_REL:
            raise NotIdentifiableError(
                "the weighted normal matrix is singular: the relative rotations cannot locate the joint; rotate "
                "the child relative to the parent about at least two different axes"
            )
        if it == _GM_ITERATIONS:
            break  # the covariance is evaluated at the converged ``a``
        step = float(np.linalg.norm(a_new - a))
        a = a_new
        if step <= 1e-12 * scale:
            break
    # Second-order bias of the estimating equation sum M^T W^-1 h under the pose noise (sigma points):
    # with W held at the converged a, psi(a) = A a - b is linear in a, and so is its expected bias
    # dA a - db; the corrected equation (A - dA) a = b - db is solved (see _debiased_weighted).
    Jp, Jc = lever_jacobian(a[:3]), lever_jacobian(a[3:])
    W_p = Jp @ Wp6 @ Jp.T
    W_c = Jc @ Wc6 @ Jc.T
    Qx, tx = _sigma_relative_poses(Q, t, noise_p, noise_c)
    A_x, b_x = _centre_normal_sums(Qx, tx, W_p[:, None], W_c[:, None])
    A_0, b_0 = _centre_normal_sums(Q, t, W_p, W_c)
    return _debiased_weighted(A_0, b_0, 0.5 * A_x - 12.0 * A_0, 0.5 * b_x - 12.0 * b_0, a, cov)


def _centre_normal_sums(Q: FloatArray, t: FloatArray, W_p: FloatArray, W_c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``A = sum M^T W^-1 M`` (6, 6) and ``b = sum M^T W^-1 t`` (6,) over every leading axis.

    ``M = [I, -Q]`` and ``W = W_p + Q W_c Q^T`` for relative poses of shape (..., 3, 3), (..., 3), so
    that the weighted estimating function ``sum M^T W^-1 (M a - t)`` is ``A a - b``.
    """
    Winv = _spd_inv(W_p + Q @ W_c @ np.swapaxes(Q, -1, -2))
    WQ = Winv @ Q
    A = np.empty((6, 6))
    A[:3, :3] = Winv.sum(axis=tuple(range(Winv.ndim - 2)))
    A[:3, 3:] = -WQ.sum(axis=tuple(range(WQ.ndim - 2)))
    A[3:, :3] = A[:3, 3:].T
    A[3:, 3:] = (np.swapaxes(Q, -1, -2) @ WQ).sum(axis=tuple(range(Q.ndim - 2)))
    Wt = np.einsum("...ij,...j->...i", Winv, t)
    b = np.concatenate([Wt, -np.einsum("...ji,...j->...i", Q, Wt)], axis=-1).reshape(-1, 6).sum(axis=0)
    return A, b


def _debiased_weighted(
    A: FloatArray, b: FloatArray, dA: FloatArray, db: FloatArray, a: FloatArray, cov: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """The weighted centre pair and its covariance with the noise's expected ``dA a - db`` removed.

    ``E[A a - b] = (A a - b)_noise-free + dA a - db`` to second order, so ``(A - dA) a = b - db`` is
    unbiased; its covariance is the sandwich ``(A - dA)^-1 A (A - dA)^-1`` (``A``: the information of
    the weighted equation). Unlike the first-order shift ``a + A^-1 (dA a - db)``, it stays right when
    the noise's part of ``A``'s small eigenvalues is as large as the motion's (a long still stance and a
    short movement: 19 s still and 1 s of movement put centres 5-8 sd off with the shift). Without
    rotation beyond the noise (``A - dA`` not positive definite) the shift is used; the verdict then
    says not identifiable. Returns ``(a, cov, dA)``, ``dA`` None when the shift was used.
    """
    A_c = 0.5 * ((A - dA) + (A - dA).T)
    lam, V = np.linalg.eigh(A_c)
    if lam[0] <= SINGULAR_REL * lam[-1]:
        a = a + cov @ (dA @ a - db)
        return a, 0.5 * (cov + cov.T), None
    A_c_inv = (V / lam) @ V.T
    a = A_c_inv @ (b - db)
    out = A_c_inv @ A @ A_c_inv
    return a, 0.5 * (out + out.T), 0.5 * (dA + dA.T)


def _world_outputs(
    prep: _Prepared, c_p: FloatArray, c_c: FloatArray, cov_parent: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """centre_world (N, 3), cov_world (N, 3, 3) and residual (N,)."""
    pp, pc = prep.poses_parent, prep.poses_child
    vp = pp.valid
    Rp = np.where(vp[:, None, None], pp.R_world_local, 0.0)
    centre_world = np.einsum("nij,j->ni", Rp, c_p) + np.where(vp[:, None], pp.d_world_local, 0.0)
    W_frame = point_covariance_local(prep.template_parent, c_p, prep.sigma_parent, pp.visible)
    W_frame = np.where(vp[:, None, None], W_frame, 0.0)
    cov_world = Rp @ (cov_parent + W_frame) @ np.swapaxes(Rp, -1, -2)
    centre_world[~vp] = np.nan
    cov_world[~vp] = np.nan
    both = prep.both
    Rc = np.where(both[:, None, None], pc.R_world_local, 0.0)
    child_world = np.einsum("nij,j->ni", Rc, c_c) + np.where(both[:, None], pc.d_world_local, 0.0)
    diff = np.where(both[:, None], centre_world - child_world, 0.0)
    residual = np.sqrt(np.einsum("ni,ni->n", diff, diff))
    residual[~both] = np.nan
    return centre_world, cov_world, residual


# --------------------------------------------------------------------------- ball joint


def _model_error_inflation(
    prep: _Prepared, c_p: FloatArray, c_c: FloatArray, Wp6: FloatArray, Wc6: FloatArray
) -> Inflation:
    """Inflation of the centre covariance from the whitened constraint residuals, in time order."""
    if prep.sigma_parent <= 0.0 and prep.sigma_child <= 0.0:
        return Inflation(factor=1.0, chi2_dof=1.0, rho=0.0)
    used = prep.both
    Q, t = prep.Q[used], prep.t[used]
    h = c_p[None, :] - np.einsum("nij,j->ni", Q, c_c) - t
    z = np.full((len(used), 3), np.nan)
    z[used] = _whitened(h, _constraint_cov(Q, c_p, c_c, Wp6, Wc6))
    return residual_inflation(z, 6)


def _centre_artefact(
    prep: _Prepared,
    Q: FloatArray,
    t: FloatArray,
    c_p: FloatArray,
    c_c: FloatArray,
    Wp6: FloatArray,
    Wc6: FloatArray,
    attachment: tuple[str, str],
    bread_correction: FloatArray | None = None,
) -> ArtefactCovariance:
    """The centre's statistical and soft-tissue covariance (skin markers; :func:`artefact_covariance`).

    Residual ``h_t = c_p - Q_t c_c - t_t``, Jacobian ``[I, -Q_t]`` in ``(c_p, c_c)``, and with
    respect to a cluster motion ``(omega_p, u_p, omega_c, u_c)`` on the bone ``[-[c_p]x, I,
    Q_t [c_c]x, -Q_t]`` (the noise Jacobian of eq. 14, the same perturbation).
    """
    n = Q.shape[0]
    h = c_p[None, :] - np.einsum("nij,j->ni", Q, c_c) - t
    J = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), -Q], axis=2)
    D = np.concatenate(
        [np.broadcast_to(-skew(c_p), (n, 3, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)), Q @ skew(c_c), -Q], axis=2
    )
    W = _constraint_cov(Q, c_p, c_c, Wp6, Wc6)
    weights = deformation_weights(prep.pooled, (prep.sigma_parent, prep.sigma_child), attachment)
    return artefact_covariance(
        h, J, D, W, joint_features(Q), (prep.template_parent, prep.template_child), weights,
        bread_correction=bread_correction,
    )


def _whitened(r: FloatArray, W: FloatArray) -> FloatArray:
    """Per frame ``W^(-1/2) r`` (``r`` (N, k), ``W`` (N, k, k)), with the symmetric square root.

    Symmetric, so independent of the eigenvectors' signs, which vary per frame.
    """
    lam, V = np.linalg.eigh(W)
    lam_safe = np.maximum(lam, 1e-300)
    out: FloatArray = np.einsum("nij,nj->ni", V, np.einsum("nji,nj->ni", V, r) / np.sqrt(lam_safe))
    return out


def _hinge_model_error(
    Q: FloatArray,
    t: FloatArray,
    st: _HingeState,
    bases: tuple[FloatArray, FloatArray, FloatArray],
    Wp6: FloatArray,
    Wc6: FloatArray,
    used: BoolArray,
) -> Inflation:
    """Inflation of the hinge covariance from its whitened 5-dof residuals (used frames, in time order)."""
    res, _, W, _ = _hinge_psi(Q, t, st, bases, Wp6, Wc6, False)
    z = np.full((len(used), 5), np.nan)
    # The direction rows (unitless) and the position rows (lengths) are whitened each by their own
    # block, so that the result does not depend on the length unit.
    for rows in (slice(0, 2), slice(2, 5)):
        z[used, rows] = _whitened(res[:, rows], W[:, rows, rows])
    return max(residual_inflation(z[:, :2], 4), residual_inflation(z[:, 2:], 5), key=lambda inf: inf.factor)


def fit_centre_two_segments(
    parent: ArrayLike,
    child: ArrayLike,
    *,
    method: str = "poses",
    weighted: bool = True,
    model_error: bool = True,
    attachment: str | tuple[str, str] = "skin",
) -> SegmentsCentreFit:
    """Ball-joint centre between two moving segments (Stoddart et al. 1999).

    Parameters
    ----------
    parent, child : array_like, shape (N, Pa, 3) and (N, Pc, 3)
        Marker positions of the two rigid segments, world frame, the same
        frames, any length unit; NaN marks a missing marker. At least 3
        markers per segment.
    method : {"poses", "sphere"}
        ``"poses"`` (default): Stoddart's pose-based estimator. ``"sphere"``:
        the child markers are expressed in the parent frame and fitted with
        :func:`jointfit_core.sphere.fit_centre` (Gamage-Lasenby); rigid
        markers only (``attachment="rigid"``): it has no soft-tissue term, so
        with skin markers it raises InputError rather than understate the error.
    weighted : bool
        For ``"poses"``: ``True`` (default) iterates Stoddart's Gauss-Markov
        solution (appendix eq. 22-23) with the per-frame residual covariance;
        ``False`` returns the unweighted closed form (eq. 9) with a sandwich
        covariance, exactly what :func:`centre_from_pose_sums` (and an online
        estimator) computes. Ignored for ``"sphere"``.
    model_error : bool
        For ``"poses"``: ``True`` (default) inflates the covariance by the
        excess and the frame-to-frame correlation of the joint-constraint
        residuals over the marker-noise model
        (:func:`jointfit_core.model_error.residual_inflation`), so that soft
        tissue artefact on real skin markers widens it; about 1 on data that
        follow the noise model. ``False`` gives the pure noise-propagated
        covariance of Stoddart's eq. (23).
    attachment : {"skin", "rigid"} or (str, str)
        How the markers are attached, for both segments or (parent, child).
        ``"skin"`` (default, marker clusters on skin): the marker noise is
        read from the second differences of the pose-fit residuals
        (:func:`jointfit_core.artefact.white_noise_std`), so that the
        cluster's deformation is not taken for noise in the weights and the
        bias compensation, and with ``model_error`` the covariance is
        ``cov_statistical + cov_artefact``
        (:func:`jointfit_core.artefact.artefact_covariance`): a soft-tissue
        prior on the clusters' motion on the bone, along the directions it
        can bias, scaled from the residuals, plus the residuals' effect with
        their autocorrelation. ``"rigid"`` (robots, markers on rigid bodies,
        bone pins): the pooled residual noise and the inflation by the
        residuals' excess and lag-1 correlation, as before.

    Returns
    -------
    SegmentsCentreFit
        Centres in both local frames (the templates' frames, also returned),
        their covariances, the per-frame world centre carried by the parent
        with its covariance, per-frame residuals, the noise estimates and the
        identifiability verdict.

    Raises
    ------
    InputError
        Wrong shapes, fewer than 3 markers on a segment, different frame
        counts, all-NaN input, fewer than 3 frames where both segments can
        be posed, unknown ``method``.
    NotIdentifiableError
        The motion cannot determine the centre at all (no relative rotation,
        or noise-free rotation about a single axis); the message says which
        movement is missing. Weakly determined centres are returned with
        ``identifiable=False`` and a ``reason`` instead.

    Notes
    -----
    **Poses** (Stoddart et al. 1999, sections 5-7 and appendix). Templates and
    poses come from :func:`jointfit_core.pose.template_from_markers` and
    :func:`~jointfit_core.pose.poses_from_markers` (eq. 4-5); the frames where
    both segments are posed are used. The joint constraint
    ``R_p c_p + d_p = R_c c_c + d_c`` becomes ``c_p = Q_t c_c + t_t`` with
    ``Q_t = R_p^T R_c``, ``t_t = R_p^T (d_c - d_p)``: eq. (9) generalised to
    distinct local frames (Stoddart's choice of both frames equal to the
    world at t = 0 gives ``c_p = c_c``; here the frames are the templates'
    own, so the centres differ by the relative pose at the reference frame).
    The closed form is :func:`centre_from_pose_sums`. The residual
    ``h_t = c_p - Q_t c_c - t_t`` (parent frame) has covariance
    ``W_t = W_p + Q_t W_c Q_t^T`` with ``W_p = sigma_p^2 ([a_p]x I_p^-1
    [a_p]x^T + I / n_p)``, ``a_p = c_p - xbar_p`` the lever from the visible
    parent template centroid to the joint and ``I_p`` the inertia-like tensor
    ``sum (|x|^2 I - x x^T)`` of the centred visible template points
    (Pennec & Thirion's pose covariance propagated to the carried centre;
    likewise ``W_c``). This is eq. (20) with the Jacobian of eq. (14).
    ``weighted=True`` iterates eq. (22) ``a = (sum M^T W_t^-1 M)^-1 sum M^T
    W_t^-1 t_t`` with ``M_t = [I, -Q_t]`` (eq. 13, 19), recomputing ``W_t`` at
    the new ``a``, from the closed form; ``cov(a) = (sum M^T W_t^-1 M)^-1``
    (eq. 23). The weighted fit uses each frame's visible markers for
    ``W_p, W_c``; the unweighted sandwich covariance uses their mean over the
    used frames (see :func:`centre_from_pose_sums`). Frames in which a
    segment's visible markers are nearly collinear or bunched (rotation
    variance above :data:`POSE_VAR_RATIO_MAX` times the full template's, or
    rotation sd above :data:`POSE_ROT_SD_MAX`) are not used.
    ``sigma_p`` and ``sigma_c`` are pooled from each segment's pose-fit
    residuals (:func:`jointfit_core.pose.noise_std_from_fit`). Covariances
    scale with the marker noise variance and, for a fixed range of motion,
    as ``1 / N``; the error grows with the lever arms over the cluster sizes.

    **Sphere** (``method="sphere"``): the child markers in the parent frame,
    ``R_p^T (y - d_p)``, move on spheres about ``c_p``; the Gamage-Lasenby
    fit gives ``centre_parent`` and ``cov_parent`` directly (it treats the
    noise as isotropic and independent, but the parent pose noise, magnified
    by the lever from the parent cluster to the child markers, is
    correlated within a frame, so its covariance is only approximate).
    ``centre_child`` is the mean over the frames of ``Q_t^T (c_p - t_t)``;
    ``cov_child = A cov_parent A^T + cov(Q_t^T (c_p - t_t)) / N`` with
    ``A`` the mean of ``Q_t^T`` (the two terms treated as independent). The
    child needs no pose for the parent-frame centre, so frames with fewer
    than 3 child markers still contribute.

    **Bias compensation.** The poses are noisy in both ``Q_t`` and ``t_t``
    (errors in variables), which biases the estimate by an amount that does
    not shrink with N (on the rig below about 0.2-0.4 sd per coordinate at
    N = 1200). The expected value of the estimating equation under the pose
    noise is evaluated to second order (closed form: analytically, see
    :func:`centre_from_pose_sums`; weighted: with +/- one-sigma
    perturbations of each pose) and removed with one Newton step.

    **Which is better** (seeded Monte-Carlo, 200 trials each, random rigs
    like Stoddart's: 3 markers per segment, clusters 100-200 mm, the joint
    0.5 m from each, sqrt(tr W_y) = 1.7 mm, N = 1200; sqrt(tr cov_parent)
    / rms error of centre_parent / mean of e/3):

    ==========================  ===========  ===========  =====
    method                      sqrt(tr W)   rms error    e/3
    ==========================  ===========  ===========  =====
    poses, weighted (default)   0.42 mm      0.44 mm      1.03
    poses, closed form          0.53 mm      0.52 mm      0.93
    sphere                      0.58 mm      3.4 mm       13
    ==========================  ===========  ===========  =====

    The weighted pose method is the most accurate; the closed form is ~25 %
    worse but O(1) per frame online. The sphere method is biased (~3 mm
    here, toward the parent) and its covariance over-confident, because the
    parent pose noise carried ~1 m to the child markers dominates and is
    correlated within a frame; it becomes competitive only when the parent
    is posed much better than the child (parent cluster 4x larger with 6
    markers: rms error 0.38 mm against 0.31 mm weighted and 0.61 mm closed
    form), and it is the one that needs no child pose in a frame.

    ``centre_world`` is ``R_p c_p + d_p`` and ``cov_world = R_p (cov_parent +
    W_p(t)) R_p^T``: the estimate's uncertainty plus this frame's parent pose
    noise at the centre (their small correlation is ignored). ``residual`` is
    ``|R_p c_p + d_p - R_c c_c - d_c|``.
    """
    if method not in _METHODS:
        raise InputError(f"method: expected one of {_METHODS}, got {method!r}")
    att = check_attachment(attachment)
    if method == "sphere" and "skin" in att:
        raise InputError(
            "method='sphere' has no soft-tissue term: on skin markers its covariance is the white noise's "
            "alone and understates the error by an order of magnitude (the right hip fixture: sd 0.3-0.5 mm "
            "for a centre 10-20 mm from the other methods); use method='poses' (the default), or "
            "attachment='rigid' for markers on rigid bodies"
        )
    skin = "skin" in att  # (method "sphere" took rigid markers only, above)
    prep = _prepare(parent, child, "ball", white=skin)
    used = prep.both
    Q, t = prep.Q[used], prep.t[used]
    n = float(used.sum())

    if method == "sphere":
        return _fit_centre_sphere(prep)

    vis_p, vis_c = prep.poses_parent.visible[used], prep.poses_child.visible[used]
    Wp6 = pose_covariance_local(prep.template_parent, prep.sigma_parent, vis_p)
    Wc6 = pose_covariance_local(prep.template_child, prep.sigma_child, vis_c)
    # The closed form's sandwich takes the mean local pose covariance over the used frames.
    Wp6_mean = Wp6.mean(axis=0)
    Wc6_mean = Wc6.mean(axis=0)
    closed = centre_from_pose_sums(
        pose_sums_from_relative(Q, t), Wp6_mean, Wc6_mean, length_scale=prep.length_scale
    )
    a = np.concatenate([closed.centre_parent, closed.centre_child])
    cov = closed.cov
    bread: FloatArray | None = None
    if weighted and prep.noisy:
        noise_p = pose_noise_local(prep.template_parent, prep.sigma_parent, vis_p)
        noise_c = pose_noise_local(prep.template_child, prep.sigma_child, vis_c)
        a, cov, bread = _gauss_markov_centre(Q, t, noise_p, noise_c, Wp6, Wc6, a)
    c_p, c_c = a[:3], a[3:]
    stat: FloatArray | None = None
    scale = (0.0, 0.0)
    motion = np.zeros(6)
    if model_error and skin and prep.noisy:
        parts = _centre_artefact(prep, Q, t, c_p, c_c, Wp6, Wc6, att, bread)
        cov, stat, scale = parts.total, parts.statistical, (float(parts.scale[0]), float(parts.scale[1]))
        motion = parts.cluster_motion[0]
    elif model_error:
        cov = cov * _model_error_inflation(prep, c_p, c_c, Wp6_mean, Wc6_mean).factor
    cov_parent, cov_child = cov[:3, :3], cov[3:, 3:]
    # a frame's centre is carried by the parent cluster's pose, off its bone's by the cluster's motion
    lever = lever_jacobian(c_p)
    centre_world, cov_world, residual = _world_outputs(prep, c_p, c_c, cov_parent + (lever * motion) @ lever.T)
    # Identifiability is about the motion: judged on the part of the covariance that more or better
    # movement reduces (the soft-tissue part does not shrink with the data).
    v_parent, v_child = (cov_parent, cov_child) if stat is None else (stat[:3, :3], stat[3:, 3:])
    identifiable, reason = _centre_verdict(
        _motion_of(prep, Q), v_parent, v_child, c_p, c_c, prep.length_scale,
        centre_sd_limit(stat is not None),
    )
    return SegmentsCentreFit(
        centre_parent=c_p,
        centre_child=c_c,
        cov_parent=cov_parent,
        cov_child=cov_child,
        template_parent=prep.template_parent,
        template_child=prep.template_child,
        centre_world=centre_world,
        cov_world=cov_world,
        residual=residual,
        rms=float(np.sqrt(np.mean(residual[used] ** 2))),
        n_frames=int(n),
        identifiable=identifiable,
        reason=reason,
        noise_std_parent=prep.sigma_parent,
        noise_std_child=prep.sigma_child,
        method="poses",
        cov_parent_statistical=None if stat is None else stat[:3, :3],
        cov_child_statistical=None if stat is None else stat[3:, 3:],
        attachment=att,
        artefact_scale=scale,
    )


def _fit_centre_sphere(prep: _Prepared) -> SegmentsCentreFit:
    """``method="sphere"`` of :func:`fit_centre_two_segments`."""
    from .sphere import fit_centre  # lazy: keeps this module importable on its own

    pp = prep.poses_parent
    vp = pp.valid
    Rp = np.where(vp[:, None, None], pp.R_world_local, 0.0)
    dp = np.where(vp[:, None], pp.d_world_local, 0.0)
    child_in_parent = np.einsum("nji,npj->npi", Rp, prep.markers_child - dp[:, None, :])
    child_in_parent[~vp] = np.nan
    used = prep.both
    Q, t = prep.Q[used], prep.t[used]
    mo = _motion_of(prep, Q)
    try:
        fit = fit_centre(child_in_parent)
    except NotIdentifiableError as exc:
        raise NotIdentifiableError(f"{_motion_diagnosis(mo)[1]} (sphere fit: {exc})") from None
    c_p = np.asarray(fit.centre, dtype=np.float64)
    cov_parent = np.asarray(fit.cov, dtype=np.float64)

    n = float(used.sum())
    u = np.einsum("nji,nj->ni", Q, c_p[None, :] - t)  # Q^T (c_p - t): the centre in the child frame
    c_c = u.mean(axis=0)
    A = np.swapaxes(Q, -1, -2).mean(axis=0)
    du = u - c_c
    scatter = du.T @ du / max(n - 1.0, 1.0)
    cov_child = A @ cov_parent @ A.T + scatter / n
    cov_child = 0.5 * (cov_child + cov_child.T)

    centre_world, cov_world, residual = _world_outputs(prep, c_p, c_c, cov_parent)
    identifiable, reason = _centre_verdict(mo, cov_parent, cov_child, c_p, c_c, prep.length_scale)
    if not fit.identifiable:
        identifiable = False
        reason = fit.reason if not reason else f"{fit.reason}; {reason}"
    return SegmentsCentreFit(
        centre_parent=c_p,
        centre_child=c_c,
        cov_parent=cov_parent,
        cov_child=cov_child,
        template_parent=prep.template_parent,
        template_child=prep.template_child,
        centre_world=centre_world,
        cov_world=cov_world,
        residual=residual,
        rms=float(np.sqrt(np.mean(residual[used] ** 2))),
        n_frames=int(fit.n_frames),
        identifiable=identifiable,
        reason=reason,
        noise_std_parent=prep.sigma_parent,
        noise_std_child=prep.sigma_child,
        method="sphere",
    )


# --------------------------------------------------------------------------- hinge


def _perp_basis(n: FloatArray) -> FloatArray:
    """Deterministic orthonormal basis (3, 2) of the plane orthogonal to the unit vector ``n``."""
    e = np.zeros(3)
    e[int(np.argmin(np.abs(n)))] = 1.0
    b1 = e - (e @ n) * n
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(n, b1)
    return np.stack([b1, b2], axis=1)


def _complement(z: FloatArray) -> FloatArray:
    """Orthonormal basis (6, 5) of the complement of the unit 6-vector ``z``."""
    U, _, _ = np.linalg.svd(z[:, None])
    out: FloatArray = U[:, 1:]
    return out


@dataclass(frozen=True)
class _HingeState:
    n_p: FloatArray
    n_c: FloatArray
    a: FloatArray  # (c_p, c_c): a corresponding pair of axis points


def _hinge_bases(st: _HingeState) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Tangent bases ``B_p``, ``B_c`` (3, 2) of the directions and the complement ``Z`` (6, 5) of the gauge."""
    z = np.concatenate([st.n_p, st.n_c]) / np.sqrt(2.0)
    return _perp_basis(st.n_p), _perp_basis(st.n_c), _complement(z)


def _hinge_psi(
    Q: FloatArray,
    t: FloatArray,
    st: _HingeState,
    bases: tuple[FloatArray, FloatArray, FloatArray],
    Wp6: FloatArray,
    Wc6: FloatArray,
    weighted: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Hinge residuals (..., 5), parameter Jacobian (..., 5, 9), noise covariance (..., 5, 5) and ``J^T W^-1 r``.

    The parameters are ``(eps_p, eps_c, eta)``: ``n_p += B_p eps_p``, ``n_c += B_c eps_c``,
    ``a += Z eta``. ``Q`` (..., 3, 3) and ``t`` (..., 3) may carry extra leading axes;
    ``Wp6``, ``Wc6`` broadcast against them. Without weights, ``J^T r``.
    """
    Bp, Bc, Z = bases
    n_p, n_c, a = st.n_p, st.n_c, st.a
    c_p, c_c = a[:3], a[3:]
    lead = Q.shape[:-2]
    Qn = np.einsum("...ij,j->...i", Q, n_c)
    res = np.empty((*lead, 5))
    res[..., :2] = (Qn - n_p) @ Bp
    res[..., 2:] = c_p - np.einsum("...ij,j->...i", Q, c_c) - t

    J = np.zeros((*lead, 5, 9))
    J[..., :2, :2] = -np.eye(2)
    J[..., :2, 2:4] = Bp.T @ Q @ Bc
    M = np.concatenate([np.broadcast_to(np.eye(3), Q.shape), -Q], axis=-1)  # (..., 3, 6)
    J[..., 2:, 4:] = M @ Z

    Gp, Gc = _hinge_noise_jacobian(Q, st, Bp)
    W = Gp @ Wp6 @ np.swapaxes(Gp, -1, -2) + Gc @ Wc6 @ np.swapaxes(Gc, -1, -2)
    Jt = np.swapaxes(J, -1, -2)
    psi = (
        np.einsum("...ij,...j->...i", Jt @ _spd_inv(W), res)
        if weighted
        else np.einsum("...ij,...j->...i", Jt, res)
    )
    return res, J, W, psi


def _hinge_noise_jacobian(Q: FloatArray, st: _HingeState, Bp: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Jacobians (..., 5, 6) of the hinge residual w.r.t. ``(omega_p, u_p)`` and ``(omega_c, u_c)``.

    Small pose errors (or cluster motions on the bone) in the local frames, rotations about the origin.
    """
    lead = Q.shape[:-2]
    c_p, c_c = st.a[:3], st.a[3:]
    Qn = np.einsum("...ij,j->...i", Q, st.n_c)
    Gp = np.zeros((*lead, 5, 6))
    Gc = np.zeros((*lead, 5, 6))
    Gp[..., :2, 0:3] = Bp.T @ skew(Qn)
    Gc[..., :2, 0:3] = -Bp.T @ Q @ skew(st.n_c)
    Gp[..., 2:, 0:3] = -skew(c_p)
    Gp[..., 2:, 3:6] = np.eye(3)
    Gc[..., 2:, 0:3] = Q @ skew(c_c)
    Gc[..., 2:, 3:6] = -Q
    return Gp, Gc


def _hinge_step(
    st: _HingeState, delta: FloatArray, bases: tuple[FloatArray, FloatArray, FloatArray]
) -> _HingeState:
    Bp, Bc, Z = bases
    n_p = st.n_p + Bp @ delta[:2]
    n_c = st.n_c + Bc @ delta[2:4]
    return _HingeState(n_p / np.linalg.norm(n_p), n_c / np.linalg.norm(n_c), st.a + Z @ delta[4:])


def _hinge_solve(
    Q: FloatArray,
    t: FloatArray,
    st: _HingeState,
    noise_p: tuple[FloatArray, FloatArray, FloatArray],
    noise_c: tuple[FloatArray, FloatArray, FloatArray],
    Wp6: FloatArray,
    Wc6: FloatArray,
    weighted: bool,
) -> tuple[_HingeState, FloatArray, tuple[FloatArray, FloatArray, FloatArray]]:
    """Gauss-Newton (weighted: Gauss-Markov) on the 9 hinge parameters, then the bias compensation.

    Returns the state, the covariance (9, 9) of the parameters and the bases they refer to.
    """
    bases = _hinge_bases(st)
    A_inv = np.full((9, 9), np.nan)
    J = W = np.zeros((0, 5, 9))
    for it in range(_GM_ITERATIONS + 1):
        bases = _hinge_bases(st)
        _, J, W, psi = _hinge_psi(Q, t, st, bases, Wp6, Wc6, weighted)
        Jt = np.swapaxes(J, -1, -2)
        A = ((Jt @ _spd_inv(W)) @ J if weighted else Jt @ J).sum(axis=0)
        delta, A_inv, ratio = _sym_solve(A, psi.sum(axis=0))
        if ratio <= SINGULAR_REL:
            raise NotIdentifiableError(
                "the hinge normal matrix is singular: the relative rotation does not vary enough to locate "
                "the axis; flex the joint through a larger range"
            )
        if it == _GM_ITERATIONS or float(np.max(np.abs(delta[:4]))) < 1e-13:
            break
        st = _hinge_step(st, -delta, bases)
    if weighted:
        cov = A_inv
    else:
        meat = (np.swapaxes(J, -1, -2) @ W @ J).sum(axis=0)
        cov = A_inv @ meat @ A_inv
    # Second-order bias of the estimating equation under the pose noise (sigma points, as for the centre).
    Qx, tx = _sigma_relative_poses(Q, t, noise_p, noise_c)
    psi_x = _hinge_psi(Qx, tx, st, bases, Wp6[:, None], Wc6[:, None], weighted)[3]
    psi_0 = _hinge_psi(Q, t, st, bases, Wp6, Wc6, weighted)[3]
    expected = 0.5 * psi_x.sum(axis=(0, 1)) - 12.0 * psi_0.sum(axis=0)
    st = _hinge_step(st, A_inv @ expected, bases)
    return st, 0.5 * (cov + cov.T), bases


def _hinge_closed_cov(
    Q: FloatArray, t: FloatArray, st: _HingeState, Wp6: FloatArray, Wc6: FloatArray
) -> tuple[FloatArray, tuple[FloatArray, FloatArray, FloatArray]]:
    """White-noise covariance (9, 9) of the hinge closed form, linearised at it, and the bases it refers to.

    Parameters
    ----------
    Q, t : ndarray, shape (N, 3, 3) and (N, 3)
        Relative poses of the used frames (input units).
    st : _HingeState
        The closed form: the top singular pair of ``sum Q_t`` and the axis-point pair.
    Wp6, Wc6 : ndarray, shape (N, 6, 6)
        Local pose-noise covariances ``(omega, u)`` of the two segments (rad^2, units^2).

    Returns
    -------
    cov : ndarray, shape (9, 9)
        ``A^-1 (sum J^T W J) A^-1``, ``A = sum J^T J``, over ``(eps_p, eps_c, eta)`` as in :func:`_hinge_psi`.
    bases : (ndarray (3, 2), ndarray (3, 2), ndarray (6, 5))

    Raises
    ------
    NotIdentifiableError
        The normal matrix is singular (too little rotation).

    Notes
    -----
    The closed form solves the unweighted hinge equations ``sum_t J_t^T r_t = 0`` to first order: its
    point pair exactly (least squares on ``c_p - Q_t c_c - t_t`` in the complement of the gauge), its
    direction pair up to a weight ``n_p^T Q_t n_c = 1 - O(error^2)`` per frame (the singular-vector
    conditions ``B_p^T sum Q_t n_c = 0``, ``B_c^T sum Q_t^T n_p = 0``), so its first-order covariance is
    the unweighted sandwich, evaluated here at the closed form itself.
    """
    bases = _hinge_bases(st)
    _, J, W, psi = _hinge_psi(Q, t, st, bases, Wp6, Wc6, False)
    Jt = np.swapaxes(J, -1, -2)
    _, A_inv, ratio = _sym_solve((Jt @ J).sum(axis=0), psi.sum(axis=0))
    if ratio <= SINGULAR_REL:
        raise NotIdentifiableError(
            "the hinge normal matrix is singular: the relative rotation does not vary enough to locate "
            "the axis; flex the joint through a larger range"
        )
    cov = A_inv @ (Jt @ W @ J).sum(axis=0) @ A_inv
    return 0.5 * (cov + cov.T), bases


def _axis_reference(reference_direction: ArrayLike | None, n_p: FloatArray) -> FloatArray:
    if reference_direction is not None:
        return check_vector3(reference_direction, name="reference_direction", unit=True)
    ref = np.zeros(3)
    ref[int(np.argmax(np.abs(n_p)))] = 1.0
    return ref


def fit_axis_two_segments(
    parent: ArrayLike,
    child: ArrayLike,
    *,
    reference_direction: ArrayLike | None = None,
    weighted: bool = True,
    model_error: bool = True,
    attachment: str | tuple[str, str] = "skin",
) -> SegmentsAxisFit:
    """Hinge axis between two moving segments from their rigid poses.

    Parameters
    ----------
    parent, child : array_like, shape (N, Pa, 3) and (N, Pc, 3)
        Marker positions of the two rigid segments, world frame, the same
        frames, any length unit; NaN marks a missing marker. At least 3
        markers per segment.
    reference_direction : array_like, shape (3,), optional
        A direction in the parent local frame; ``direction_parent`` is chosen
        so that its dot product with it is >= 0. Default: the parent local
        axis (x, y or z) along which the estimated direction has its largest
        component, i.e. that component is made positive.
    weighted : bool
        Rigid attachment only. ``True`` (default): Gauss-Markov with the
        per-frame noise of the constraints; ``False``: the unweighted
        least-squares solution with a sandwich covariance. Skin attachment
        always reports the closed form (see ``attachment``).
    model_error : bool
        ``True`` (default): grow the covariances by the model error seen in
        the whitened hinge residuals (their size beyond the marker noise and
        their frame-to-frame correlation, as for the ball joint:
        :func:`jointfit_core.model_error.residual_inflation`), so that skin
        motion does not leave them over-confident.
    attachment : {"skin", "rigid"} or (str, str)
        As in :func:`fit_centre_two_segments`: ``"skin"`` (default; either
        segment on skin) reports the closed form (no refinement, no bias
        compensation: the estimate :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums`
        and the online estimator give on the same frames), reads the white
        noise from the residuals' second differences and, with
        ``model_error``, gives ``cov_statistical + cov_artefact`` over the 9
        hinge parameters, both linearised at the closed form
        (:func:`jointfit_core.artefact.artefact_covariance` with
        ``weighted=False``); ``"rigid"`` the Gauss-Markov refinement and the
        previous inflation.

    Returns
    -------
    SegmentsAxisFit
        Direction and point of the axis in both local frames with their
        covariances, the axis in world coordinates carried by the parent,
        per-frame residuals, the noise estimates and the verdict.

    Raises
    ------
    InputError
        As :func:`fit_centre_two_segments`, or a bad ``reference_direction``.
    NotIdentifiableError
        No relative rotation (the axis is undefined).

    Notes
    -----
    A hinge with direction ``n_p`` (parent frame) and ``n_c`` (child frame)
    satisfies ``Q_t n_c = n_p``. **Direction**: maximising ``sum_t n_p^T Q_t
    n_c`` (equivalently minimising ``sum_t |Q_t n_c - n_p|^2``) gives the top
    singular pair of ``S = sum Q_t``: ``n_p`` the left, ``n_c`` the right
    singular vector, so ``Q_t n_c ~ n_p``. Its singular values ``s_k``
    diagnose the motion: ``1 - s_1 / N`` (spread about the axis, noise only
    for a clean hinge) much smaller than ``1 - s_2 / N`` (the flexion range);
    when they are comparable (ratio above :data:`SINGLE_AXIS_RATIO`) the
    motion is not a hinge and the axis is flagged. **Point**: the ball-joint
    system ``c_p = Q_t c_c + t_t`` (see :func:`fit_centre_two_segments`) is
    singular along ``(n_p, n_c)``; it is solved in the complement of that
    direction (pseudo-inverse), giving a corresponding pair of axis points.
    The reported ``point_parent`` is the point of the parent axis nearest the
    parent template centroid (the local origin), ``point_child`` likewise.

    **Refinement and covariance**: the 9 parameters (2 + 2 tangent
    parameters of the directions, 5 of the axis-point pair in the complement
    of the gauge direction ``(n_p, n_c)``) are fitted to the per-frame
    residual ``[B_p^T (Q_t n_c - n_p); c_p - Q_t c_c - t_t]`` (5 values,
    ``B_p`` a basis orthogonal to ``n_p``). Its noise is propagated from the
    pose noise of both segments (Pennec & Thirion, local rotation ``omega``
    and translation ``u``): ``Q_t n_c - n_p`` gets ``[Q_t n_c]x omega_p -
    Q_t [n_c]x omega_c`` (covariance ``[n_p]x Sigma_rot,p [n_p]x^T + Q_t
    [n_c]x Sigma_rot,c [n_c]x^T Q_t^T``) and the point part ``-[c_p]x
    omega_p + u_p + Q_t [c_c]x omega_c - Q_t u_c`` (the two parts are
    correlated through ``omega``, which the 5x5 covariance keeps).
    Rigid attachment, ``weighted=True``: Gauss-Markov iterations (Stoddart
    appendix eq. 22-23) from the closed form, covariance ``(sum J^T W^-1
    J)^-1``; ``weighted=False``: the closed form refined to the stationary
    point of the projected residual, covariance ``A^-1 (sum J^T W J) A^-1``
    with ``A = sum J^T J``. Skin attachment: the closed form itself, with
    that sandwich evaluated at it (the closed form solves the unweighted
    equations to first order: exactly for the point pair, up to a per-frame
    weight ``n_p^T Q_t n_c = 1 - O(misalignment^2)`` for the directions).
    Under soft-tissue artefact the refinement is less accurate than the
    closed form it starts from (its weights come from the white pose noise,
    while the misfit is mostly artefact, which they do not describe):
    measured on the knee of ``bench/sta.py``, ``bench/results/sta_knee_before.md``
    against ``sta_knee_after.md``. The direction covariances are rank 2 (orthogonal to
    the direction). The point covariances are propagated through
    ``point = c - n (n . c)`` and include the along-axis shift caused by the
    direction's uncertainty. All covariances scale with the marker noise
    variance and as ``1 / N`` for a fixed flexion range. Rigid attachment:
    the second-order bias from the noisy poses is removed as in
    :func:`fit_centre_two_segments`.

    Measured (rigid attachment; seeded Monte-Carlo, 200 random
    Stoddart-like rigs with a +/-50 deg hinge, sqrt(tr W_y) = 1.7 mm, N =
    1200, weighted): direction sd ~0.055 deg (sqrt(tr cov) 0.97 mrad, rms error 0.97 mrad, mean e/2
    1.02); point sqrt(tr cov) 0.48 mm, rms error 0.47 mm, mean e/3 0.93.
    The closed form is ~5-10 % less precise.

    ``direction_world = R_p n_p``, ``point_world = R_p point_parent + d_p``;
    ``residual`` is the distance of the parent-carried axis point from the
    child-carried axis line.
    """
    att = check_attachment(attachment)
    skin = "skin" in att
    prep = _prepare(parent, child, "hinge", white=skin)
    used = prep.both
    Q, t = prep.Q[used], prep.t[used]
    n = float(used.sum())
    S = Q.sum(axis=0)
    U, s, V = svd3(S)
    deficit = np.clip(1.0 - s / n, 0.0, None)
    if deficit[1] <= SINGULAR_REL:
        raise NotIdentifiableError(
            "no relative rotation between the child and the parent: the hinge axis is undefined; flex the joint"
        )
    n_p, n_c = U[:, 0].copy(), V[:, 0].copy()
    ref = _axis_reference(reference_direction, n_p)
    if n_p @ ref < 0.0:
        n_p, n_c = -n_p, -n_c

    # Closed-form axis-point pair: pseudo-inverse of H in the complement of (n_p, n_c).
    g = np.concatenate([t.sum(axis=0), -np.einsum("nji,nj->i", Q, t)])
    st = _HingeState(n_p, n_c, gauge_free_pinv(U, s, V, n) @ g)

    vis_p, vis_c = prep.poses_parent.visible[used], prep.poses_child.visible[used]
    Wp6 = pose_covariance_local(prep.template_parent, prep.sigma_parent, vis_p)
    Wc6 = pose_covariance_local(prep.template_child, prep.sigma_child, vis_c)
    if skin:  # the closed form itself: under soft-tissue artefact the refinement moves it away from the truth
        cov, (Bp, Bc, Z) = _hinge_closed_cov(Q, t, st, Wp6, Wc6)
    else:
        noise_p = pose_noise_local(prep.template_parent, prep.sigma_parent, vis_p)
        noise_c = pose_noise_local(prep.template_child, prep.sigma_child, vis_c)
        use_weights = weighted and prep.noisy
        st, cov, (Bp, Bc, Z) = _hinge_solve(Q, t, st, noise_p, noise_c, Wp6, Wc6, use_weights)
    stat: FloatArray | None = None
    scale = (0.0, 0.0)
    if model_error and prep.noisy and skin:
        res, J, W, _ = _hinge_psi(Q, t, st, (Bp, Bc, Z), Wp6, Wc6, False)
        D = np.concatenate(_hinge_noise_jacobian(Q, st, Bp), axis=-1)
        weights = deformation_weights(prep.pooled, (prep.sigma_parent, prep.sigma_child), att)
        parts = artefact_covariance(
            res, J, D, W, joint_features(Q), (prep.template_parent, prep.template_child), weights, weighted=False
        )
        cov, stat, scale = parts.total, parts.statistical, (float(parts.scale[0]), float(parts.scale[1]))
    elif model_error and prep.noisy:
        cov = cov * _hinge_model_error(Q, t, st, (Bp, Bc, Z), Wp6, Wc6, used).factor
    n_p, n_c = st.n_p, st.n_c
    if n_p @ ref < 0.0:  # cannot flip in a few small steps, but keep the promise
        n_p, n_c = -n_p, -n_c
    c_p, c_c = st.a[:3], st.a[3:]
    point_p = c_p - n_p * (n_p @ c_p)
    point_c = c_c - n_c * (n_c @ c_c)

    # Project on the planes orthogonal to the final directions (the bias step moved them slightly).
    P_p = np.eye(3) - np.outer(n_p, n_p)
    P_c = np.eye(3) - np.outer(n_c, n_c)
    cov_dir_p = P_p @ Bp @ cov[:2, :2] @ Bp.T @ P_p
    cov_dir_c = P_c @ Bc @ cov[2:4, 2:4] @ Bc.T @ P_c
    Jpp = np.zeros((3, 9))
    Jpp[:, :2] = -((st.n_p @ c_p) * Bp + np.outer(st.n_p, c_p @ Bp))
    Jpp[:, 4:] = (np.eye(3) - np.outer(st.n_p, st.n_p)) @ Z[:3]
    Jpc = np.zeros((3, 9))
    Jpc[:, 2:4] = -((st.n_c @ c_c) * Bc + np.outer(st.n_c, c_c @ Bc))
    Jpc[:, 4:] = (np.eye(3) - np.outer(st.n_c, st.n_c)) @ Z[3:]
    cov_pt_p = Jpp @ cov @ Jpp.T
    cov_pt_c = Jpc @ cov @ Jpc.T
    stat_dir_p = stat_pt_p = None
    v_dir = (cov_dir_p, cov_dir_c, cov_pt_p, cov_pt_c)
    if stat is not None:
        stat_dir_p = P_p @ Bp @ stat[:2, :2] @ Bp.T @ P_p
        stat_dir_p = 0.5 * (stat_dir_p + stat_dir_p.T)
        stat_pt_p = Jpp @ stat @ Jpp.T
        stat_pt_p = 0.5 * (stat_pt_p + stat_pt_p.T)
        # the verdict on the part that more movement reduces (see fit_centre_two_segments)
        v_dir = (stat_dir_p, P_c @ Bc @ stat[2:4, 2:4] @ Bc.T @ P_c, stat_pt_p, Jpc @ stat @ Jpc.T)

    # World outputs and residuals.
    pp, pc = prep.poses_parent, prep.poses_child
    vp = pp.valid
    Rp = np.where(vp[:, None, None], pp.R_world_local, 0.0)
    direction_world = np.einsum("nij,j->ni", Rp, n_p)
    point_world = np.einsum("nij,j->ni", Rp, point_p) + np.where(vp[:, None], pp.d_world_local, 0.0)
    direction_world[~vp] = np.nan
    point_world[~vp] = np.nan
    Rc = np.where(used[:, None, None], pc.R_world_local, 0.0)
    child_point = np.einsum("nij,j->ni", Rc, point_c) + np.where(used[:, None], pc.d_world_local, 0.0)
    child_dir = np.einsum("nij,j->ni", Rc, n_c)
    diff = np.where(used[:, None], point_world - child_point, 0.0)
    along = np.einsum("ni,ni->n", diff, child_dir)
    perp = diff - along[:, None] * child_dir
    residual = np.sqrt(np.einsum("ni,ni->n", perp, perp))
    residual[~used] = np.nan

    identifiable, reason = _axis_verdict(_motion_of(prep, Q), *v_dir, point_p, point_c, prep.length_scale)
    return SegmentsAxisFit(
        direction_parent=n_p,
        point_parent=point_p,
        direction_child=n_c,
        point_child=point_c,
        cov_direction_parent=0.5 * (cov_dir_p + cov_dir_p.T),
        cov_point_parent=0.5 * (cov_pt_p + cov_pt_p.T),
        cov_direction_child=0.5 * (cov_dir_c + cov_dir_c.T),
        cov_point_child=0.5 * (cov_pt_c + cov_pt_c.T),
        template_parent=prep.template_parent,
        template_child=prep.template_child,
        direction_world=direction_world,
        point_world=point_world,
        residual=residual,
        rms=float(np.sqrt(np.mean(residual[used] ** 2))),
        n_frames=int(n),
        identifiable=identifiable,
        reason=reason,
        noise_std_parent=prep.sigma_parent,
        noise_std_child=prep.sigma_child,
        cov_direction_parent_statistical=stat_dir_p,
        cov_point_parent_statistical=stat_pt_p,
        attachment=att,
        artefact_scale=scale,
    )


def _axis_verdict(
    mo: _Motion,
    cov_dir_p: FloatArray,
    cov_dir_c: FloatArray,
    cov_pt_p: FloatArray,
    cov_pt_c: FloatArray,
    point_p: FloatArray,
    point_c: FloatArray,
    length_scale: float,
) -> tuple[bool, str]:
    deficit, noise = mo.deficit, mo.noise
    flexion = _spread_deg(deficit[1])
    if not mo.excited[1]:
        return False, (
            f"no relative rotation beyond the pose noise (rms spread ~{flexion:.2g} deg, noise alone "
            f"~{_spread_deg(noise[1]):.2g} deg): the hinge axis is undetermined; flex the joint through a larger "
            "range"
        )
    wobble = deficit[0] - noise[0]
    if wobble > SINGLE_AXIS_RATIO * (deficit[1] - noise[1]):
        return False, (
            f"the relative rotation is not about a single fixed axis (rms spread about the best axis "
            f"{_fmt_dir(mo.axes[:, 0])} ~{_spread_deg(deficit[0]):.2g} deg, beyond the pose noise "
            f"~{_spread_deg(noise[0]):.2g} deg, against ~{flexion:.2g} deg about the others): the motion is not a "
            "hinge and the axis is not determined; use fit_centre_two_segments for a ball joint, or flex only "
            "about the hinge axis"
        )
    sd_dir = np.rad2deg(max(_max_sd(cov_dir_p), _max_sd(cov_dir_c)))
    if not np.isfinite(sd_dir) or sd_dir > AXIS_SD_MAX_DEG:
        return False, (
            f"axis direction poorly determined (sd {sd_dir:.3g} deg > {AXIS_SD_MAX_DEG:g} deg; flexion range "
            f"~{flexion:.2g} deg rms): flex the joint through a larger range or record more frames"
        )
    sd_pt = max(_max_sd(cov_pt_p), _max_sd(cov_pt_c))
    lever = max(float(np.linalg.norm(point_p)), float(np.linalg.norm(point_c)), length_scale)
    if not np.isfinite(sd_pt) or sd_pt > SD_REL_MAX * lever:
        return False, (
            f"axis position poorly determined (sd {sd_pt:.3g} > {SD_REL_MAX:.0%} of the lever arm {lever:.3g}; "
            f"flexion range ~{flexion:.2g} deg rms): flex the joint through a larger range or record more frames"
        )
    return True, ""
