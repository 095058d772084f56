"""Joint estimates in anatomical terms: a hip centre in the ISB pelvis frame, a knee axis against the epicondyles.

Pure numpy. Landmarks are single points in the frame the estimate is given
in (e.g. the parent segment's template frame); the results are in that
frame's length unit unless a name says ``mm`` (then ``mm_per_unit`` converts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .frames import isb_pelvis_frame

__all__ = [
    "HIP_REGRESSIONS",
    "HipAnatomy",
    "KneeAxisAnatomy",
    "hip_regression",
    "hip_in_pelvis",
    "axis_against_epicondyles",
]

FloatArray = NDArray[np.float64]

#: Published hip-centre regressions, in the ISB pelvis axes with origin at the mid-ASIS (x anterior, y
#: superior, z lateral: right for a right hip), as (coefficient of the inter-ASIS width W, coefficient of the
#: pelvis depth D, offset in mm) per axis: ``c = a_W * W + a_D * D + b``.
HIP_REGRESSIONS: dict[str, tuple[tuple[float, float, float], ...]] = {
    # Bell, Pedersen & Brand (1990), J Biomech 23(6):617-621: 19 % posterior, 30 % inferior, 36 % lateral of W.
    "bell_1990": ((-0.19, 0.0, 0.0), (-0.30, 0.0, 0.0), (0.36, 0.0, 0.0)),
    # Harrington et al. (2007), J Biomech 40(3):595-602, eqs. with D = mid-ASIS to mid-PSIS:
    # x = -0.24 D - 9.9 mm, y = -0.30 W - 10.9 mm, z = 0.33 W + 7.3 mm.
    "harrington_2007": ((0.0, -0.24, -9.9), (-0.30, 0.0, -10.9), (0.33, 0.0, 7.3)),
}


def hip_regression(name: str, width: float, depth: float, side: str, mm_per_unit: float = 1.0) -> FloatArray:
    """A regression's hip centre, ISB pelvis axes, origin mid-ASIS, in the input unit.

    Parameters
    ----------
    name : {"bell_1990", "harrington_2007"}
        See :data:`HIP_REGRESSIONS`.
    width : float
        Inter-ASIS distance W (input unit).
    depth : float
        Distance between the mid-ASIS and the mid-PSIS, D (input unit).
    side : {"right", "left"}
        The hip (z is lateral: positive for the right hip, negative for the left).
    mm_per_unit : float
        Millimetres per input unit (1 for mm, 1000 for m), for the offsets in mm.

    Returns
    -------
    ndarray, shape (3,)
    """
    if name not in HIP_REGRESSIONS:
        raise InputError(f"name: expected one of {sorted(HIP_REGRESSIONS)}, got {name!r}")
    if side not in ("right", "left"):
        raise InputError(f"side: expected 'right' or 'left', got {side!r}")
    coef = np.array(HIP_REGRESSIONS[name])
    out: FloatArray = coef[:, 0] * width + coef[:, 1] * depth + coef[:, 2] / mm_per_unit
    if side == "left":
        out[2] = -out[2]
    return out


@dataclass(frozen=True)
class HipAnatomy:
    """A hip centre in the ISB pelvis frame (origin mid-ASIS) next to the regressions.

    Attributes
    ----------
    side : str
        ``"right"`` or ``"left"``: the side of the mid-ASIS the child segment lies on.
    centre : ndarray, shape (3,)
        The estimate: x anterior, y superior, z right (input unit).
    cov : ndarray, shape (3, 3)
        Its covariance in those axes (input unit squared).
    width, depth : float
        Inter-ASIS width W and mid-ASIS to mid-PSIS depth D (input unit).
    percent_width : ndarray, shape (3,)
        ``100 * centre / W`` (z: lateral, positive away from the midline), the form of Bell et al.
    regressions : dict of str to ndarray, shape (3,)
        :func:`hip_regression` of each of :data:`HIP_REGRESSIONS` (same axes, unit).
    """

    side: str
    centre: FloatArray
    cov: FloatArray
    width: float
    depth: float
    percent_width: FloatArray
    regressions: dict[str, FloatArray]

    def distance_to(self, name: str) -> float:
        """Distance between the estimate and a regression's centre (input unit)."""
        return float(np.linalg.norm(self.centre - self.regressions[name]))


def _point(name: str, value: ArrayLike) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise InputError(f"{name}: expected 3 finite coordinates, got {np.array2string(arr, precision=4)}")
    return arr


def hip_in_pelvis(
    centre: ArrayLike,
    cov: ArrayLike,
    rasis: ArrayLike,
    lasis: ArrayLike,
    rpsis: ArrayLike,
    lpsis: ArrayLike,
    thigh_point: ArrayLike,
    mm_per_unit: float = 1.0,
) -> HipAnatomy:
    """Express a hip centre in the ISB pelvis frame, as % of the pelvis width, and beside the regressions.

    Parameters
    ----------
    centre : array_like, shape (3,)
        The hip centre in some frame (e.g. the pelvis template frame), input unit.
    cov : array_like, shape (3, 3)
        Its covariance in that frame.
    rasis, lasis, rpsis, lpsis : array_like, shape (3,)
        The iliac spines in the same frame.
    thigh_point : array_like, shape (3,)
        Any point of the thigh (e.g. its markers' mean) in the same frame: its side of the mid-ASIS says
        which hip this is.
    mm_per_unit : float
        Millimetres per input unit (for the regressions' offsets in mm).

    Returns
    -------
    HipAnatomy

    Raises
    ------
    InputError
        Non-finite or coincident landmarks.
    """
    pts = [_point(n, v) for n, v in (("rasis", rasis), ("lasis", lasis), ("rpsis", rpsis), ("lpsis", lpsis))]
    c = _point("centre", centre)
    cv = np.asarray(cov, dtype=np.float64).reshape(3, 3)
    width = float(np.linalg.norm(pts[0] - pts[1]))
    depth = float(np.linalg.norm(0.5 * (pts[0] + pts[1]) - 0.5 * (pts[2] + pts[3])))
    if not (width > 0.0 and depth > 0.0):
        raise InputError(f"the iliac spines coincide (width {width:g}, depth {depth:g}): no pelvis frame")
    R, origin = isb_pelvis_frame(*(p[None] for p in pts))
    R0 = R[0]
    c_isb = R0.T @ (c - origin[0])
    side_z = float(R0[:, 2] @ (_point("thigh_point", thigh_point) - origin[0]))
    side = "right" if side_z >= 0.0 else "left"
    lateral = np.array([1.0, 1.0, 1.0 if side == "right" else -1.0])
    return HipAnatomy(
        side=side,
        centre=c_isb,
        cov=R0.T @ cv @ R0,
        width=width,
        depth=depth,
        percent_width=100.0 * lateral * c_isb / width,
        regressions={n: hip_regression(n, width, depth, side, mm_per_unit) for n in HIP_REGRESSIONS},
    )


@dataclass(frozen=True)
class KneeAxisAnatomy:
    """A hinge axis against the line through the epicondyles.

    Attributes
    ----------
    angle_deg : float
        Angle between the axis and the epicondyle line, 0-90 deg (the sign of either is not compared).
    angle_sd_deg : float
        The axis direction's largest sd (deg), the uncertainty of that angle.
    distance : float
        Distance of the epicondyles' midpoint from the axis line (input unit).
    epicondyle_width : float
        Distance between the epicondyles (input unit).
    """

    angle_deg: float
    angle_sd_deg: float
    distance: float
    epicondyle_width: float


def axis_against_epicondyles(
    point: ArrayLike, direction: ArrayLike, cov_direction: ArrayLike, lateral: ArrayLike, medial: ArrayLike
) -> KneeAxisAnatomy:
    """Compare a hinge axis with the epicondyle line (same frame, e.g. the thigh template frame).

    Parameters
    ----------
    point : array_like, shape (3,)
        A point of the axis.
    direction : array_like, shape (3,)
        Its direction (normalised here).
    cov_direction : array_like, shape (3, 3)
        Covariance of the direction (rad^2).
    lateral, medial : array_like, shape (3,)
        The epicondyles.

    Returns
    -------
    KneeAxisAnatomy
    """
    q, a = _point("point", point), _point("direction", direction)
    le, me = _point("lateral", lateral), _point("medial", medial)
    if not np.linalg.norm(a) > 0.0:
        raise InputError("direction: expected a non-zero vector")
    a = a / np.linalg.norm(a)
    line = le - me
    width = float(np.linalg.norm(line))
    if not width > 0.0:
        raise InputError("the epicondyles coincide: no epicondyle line")
    cos = abs(float(a @ line)) / width
    mid = 0.5 * (le + me)
    rel = mid - q
    radial = rel - (rel @ a) * a
    w = np.linalg.eigvalsh(np.asarray(cov_direction, dtype=np.float64).reshape(3, 3))[-1]
    return KneeAxisAnatomy(
        angle_deg=math.degrees(math.acos(min(cos, 1.0))),
        angle_sd_deg=math.degrees(math.sqrt(max(float(w), 0.0))),
        distance=float(np.linalg.norm(radial)),
        epicondyle_width=width,
    )
