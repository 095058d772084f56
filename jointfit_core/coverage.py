"""How far a joint's motion has come toward what the identifiability verdict needs ("coverage").

The two-segment closed forms (:func:`~jointfit_core.segments.centre_from_pose_sums`,
:func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums`) call an estimate
identifiable when (1) the relative rotation exceeds what the pose noise alone
would cause about the directions the joint needs (a ball: all three, i.e.
rotation about at least two axes; a hinge: the flexion) and (2) its standard
deviation is within the verdict's limit (a centre:
:data:`~jointfit_core.segments.CENTRE_SD_REL_MAX` of the lever arm; an axis point:
:data:`~jointfit_core.segments.SD_REL_MAX` of it; a hinge direction:
:data:`~jointfit_core.segments.AXIS_SD_MAX_DEG`). Coverage measures both in
the same units: the information there is against the information needed.

* **estimate part**: ``limit**2 / variance`` along each principal direction of
  the estimate's covariance (information grows about linearly with frames and
  with the square of the range of motion, so 50 % is halfway in data);
* **motion part**: ``(deficit - noise) / (NOISE_SNR_MIN * noise)`` for the
  rotation spread (deficit ``1 - s_k / N``) of the needed directions against
  the pose-noise spread, the quantity the verdict's "excited" test compares.

Each part is capped at 1; the coverage is the smallest part, so it is 1
(100 %) exactly when every threshold of the verdict's coverage tests is met.
The verdict's remaining test is one of consistency, not coverage: a hinge
whose relative rotation is not about a single axis is not identifiable at any
coverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .hinge_from_sums import PoseSumsAxis, _kq
from .segments import (
    AXIS_SD_MAX_DEG,
    NOISE_SNR_MIN,
    SD_REL_MAX,
    SINGULAR_REL,
    PoseSums,
    PoseSumsCentre,
    _motion,
    centre_sd_limit,
)

__all__ = ["Coverage", "joint_coverage"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Coverage:
    """A joint's coverage: fractions (0-1) of what the identifiability verdict needs.

    Attributes
    ----------
    overall : float
        The smallest of the parts below (1: every coverage threshold met).
    motion : float or None
        The relative rotation beyond the pose noise, about the least rotated
        needed direction; None when no window is given (a frozen estimate).
    estimate : float
        The estimate's information against the verdict's limit: ball, the
        centre's least-determined direction (parent and child frames); hinge,
        the smaller of the direction's and the axis point's.
    by_direction : ndarray, shape (3,)
        Ball: the estimate part along each principal direction of the parent
        frame centre covariance, least covered first; hinge: (direction,
        point, 1.0) parts.
    least_covered : ndarray, shape (3,)
        Ball: the unit direction (parent frame) the centre is least
        determined along (the axis the motion has rotated about most: rotate
        about others); hinge: the least-determined perpendicular of the axis
        direction.
    """

    overall: float
    motion: float | None
    estimate: float
    by_direction: FloatArray
    least_covered: FloatArray


def _fraction(limit_sq: float, variance: float) -> float:
    if not np.isfinite(variance):
        return 0.0
    if variance <= limit_sq:
        return 1.0
    return float(limit_sq / variance)


def _eig(cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    if not np.isfinite(cov).all():
        return np.full(3, np.inf), np.eye(3)
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    return np.maximum(lam, 0.0), V


def _motion_fraction(deficit: float, noise: float) -> float:
    if deficit <= SINGULAR_REL:
        return 0.0
    if noise <= 0.0:
        return 1.0
    return float(np.clip((deficit - noise) / (NOISE_SNR_MIN * noise), 0.0, 1.0))


def _window_motion(
    kind: str, sums: PoseSums, W_parent_local: ArrayLike, W_child_local: ArrayLike
) -> float:
    Wp = np.asarray(W_parent_local, dtype=np.float64)
    Wc = np.asarray(W_child_local, dtype=np.float64)
    n = float(sums.n)
    mo = _motion(np.asarray(sums.S), n, Wp[:3, :3], _kq(np.asarray(sums.K), Wc[:3, :3]) / n)
    needed = (0, 2) if kind == "ball" else (1,)
    return min(_motion_fraction(float(mo.deficit[k]), float(mo.noise[k])) for k in needed)


def joint_coverage(
    solution: PoseSumsCentre | PoseSumsAxis,
    length_scale: float,
    sums: PoseSums | None = None,
    W_parent_local: ArrayLike | None = None,
    W_child_local: ArrayLike | None = None,
    skin: bool = False,
) -> Coverage:
    """The coverage of a two-segment estimate (see the module docstring).

    Parameters
    ----------
    solution : PoseSumsCentre or PoseSumsAxis
        The estimate (covariances as the verdict saw them, e.g. with the
        serial-correlation factor).
    length_scale : float
        Lower bound of the lever arm, input units (the one the solve used:
        the larger template rms radius).
    sums : PoseSums, optional
        The window's sums; without them (a frozen estimate) the motion part
        is None and not counted.
    W_parent_local, W_child_local : array_like, shape (6, 6), optional
        The mean pose covariances the solve used (with the noise variance),
        rotation in rad, translation in input units; required with ``sums``.
    skin : bool
        Skin markers: a centre's limit is :data:`~jointfit_core.segments.SD_REL_MAX` of the lever
        arm, as the verdict's on skin estimates (rigid: ``CENTRE_SD_REL_MAX``).

    Returns
    -------
    Coverage
    """
    motion = None
    if sums is not None and W_parent_local is not None and W_child_local is not None and sums.n >= 3:
        motion = _window_motion("ball" if isinstance(solution, PoseSumsCentre) else "hinge", sums,
                                W_parent_local, W_child_local)
    if isinstance(solution, PoseSumsCentre):
        lever = max(float(np.linalg.norm(solution.centre_parent)), float(np.linalg.norm(solution.centre_child)),
                    length_scale)
        limit_sq = (centre_sd_limit(skin) * lever) ** 2
        lam_p, V = _eig(solution.cov_parent)
        lam_c, _ = _eig(solution.cov_child)
        by = np.array([_fraction(limit_sq, float(v)) for v in lam_p[::-1]])
        estimate = min(float(by[0]), _fraction(limit_sq, float(lam_c[-1])))
        least = V[:, -1]
    else:
        lever = max(float(np.linalg.norm(solution.point_parent)), float(np.linalg.norm(solution.point_child)),
                    length_scale)
        dir_sq = float(np.radians(AXIS_SD_MAX_DEG)) ** 2
        lam_dp, V = _eig(solution.cov_direction_parent)
        lam_dc, _ = _eig(solution.cov_direction_child)
        d = _fraction(dir_sq, float(max(lam_dp[-1], lam_dc[-1])))
        pt_sq = (SD_REL_MAX * lever) ** 2
        p = _fraction(pt_sq, float(max(_eig(solution.cov_point_parent)[0][-1], _eig(solution.cov_point_child)[0][-1])))
        by = np.array([d, p, 1.0])
        estimate = min(d, p)
        least = V[:, -1]
    overall = estimate if motion is None else min(estimate, motion)
    return Coverage(overall=overall, motion=motion, estimate=estimate, by_direction=by, least_covered=least)
