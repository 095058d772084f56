"""The geometry of a joint's kept marker frames, for its anatomical results and range of motion (ROS-free).

:class:`SegmentGeometry` holds it for ``jointfit fit`` (every kept frame,
:func:`jointfit_ros.report.segment_geometry`) and for the live node (a
sample of recent frames, :class:`jointfit_ros.live_geometry.LiveGeometry`);
:mod:`jointfit_ros.anatomy_report` reads it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["SegmentGeometry", "landmark_stat"]

FloatArray = NDArray[np.float64]


def landmark_stat(local: FloatArray) -> tuple[FloatArray, float, int] | None:
    """A landmark marker's place in the parent frame from its positions there (N, 3) (NaN rows left out).

    Returns the median (3,), the rms distance of the frames from it (input
    units: how rigidly the marker moves with the parent) and the number of
    frames; None when no row is finite.
    """
    local = local[np.isfinite(local).all(axis=1)]
    if not local.shape[0]:
        return None
    med = np.median(local, axis=0)
    return med, float(np.sqrt(np.mean(np.sum((local - med) ** 2, axis=1)))), int(local.shape[0])


class SegmentGeometry:
    """Per-frame poses of both segments from the kept frames and the final templates.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Frame times, s from the first frame.
    residual_parent, residual_child : ndarray, shape (N, Pp) and (N, Pc)
        Distance of each marker from its posed template point, input units
        (NaN where missing or not posed).
    child_in_parent : ndarray, shape (N, Pc, 3)
        Child markers in the parent segment frame, input units.
    joint_residual : ndarray, shape (N,) or None
        Per frame, the distance between the joint carried by the parent and
        by the child with the final estimate (:attr:`JointOutput.residual
        <jointfit_core.estimator.JointOutput.residual>`: ball, between the
        two centres; hinge, of the parent's axis point from the child's axis
        line), input units; NaN where a segment is not posed; None without a
        final estimate.
    R_parent_child : ndarray, shape (N, 3, 3) or None
        Per frame, the child's orientation in the parent frame (NaN where a segment is not posed).
    landmarks_parent : dict of str to (ndarray (3,), float, int)
        Each ``<joint>.anatomical.*`` marker in the parent frame: the median over the posed frames where it is
        visible, the rms distance of those frames from it (input units: how rigidly it moves with the parent)
        and their number.
    """

    def __init__(
        self,
        t: FloatArray,
        rp: FloatArray,
        rc: FloatArray,
        cip: FloatArray,
        joint_residual: FloatArray | None = None,
        R_parent_child: FloatArray | None = None,
        landmarks_parent: dict[str, tuple[FloatArray, float, int]] | None = None,
    ) -> None:
        self.t = t
        self.residual_parent = rp
        self.residual_child = rc
        self.child_in_parent = cip
        self.joint_residual = joint_residual
        self.R_parent_child = R_parent_child
        self.landmarks_parent = landmarks_parent or {}
