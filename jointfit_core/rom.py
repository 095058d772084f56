"""Range of motion of a joint from its per-frame relative rotations.

Pure numpy/scipy. The relative rotation of a frame is ``R_parent^T R_child``
(the child's orientation in the parent segment frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .errors import InputError

__all__ = ["RangeOfMotion", "range_of_motion", "twist_angles"]

FloatArray = NDArray[np.float64]

#: The range is taken between these percentiles of the frames' angles, so that a single frame with a label
#: swap (a rotation of 100+ deg for one sample) does not set it.
RANGE_PERCENTILES = (0.5, 99.5)


@dataclass(frozen=True)
class RangeOfMotion:
    """How far a joint turned.

    Attributes
    ----------
    ranges_deg : ndarray, shape (3,)
        Range (deg, between :data:`RANGE_PERCENTILES`) of the rotation about each principal axis, largest first.
    axes : ndarray, shape (3, 3)
        Rows: the principal axes (parent frame, unit) of the rotations about the mean orientation.
    angles_deg : ndarray, shape (N, 3)
        Per frame, the rotation vector from the mean orientation along each principal axis (deg; NaN where
        the frame has no relative rotation).
    flexion_range_deg : float or None
        Hinge: the range of the rotation about the hinge axis (twist, deg); None without an axis.
    flexion_deg : ndarray, shape (N,) or None
        Hinge: per frame, that rotation from the mean orientation (deg).
    n_frames : int
        Frames with a relative rotation.
    """

    ranges_deg: FloatArray
    axes: FloatArray
    angles_deg: FloatArray
    flexion_range_deg: float | None
    flexion_deg: FloatArray | None
    n_frames: int


def _spread(x: FloatArray) -> float:
    lo, hi = np.percentile(x, RANGE_PERCENTILES)
    return float(hi - lo)


def twist_angles(rotations: Rotation, axis: FloatArray) -> FloatArray:
    """Angle (rad, in (-pi, pi]) of each rotation's twist about a unit ``axis`` (swing-twist decomposition)."""
    q = rotations.as_quat()  # (N, 4), scalar last
    out: FloatArray = 2.0 * np.arctan2(q[:, :3] @ axis, q[:, 3])
    return np.angle(np.exp(1j * out))  # wrapped


def range_of_motion(R_parent_child: ArrayLike, axis: ArrayLike | None = None) -> RangeOfMotion:
    """The range of motion of a joint over a recording.

    Parameters
    ----------
    R_parent_child : array_like, shape (N, 3, 3)
        Per frame, the child's orientation in the parent frame; frames with a NaN are left out.
    axis : array_like, shape (3,), optional
        A hinge's axis in the parent frame: the flexion range is the range of the twist about it.

    Returns
    -------
    RangeOfMotion

    Raises
    ------
    InputError
        Wrong shape or fewer than 2 frames with a rotation.

    Notes
    -----
    The rotations are taken relative to their mean (``scipy.spatial.transform.Rotation.mean``, the chordal
    L2 mean); their rotation vectors are split along their principal directions (eigenvectors of their
    second moments), and each range is the spread of the projections between the 0.5th and 99.5th
    percentiles. For rotations of up to ~90 deg from the mean the rotation vector's components are the
    angles about those axes to within a few percent; the hinge's twist is exact.
    """
    R = np.asarray(R_parent_child, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise InputError(f"R_parent_child: expected shape (N, 3, 3), got {R.shape}")
    ok = np.isfinite(R).all(axis=(1, 2))
    n = int(ok.sum())
    if n < 2:
        raise InputError(f"R_parent_child: expected at least 2 frames with a rotation, got {n}")
    rot = Rotation.from_matrix(R[ok])
    mean = rot.mean()
    from_mean = rot * mean.inv()  # R_i M^T: the turn from the mean orientation, parent frame
    rv = from_mean.as_rotvec()
    _, v = np.linalg.eigh(rv.T @ rv)
    axes = v[:, ::-1].T
    proj = rv @ axes.T
    angles = np.full((R.shape[0], 3), np.nan)
    angles[ok] = np.degrees(proj)
    ranges = np.array([_spread(angles[ok, k]) for k in range(3)])
    flexion_range: float | None = None
    flexion: FloatArray | None = None
    if axis is not None:
        a = np.asarray(axis, dtype=np.float64).reshape(3)
        if not np.linalg.norm(a) > 0.0:
            raise InputError("axis: expected a non-zero direction")
        a = a / np.linalg.norm(a)
        twist = twist_angles(from_mean, a)
        flexion = np.full(R.shape[0], np.nan)
        flexion[ok] = np.degrees(twist)
        flexion_range = _spread(flexion[ok])
    return RangeOfMotion(ranges, axes, angles, flexion_range, flexion, n)

