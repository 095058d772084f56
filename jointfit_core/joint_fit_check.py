"""Whether two segments turn about one joint at all: the joint residual against the pose noise.

Pure numpy. A joint estimated between two segments that are not joined (a
segment between them, the wrong segments named) is still a least-squares
answer, and rigid markers give it a covariance of a millimetre or two. The
joint residual tells: for a joint, the centre (a hinge: the point of its axis)
carried by the two segments' poses differs only by the poses' noise,

    E|e|^2 = tr(J_p W_p J_p^T) + tr(J_c W_c J_c^T),    J = [-[c]x, I],

``W`` the window's mean local pose covariance of each segment (its markers'
noise through the pose fit, Stoddart et al. 1999 eq. 8; on skin the pooled
noise, which holds the clusters' deformation) and ``c`` the point in that
segment's frame (:func:`~jointfit_core.pose.pose_covariance_local`, Notes).
Between segments that are not joined, the residual is the distance the
"centre" travels between them: tens to hundreds of millimetres.

Measured (the lower body, 20 s at 100 Hz, 2 seeds; rms over this expectation):

- joints, rigid markers: 1.03-1.09; skin markers: 0.53-0.97; the real hip 1.04, the real knee 0.46;
- not joints (right thigh to left shank as a hinge, pelvis to right shank or foot, the two feet or
  thighs as balls): rigid 12-36 (24-36 for those the solve called identifiable), skin 4.9-7.7; the
  real wheelchair-racing elbow as a hinge (it pronates too) 13.4.

The verdict applies to rigid markers only (``attachment: rigid``: robots, bone pins, rigid-body pose
inputs): on skin the clusters' motion on their bones adds to the residual, and the soft-tissue prior,
which reads that motion, gives non-joints a covariance of decimetres (measured: 60-940 mm sd).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .pose import lever_jacobian

__all__ = ["NOT_A_JOINT_RATIO", "expected_residual_rms", "not_a_joint_reason"]

FloatArray = NDArray[np.float64]

#: The joint residual's rms over :func:`expected_residual_rms` above which two rigidly marked segments do not
#: turn about one joint of the kind fitted: joints read at most 1.1, identifiable non-joints 24-36 (the module
#: notes); a hip whose skin cluster shifts 10 mm between movement blocks, marked rigid, reads 9 (its consistency
#: check warns, ``test/test_consistency.py``).
NOT_A_JOINT_RATIO = 10.0


def _carried_spread2(W: FloatArray, point: FloatArray) -> float:
    """``tr(J W J^T)``, ``J = [-[p]x, I]``: the mean squared error of a body-fixed point carried by the pose."""
    J = lever_jacobian(point)
    return float(np.trace(J @ W @ J.T))


def expected_residual_rms(W_parent: ArrayLike, W_child: ArrayLike, point_parent: ArrayLike,
                          point_child: ArrayLike) -> float:
    """The rms joint residual that the two segments' pose noise alone gives (input units).

    Parameters
    ----------
    W_parent, W_child : array_like, shape (6, 6)
        Mean local pose covariance of each segment over the window, of ``(omega, u)``
        (:func:`~jointfit_core.pose.pose_covariance_local`), at the noise in use.
    point_parent, point_child : array_like, shape (3,)
        The joint centre (hinge: the axis point) in each segment's local frame (input units).

    Returns
    -------
    float
        ``sqrt(E|e|^2)`` (module notes).
    """
    total = _carried_spread2(np.asarray(W_parent, dtype=np.float64), np.asarray(point_parent, dtype=np.float64))
    total += _carried_spread2(np.asarray(W_child, dtype=np.float64), np.asarray(point_child, dtype=np.float64))
    return float(np.sqrt(max(total, 0.0)))


def not_a_joint_reason(rms: float, expected: float, kind: str) -> str:
    """Why two segments whose joint residual is :data:`NOT_A_JOINT_RATIO` times its expectation are no joint ("" if not)."""
    if not (expected > 0.0 and rms > NOT_A_JOINT_RATIO * expected):
        return ""
    what = "a hinge (one fixed axis)" if kind == "hinge" else "one joint"
    return (
        f"the two segments do not turn about {what} as rigid bodies: the joint carried by their poses differs by "
        f"{rms:.3g} rms, {rms / expected:.0f} times what their markers' noise gives ({expected:.3g}); are they the "
        "segments on either side of this joint, with no segment between them? (markers on skin: attachment: skin; "
        "a configured noise far below the real one reads so too)"
    )
