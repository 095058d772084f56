"""Solving an online joint's window: from its sums vector to the estimate with its covariances.

:func:`solve_window` is all an estimate needs, from a :class:`SolveRequest`
(a copy of the window's sums and the joint's settings; picklable, so that the
node can solve in another process, :mod:`jointfit_ros.solver_process`) to a
:class:`SolveResult`: the closed forms on the window's pose sums
(:func:`~jointfit_core.segments.centre_from_pose_sums`,
:func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums`; Stoddart et al.
eq. 9), their covariances widened by the joint residual's serial correlation
(:mod:`jointfit_core.serial`), the soft-tissue part
(:mod:`jointfit_core.artefact_sums`) and the movement verdict of skin markers.
The sums' layout is :mod:`jointfit_core.joint_sums`'.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .artefact import deformation_weights
from .artefact_sums import (
    SumsArtefact,
    artefact_from_sums,
    ball_parameters,
    ball_parameters_jacobian,
    hinge_parameters,
)
from .hinge_from_sums import PoseSumsAxis, axis_from_pose_sums
from .joint_fit_check import expected_residual_rms, not_a_joint_reason
from .joint_sums import (
    _FM,
    _FS,
    _LAG,
    _MOVE,
    _SS,
    _TL,
    _W,
    _WN,
    _Z,
    _ZZ,
)
from .segments import (
    AXIS_SD_MAX_DEG,
    SD_REL_MAX,
    PoseSums,
    PoseSumsCentre,
    centre_from_pose_sums,
    centre_sd_limit,
)
from .serial import (
    NOMINAL_RATE_HZ,
    LagSums,
    SerialInflation,
    TimeLagSums,
    hinge_residual_pair,
    integrated_factor,
    lag1_autocorrelation_from_sums,
    lag_nodes,
    residual_lag_sum_from_sums,
    residual_sum_squares_from_sums,
    rotation_residual_sums,
    serial_factor,
    smooth_energy_from_lags,
)
from .white_noise_sums import white_noise_from_sums

__all__ = ["SKIN_MIN_MOVEMENT_S", "SolveRequest", "SolveResult", "solve_window", "unpack_pose_sums"]

FloatArray = NDArray[np.float64]

#: Skin markers: the least movement (s) in the window before an estimate may be called identifiable.
#: The soft-tissue artefact is correlated over about a second of movement (0.8 s of data per
#: independent sample on the hip model, ``bench/sta_online.py``), and its size is read from the
#: residual's correlation at lags of up to seconds (:func:`~jointfit_core.serial.smooth_energy_from_lags`);
#: from less movement (the first second of a session, or after a still stance) the skin part reads 0
#: and the estimate was confidently wrong (knee, 10 mm of artefact, 0.3-0.8 s of movement: e/2 up to
#: 250; ``test/test_skin_movement.py``). Two independent samples of the artefact: 2 s.
SKIN_MIN_MOVEMENT_S = 2.0


def _gather_indices() -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Indices into the sums of ``K = sum kron(Q, Q)`` (9, 9), ``sum Q^T t`` (3, 3: summed over axis 0) and ``|t|^2`` (3).

    ``vec(Z) vec(Z)^T`` holds ``Z_ij Z_kl`` at ``(4 i + j, 4 k + l)``; ``K`` has ``Q_ij Q_kl`` at
    ``(3 i + k, 3 j + l)``; ``(Q^T t)_j = sum_i Q_ij t_i``; ``|t|^2 = sum_i t_i t_i``.
    """
    i, k, j, l = np.meshgrid(range(3), range(3), range(3), range(3), indexing="ij")  # K row (i, k), column (j, l)
    K = (_ZZ.start + (4 * i + j) * 12 + 4 * k + l).reshape(9, 9)
    ii, jj = np.meshgrid(range(3), range(3), indexing="ij")
    qt = _ZZ.start + (4 * ii + jj) * 12 + 4 * ii + 3
    tt = _ZZ.start + (4 * np.arange(3) + 3) * 13
    return K, qt, tt


_K_IDX, _QT_IDX, _TT_IDX = _gather_indices()



# --------------------------------------------------------------------------- serial correlation


def _max_sd(cov: FloatArray, limit: float) -> float:
    """Largest standard deviation of ``cov``, or ``sqrt(tr cov)`` (an upper bound) when that is within ``limit``."""
    bound = float(np.sqrt(max(float(np.trace(cov)), 0.0)))
    if bound <= limit:
        return bound
    return float(np.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0)))


def _inflated(
    sol: PoseSumsCentre | PoseSumsAxis, factor: float, seconds: float, length_scale: float, centre_limit: float
) -> PoseSumsCentre | PoseSumsAxis:
    """The estimate with its covariances times ``factor``; flagged when they exceed the verdict's limits.

    The limits are the ones the closed forms check (a centre's standard deviation above
    ``centre_limit`` of the lever arm (:data:`~jointfit_core.segments.CENTRE_SD_REL_MAX`, skin
    markers :data:`~jointfit_core.segments.SD_REL_MAX`), an axis point's above
    :data:`~jointfit_core.segments.SD_REL_MAX`, a direction sd
    above :data:`~jointfit_core.segments.AXIS_SD_MAX_DEG`); an estimate already
    flagged keeps its reason.
    """
    why = f"(the joint residual is correlated over {seconds:.3g} s of data: covariance x{factor:.3g})"
    advice = "record more, and more varied, movement cycles"
    identifiable, reason = sol.identifiable, sol.reason
    if isinstance(sol, PoseSumsCentre):
        cov = factor * sol.cov
        cov_p, cov_c = cov[:3, :3], cov[3:, 3:]
        if identifiable:
            lever = max(float(np.linalg.norm(sol.centre_parent)), float(np.linalg.norm(sol.centre_child)), length_scale)
            sd = max(_max_sd(cov_p, centre_limit * lever), _max_sd(cov_c, centre_limit * lever))
            if not sd <= centre_limit * lever:
                identifiable = False
                reason = (
                    f"centre poorly determined: its standard deviation ({sd:.3g}) exceeds {centre_limit:.0%} of the "
                    f"lever arm ({lever:.3g}) once the frames' correlation is accounted for {why}; {advice}"
                )
        return replace(sol, cov=cov, cov_parent=cov_p, cov_child=cov_c, identifiable=identifiable, reason=reason)
    cov_dp, cov_dc = factor * sol.cov_direction_parent, factor * sol.cov_direction_child
    cov_pp, cov_pc = factor * sol.cov_point_parent, factor * sol.cov_point_child
    if identifiable:
        dir_max = float(np.deg2rad(AXIS_SD_MAX_DEG))
        sd_dir = float(np.rad2deg(max(_max_sd(cov_dp, dir_max), _max_sd(cov_dc, dir_max))))
        lever = max(float(np.linalg.norm(sol.point_parent)), float(np.linalg.norm(sol.point_child)), length_scale)
        sd_pt = max(_max_sd(cov_pp, SD_REL_MAX * lever), _max_sd(cov_pc, SD_REL_MAX * lever))
        if not sd_dir <= AXIS_SD_MAX_DEG:
            identifiable = False
            reason = (
                f"axis direction poorly determined (sd {sd_dir:.3g} deg > {AXIS_SD_MAX_DEG:g} deg once the frames' "
                f"correlation is accounted for {why}): {advice}"
            )
        elif not sd_pt <= SD_REL_MAX * lever:
            identifiable = False
            reason = (
                f"axis position poorly determined (sd {sd_pt:.3g} > {SD_REL_MAX:.0%} of the lever arm {lever:.3g} "
                f"once the frames' correlation is accounted for {why}): {advice}"
            )
    return replace(
        sol,
        cov_direction_parent=cov_dp,
        cov_direction_child=cov_dc,
        cov_point_parent=cov_pp,
        cov_point_child=cov_pc,
        identifiable=identifiable,
        reason=reason,
    )



def unpack_pose_sums(s: FloatArray) -> tuple[PoseSums, FloatArray, FloatArray, float, float]:
    """:meth:`~jointfit_core.estimator.OnlineJoint.pose_sums` of a sums vector (the estimator's layout, at least one frame)."""
    n = float(s[0])
    Z = s[_Z].reshape(3, 4)
    sums = PoseSums(n, Z[:, :3], Z[:, 3], s[_QT_IDX].sum(axis=0), float(s[_TT_IDX].sum()), s[_K_IDX])
    ssp, dofp, ssc, dofc = s[_SS : _SS + 4]
    sigma_p = float(np.sqrt(max(ssp, 0.0) / dofp)) if dofp > 0 else 0.0
    sigma_c = float(np.sqrt(max(ssc, 0.0) / dofc)) if dofc > 0 else 0.0
    W = s[_W]
    return sums, W[:36].reshape(6, 6) / n, W[36:].reshape(6, 6) / n, sigma_p, sigma_c


@dataclass(frozen=True, eq=False)
class SolveRequest:
    """One window's sums and settings, all :func:`solve_window` needs (made by :meth:`~jointfit_core.estimator.OnlineJoint.solve_request`).

    Copies only, no reference to the estimator, and picklable: the node solves
    in a separate process while the estimator takes further frames.

    Attributes
    ----------
    kind : str
        "ball" or "hinge".
    sums : ndarray, shape (n_sums,)
        A copy of the window's sums vector (the estimator's layout: relative
        poses, their outer products, pose-noise weights, residual sums and
        lag pairs; one array, so that sending it costs little).
    noise_std : tuple of (float or None)
        The fixed marker noise (parent, child), input units; None: estimated from the residual sums.
    length_scale : float
        The larger template rms radius, input units.
    reference_direction : ndarray, shape (3,), or None
        Hinge sign convention in the parent frame.
    serial_correlation : bool
        Whether the covariances take the serial-correlation factor.
    generation, version : int
        The estimator's state the request was made in (:meth:`~jointfit_core.estimator.OnlineJoint.install` drops stale results).
    attachment : (str, str)
        ``"skin"`` or ``"rigid"`` for the parent and the child: skin adds the
        soft-tissue part (:func:`~jointfit_core.artefact_sums.artefact_from_sums`).
    radii : (float, float)
        The two templates' rms radii, input units.
    n_markers : (int, int)
        Marker counts of the parent and the child (the soft-tissue prior's, :func:`~jointfit_core.artefact.prior_scale2`).
    """

    kind: str
    sums: FloatArray
    noise_std: tuple[float | None, float | None]
    length_scale: float
    reference_direction: FloatArray | None
    serial_correlation: bool
    generation: int
    version: int
    attachment: tuple[str, str] = ("rigid", "rigid")
    radii: tuple[float, float] = (0.0, 0.0)
    n_markers: tuple[int, int] = (4, 4)


@dataclass(frozen=True, eq=False)
class SolveResult:
    """:func:`solve_window`'s answer to a :class:`SolveRequest` (picklable).

    Attributes
    ----------
    solution : PoseSumsCentre or PoseSumsAxis
        The estimate, covariances with the serial-correlation factor.
    serial : SerialInflation
        The residual's lag-1 correlation, the frame interval and the factor applied.
    noise_std : tuple of float
        The marker noise (parent, child) used, input units.
    generation, version : int
        The request's.
    statistical : PoseSumsCentre or PoseSumsAxis or None
        Skin markers: the estimate with the statistical covariances only
        (white noise and serial correlation; ``solution`` has them plus the
        soft-tissue part); None for rigid markers (``solution`` is that).
    artefact_scale : float
        The soft-tissue prior's estimated scale (input units per radian; 0 for rigid).
    white_noise_std : tuple of float or None
        Skin markers: the white marker noise (parent, child) read from the second differences of
        the pose-fit residuals (:mod:`~jointfit_core.white_noise_sums`), where the window has frame
        triples for it (else the pooled noise), input units; what a ball joint's bias compensation
        used. None for rigid markers (``noise_std`` is white noise there).
    cluster_motion : ndarray, shape (2, 6) or None
        Skin markers: per frame, the variance of each cluster's motion on its bone, ``(omega, u)``
        per component, parent then child (:attr:`~jointfit_core.artefact_sums.SumsArtefact.cluster_motion`);
        None for rigid markers.
    """

    solution: PoseSumsCentre | PoseSumsAxis
    serial: SerialInflation
    noise_std: tuple[float, float]
    generation: int
    version: int
    statistical: PoseSumsCentre | PoseSumsAxis | None = None
    artefact_scale: float = 0.0
    white_noise_std: tuple[float, float] | None = None
    cluster_motion: FloatArray | None = None


def solve_window(request: SolveRequest) -> SolveResult:
    """Solve a window: the closed form on its sums, then the serial-correlation factor.

    Parameters
    ----------
    request : SolveRequest

    Returns
    -------
    SolveResult

    Raises
    ------
    InputError
        Fewer than 3 frames in the sums.
    NotIdentifiableError
        The window's motion cannot determine the joint at all.

    Notes
    -----
    Ball: :func:`~jointfit_core.segments.centre_from_pose_sums`; hinge:
    :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums` (Stoddart et al.,
    eqs. 10-13 and 19, on running sums). The factor is
    :func:`~jointfit_core.serial.integrated_factor` of the joint residual's
    autocorrelation at the frame interval and at lags in seconds (see
    :class:`~jointfit_core.joint_estimate.JointEstimate`'s Notes); skin markers add the soft-tissue part,
    scaled from the residual's smooth part
    (:func:`~jointfit_core.serial.smooth_energy_from_lags`; hinge: also from
    the axis-alignment residual, :func:`~jointfit_core.serial.rotation_residual_sums`).
    """
    sums, Wp_unit, Wc_unit, sigma_p, sigma_c = unpack_pose_sums(request.sums)
    fixed_p, fixed_c = request.noise_std
    sigma_p = sigma_p if fixed_p is None else fixed_p
    sigma_c = sigma_c if fixed_c is None else fixed_c
    Wp, Wc = sigma_p**2 * Wp_unit, sigma_c**2 * Wc_unit
    scale = request.length_scale
    skin = "skin" in request.attachment
    white = _white_noise(request, (sigma_p, sigma_c)) if skin else None
    centre_limit = centre_sd_limit(skin)
    sol: PoseSumsCentre | PoseSumsAxis
    W_bias = None if white is None else (white[0] ** 2 * Wp_unit, white[1] ** 2 * Wc_unit)
    if request.kind == "ball":
        sol = centre_from_pose_sums(sums, Wp, Wc, length_scale=scale, W_bias=W_bias, sd_limit=centre_limit)
        c_p, c_c = sol.centre_parent, sol.centre_child
    else:
        sol = axis_from_pose_sums(
            sums, Wp, Wc, length_scale=scale, reference_direction=request.reference_direction, W_bias=W_bias
        )
        c_p, c_c = hinge_residual_pair(sums, sol.direction_parent, sol.direction_child, sol.point_parent, sol.point_child)
    lag = LagSums.from_vector(request.sums[_LAG : _LAG + 29])
    tl = TimeLagSums.from_vector(request.sums[_TL])
    nodes = lag_nodes(lag, tl)
    lags = np.array([x for x, _ in nodes])
    counts = np.array([node.n_pairs for _, node in nodes])
    ss = residual_sum_squares_from_sums(sums, c_p, c_c)
    lag_sums = np.array([residual_lag_sum_from_sums(node, c_p, c_c) for _, node in nodes])
    rho_raw = lag1_autocorrelation_from_sums(sums, lag, c_p, c_c)
    rho, _ = serial_factor(rho_raw)
    dt = tl.frame_interval
    factor = 1.0
    if request.serial_correlation and lags.size and ss > 0.0:
        factor = integrated_factor(lags, lag_sums / counts / (ss / float(sums.n)), dt, float(sums.n), counts)
    if factor != 1.0:
        sol = _inflated(sol, factor, factor * dt, scale, centre_limit)
    serial = SerialInflation(rho=rho, rho_raw=rho_raw, factor=factor, n_pairs=lag.n_pairs, frame_interval_s=dt)
    if not skin:  # rigid markers: the joint residual is the poses' noise, or no joint (skin: the prior's part)
        return SolveResult(_joint_verdict(sol, Wp, Wc), serial, (sigma_p, sigma_c), request.generation, request.version)
    smooth, rotation_smooth, rotation_ss = 0.0, 0.0, 0.0
    if lags.size:
        smooth = smooth_energy_from_lags(lag_sums, counts, lags, ss, float(sums.n))
        if isinstance(sol, PoseSumsAxis):
            n_p, n_c = sol.direction_parent, sol.direction_child
            rot = [rotation_residual_sums(sums, node, n_p, n_c) for _, node in nodes]
            rotation_ss = rot[0][0]
            rotation_smooth = smooth_energy_from_lags([g for _, g in rot], counts, lags, rotation_ss, float(sums.n))
    assert white is not None
    art = _sums_artefact(
        request, sums, sol, (c_p, c_c), smooth, rotation_smooth, rotation_ss,
        deformation_weights((sigma_p, sigma_c), white, request.attachment),
    )
    window_s = float(sums.n) * dt if dt > 0.0 else float(sums.n) / NOMINAL_RATE_HZ
    total = _movement_verdict(_with_artefact(sol, art.cov), float(request.sums[_MOVE]), window_s)
    return SolveResult(
        total, serial, (sigma_p, sigma_c), request.generation, request.version, sol, art.scale, white, art.cluster_motion
    )


def _joint_verdict(sol: PoseSumsCentre | PoseSumsAxis, Wp: FloatArray, Wc: FloatArray) -> PoseSumsCentre | PoseSumsAxis:
    """Rigid markers: an estimate whose joint residual is far beyond the poses' noise, flagged not identifiable.

    :func:`~jointfit_core.joint_fit_check.not_a_joint_reason`: the two segments do not turn about one
    joint of this kind (a segment between them, the wrong segments, or markers on skin marked rigid); its
    covariance would be that of a joint.
    """
    if not sol.identifiable:
        return sol
    if isinstance(sol, PoseSumsCentre):
        points, kind = (sol.centre_parent, sol.centre_child), "ball"
    else:
        points, kind = (sol.point_parent, sol.point_child), "hinge"
    reason = not_a_joint_reason(float(sol.rms), expected_residual_rms(Wp, Wc, *points), kind)
    return dataclasses.replace(sol, identifiable=False, reason=reason) if reason else sol


def _white_noise(request: SolveRequest, pooled: tuple[float, float]) -> tuple[float, float]:
    """Skin markers: each segment's white noise, the smaller of the window's second-difference reading and the pooled one.

    As :func:`~jointfit_core.segments.fit_centre_two_segments` reads it over a recording (``min``:
    the second differences of a cluster without deformation read the pooled noise, to sampling);
    the pooled noise where the window has no frame triple (3-marker clusters, every frame occluded
    differently) or the noise is fixed.
    """
    read = white_noise_from_sums(request.sums[_WN])
    out = []
    for k in range(2):
        w = read[k]
        fixed = request.noise_std[k] is not None
        out.append(pooled[k] if fixed or not np.isfinite(w) else min(pooled[k], w))
    return (out[0], out[1])


def _movement_verdict(sol: PoseSumsCentre | PoseSumsAxis, seconds: float, window_s: float) -> PoseSumsCentre | PoseSumsAxis:
    """A skin estimate from too little movement, flagged not identifiable.

    ``seconds`` of movement in a window of ``window_s`` (its frames times their mean interval):
    at least :data:`SKIN_MIN_MOVEMENT_S`, or half the window when it is shorter than twice that
    (a window of 2 s could never hold 2 s of movement; half of it moving keeps the stance from
    dominating the residual's correlation).
    """
    needed = min(SKIN_MIN_MOVEMENT_S, 0.5 * window_s)
    if not sol.identifiable or seconds >= needed:
        return sol
    reason = (
        f"skin markers: {seconds:.2g} s of movement in the window so far; the soft-tissue artefact's size is read "
        f"from at least {needed:.2g} s of it (before, the estimate looks more certain than it is): keep moving"
    )
    return replace(sol, identifiable=False, reason=reason)


def _sums_artefact(
    request: SolveRequest,
    sums: PoseSums,
    sol: PoseSumsCentre | PoseSumsAxis,
    centres: tuple[FloatArray, FloatArray],
    smooth: float,
    rotation_smooth: float = 0.0,
    rotation_ss: float = 0.0,
    deformation: tuple[float, float] = (0.0, 0.0),
) -> SumsArtefact:
    """The soft-tissue covariance of a window's estimate (skin segments weighted equally).

    ``deformation``: each segment's deformation variance (:func:`~jointfit_core.artefact.deformation_weights`),
    whose larger sets the literature prior on the scale, with that segment's marker count.
    """
    n = float(sums.n)
    S, st, sqt = np.asarray(sums.S), np.asarray(sums.sum_t), np.asarray(sums.sum_qt_t)
    weights = (float(request.attachment[0] == "skin"), float(request.attachment[1] == "skin"))
    jacobian: Callable[[FloatArray], FloatArray] | None = None
    if isinstance(sol, PoseSumsCentre):
        def solver(X: FloatArray) -> FloatArray:
            return np.stack([ball_parameters(n, x[:9].reshape(3, 3), x[9:12], x[12:]) for x in X])

        def jacobian(x: FloatArray) -> FloatArray:
            return ball_parameters_jacobian(n, x[:9].reshape(3, 3), x[9:12], x[12:])
    else:
        ref = sol.direction_parent.copy()

        def solver(X: FloatArray) -> FloatArray:
            return hinge_parameters(n, X[:, :9].reshape(-1, 3, 3), X[:, 9:12], X[:, 12:], ref)
    directions = None if isinstance(sol, PoseSumsCentre) else (sol.direction_parent, sol.direction_child)
    fs = request.sums[_FS] if directions is None else np.concatenate([request.sums[_FS], request.sums[_FM]])
    return artefact_from_sums(
        fs, n, S, st, sqt, solver, centres, request.radii, weights, smooth, directions,
        rotation_smooth, rotation_ss, jacobian,
        deformation=max(deformation), n_markers=request.n_markers[int(np.argmax(deformation))],
    )


def _with_artefact(sol: PoseSumsCentre | PoseSumsAxis, cov: FloatArray) -> PoseSumsCentre | PoseSumsAxis:
    """The estimate with the soft-tissue covariance added (ball: over ``(c_p, c_c)``; hinge: directions, points)."""
    if isinstance(sol, PoseSumsCentre):
        total = sol.cov + cov
        return replace(sol, cov=total, cov_parent=total[:3, :3], cov_child=total[3:, 3:])
    # The soft-tissue part is linearised at the closed form without the bias step
    # (artefact_sums.hinge_parameters): keep each direction's covariance orthogonal to the published direction.
    P_p = np.eye(3) - np.outer(sol.direction_parent, sol.direction_parent)
    P_c = np.eye(3) - np.outer(sol.direction_child, sol.direction_child)
    return replace(
        sol,
        cov_direction_parent=sol.cov_direction_parent + P_p @ cov[:3, :3] @ P_p,
        cov_direction_child=sol.cov_direction_child + P_c @ cov[3:6, 3:6] @ P_c,
        cov_point_parent=sol.cov_point_parent + cov[6:9, 6:9],
        cov_point_child=sol.cov_point_child + cov[9:, 9:],
    )


# --------------------------------------------------------------------------- the estimator


