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

__all__ = ["pelvis_frame", "to_frame"]

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
