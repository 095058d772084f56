"""Anatomical reference frames built from landmark markers.

These give joint estimates a meaning a clinician recognises (e.g. a hip
centre in a pelvis frame). Each function returns, per frame, the rotation
``R_world_frame`` (columns are the frame's axes in world coordinates) and the
origin, so that ``p_frame = R_world_frame^T (p_world - origin)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

__all__ = ["pelvis_frame", "to_frame", "isb_pelvis_frame", "isb_femur_frame", "isb_tibia_frame", "vector_to_frame"]

FloatArray = NDArray[np.float64]


def _points(name: str, value: ArrayLike) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected shape (N, 3), got {arr.shape}")
    return arr


def pelvis_frame(rasis: ArrayLike, lasis: ArrayLike, rpsis: ArrayLike, lpsis: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Pelvis frame from the anterior and posterior iliac spines.

    Parameters
    ----------
    rasis, lasis, rpsis, lpsis : array_like, shape (N, 3)
        Right/left anterior and posterior superior iliac spine markers.

    Returns
    -------
    R_world_pelvis : ndarray, shape (N, 3, 3)
        Columns: x anterior, y toward the left ASIS, z up (x cross y).
    origin : ndarray, shape (N, 3)
        Midpoint of the ASISs. NaN where a landmark is missing.

    Notes
    -----
    y is the unit vector from RASIS to LASIS; x is the component of
    (mid-ASIS - mid-PSIS) orthogonal to y; z = x cross y. This is the frame
    in which the hip-centre literature values of the fixtures are quoted.
    """
    ra, la, rp, lp = (_points(n, v) for n, v in (("rasis", rasis), ("lasis", lasis), ("rpsis", rpsis), ("lpsis", lpsis)))
    origin = 0.5 * (ra + la)
    y = la - ra
    y = y / np.linalg.norm(y, axis=1, keepdims=True)
    fwd = origin - 0.5 * (rp + lp)
    x = fwd - np.einsum("ni,ni->n", fwd, y)[:, None] * y
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=2), origin


def to_frame(points_world: ArrayLike, R_world_frame: ArrayLike, origin: ArrayLike) -> FloatArray:
    """Express world points, shape (N, 3), in a per-frame reference frame."""
    p = _points("points_world", points_world)
    rot = np.asarray(R_world_frame, dtype=np.float64)
    return np.einsum("nji,nj->ni", rot, p - np.asarray(origin, dtype=np.float64))


def _unit(v: FloatArray) -> FloatArray:
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return out


def _side_sign(side: str) -> float:
    if side not in ("right", "left"):
        raise InputError(f"side: expected 'right' or 'left', got {side!r}")
    return 1.0 if side == "right" else -1.0


def isb_pelvis_frame(
    rasis: ArrayLike, lasis: ArrayLike, rpsis: ArrayLike, lpsis: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """The ISB pelvis axes (Wu et al. 2002) from the iliac spines, origin at the mid-ASIS.

    Parameters
    ----------
    rasis, lasis, rpsis, lpsis : array_like, shape (N, 3)
        Right/left anterior and posterior superior iliac spines, any length unit.

    Returns
    -------
    R_world_pelvis : ndarray, shape (N, 3, 3)
        Columns: X anterior, Y superior (cranial), Z toward the right ASIS.
    origin : ndarray, shape (N, 3)
        Midpoint of the ASISs (NaN where a landmark is missing).

    Notes
    -----
    Wu et al. (2002, J Biomech 35:543, section 2.2): Z is parallel to the
    line from LASIS to RASIS, pointing right; X lies in the plane of the two
    ASISs and the mid-PSIS, orthogonal to Z, pointing anteriorly; Y = Z x X
    points cranially. The ISB origin is the hip centre itself; here the
    origin is the mid-ASIS, as in the hip-centre regressions that are quoted
    in these axes (Bell et al. 1990; Harrington et al. 2007).
    """
    ra, la, rp, lp = (_points(n, v) for n, v in (("rasis", rasis), ("lasis", lasis), ("rpsis", rpsis), ("lpsis", lpsis)))
    origin = 0.5 * (ra + la)
    z = _unit(ra - la)
    fwd = origin - 0.5 * (rp + lp)
    x = _unit(fwd - np.einsum("ni,ni->n", fwd, z)[:, None] * z)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2), origin


def isb_femur_frame(
    hip_centre: ArrayLike, lateral_epicondyle: ArrayLike, medial_epicondyle: ArrayLike, side: str
) -> tuple[FloatArray, FloatArray]:
    """The ISB femur frame (Wu et al. 2002) from the hip centre and the femoral epicondyles.

    Parameters
    ----------
    hip_centre, lateral_epicondyle, medial_epicondyle : array_like, shape (N, 3)
        Any length unit.
    side : {"right", "left"}
        Which femur (the lateral epicondyle lies on this side).

    Returns
    -------
    R_world_femur : ndarray, shape (N, 3, 3)
        Columns: X anterior, Y from the mid-epicondyles to the hip centre
        (cranial), Z to the right.
    origin : ndarray, shape (N, 3)
        The hip centre.

    Notes
    -----
    Wu et al. (2002, section 2.4.2): Y joins the midpoint of the epicondyles
    and the hip centre; Z is perpendicular to Y in the plane of the hip
    centre and the two epicondyles, pointing right; X = Y x Z.
    """
    h = _points("hip_centre", hip_centre)
    le = _points("lateral_epicondyle", lateral_epicondyle)
    me = _points("medial_epicondyle", medial_epicondyle)
    right = _side_sign(side) * (le - me)
    y = _unit(h - 0.5 * (le + me))
    z = _unit(right - np.einsum("ni,ni->n", right, y)[:, None] * y)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=2), h


def isb_tibia_frame(
    lateral_condyle: ArrayLike,
    medial_condyle: ArrayLike,
    lateral_malleolus: ArrayLike,
    medial_malleolus: ArrayLike,
    side: str,
) -> tuple[FloatArray, FloatArray]:
    """The ISB tibia/fibula frame (Wu et al. 2002) from the condyles (or epicondyles) and the malleoli.

    Parameters
    ----------
    lateral_condyle, medial_condyle : array_like, shape (N, 3)
        Most lateral/medial points of the tibial condyles; the femoral
        epicondyles are the usual marker stand-ins.
    lateral_malleolus, medial_malleolus : array_like, shape (N, 3)
    side : {"right", "left"}
        Which leg.

    Returns
    -------
    R_world_tibia : ndarray, shape (N, 3, 3)
        Columns: X anterior, Y cranial, Z to the right.
    origin : ndarray, shape (N, 3)
        The mid-malleoli (IM).

    Notes
    -----
    Wu et al. (2002, section 2.4.3): Z joins the malleoli, pointing right; X
    is perpendicular to the torsional plane (IM and the two condyles),
    pointing anteriorly; Y is perpendicular to X and Z (cranial); X is then
    made orthogonal to Y and Z.
    """
    lc = _points("lateral_condyle", lateral_condyle)
    mc = _points("medial_condyle", medial_condyle)
    lm = _points("lateral_malleolus", lateral_malleolus)
    mm = _points("medial_malleolus", medial_malleolus)
    s = _side_sign(side)
    origin = 0.5 * (lm + mm)
    z = _unit(s * (lm - mm))
    right_c, left_c = (lc, mc) if s > 0 else (mc, lc)
    normal = np.cross(left_c - origin, right_c - origin)  # anterior for either side
    y = _unit(np.cross(z, normal))
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=2), origin


def vector_to_frame(vectors_world: ArrayLike, R_world_frame: ArrayLike) -> FloatArray:
    """Express world directions (no origin shift), shape (N, 3), in a per-frame reference frame."""
    v = _points("vectors_world", vectors_world)
    return np.einsum("nji,nj->ni", np.asarray(R_world_frame, dtype=np.float64), v)
