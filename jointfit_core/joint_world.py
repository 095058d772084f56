"""A joint's per-frame output in the world: its latest estimate carried by the frame's parent pose.

:class:`WorldOutput` turns an estimate in the parent's template frame
(:class:`~jointfit_core.segments.PoseSumsCentre`,
:class:`~jointfit_core.hinge_from_sums.PoseSumsAxis`) and one frame's segment
poses into a :class:`JointOutput`: the joint's world position (and axis), its
covariance with this frame's parent pose noise, the residual between the
parent- and the child-carried joint, and the relative rotation for the joint
angles. The parts that depend only on the estimate and the parent's visible
markers are cached per visible set until the estimate changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .hinge_from_sums import PoseSumsAxis
from .pose import lever_jacobian, skew
from .segment_tracker import VisibleSet
from .segments import PoseSumsCentre

__all__ = ["JointOutput", "WorldOutput"]

FloatArray = NDArray[np.float64]
_Cached = tuple[FloatArray, FloatArray, FloatArray, FloatArray | None, FloatArray]


@dataclass(frozen=True, eq=False)
class JointOutput:
    """The joint in the world for one frame, carried by the parent's pose.

    Attributes
    ----------
    kind : str
        "ball" or "hinge".
    position : ndarray, shape (3,)
        Ball: the joint centre; hinge: the axis point nearest the parent
        template centroid. World frame, input units.
    cov : ndarray, shape (3, 3)
        Its covariance: the estimate's (parent frame, rotated) plus this
        frame's parent pose noise at that point.
    direction : ndarray, shape (3,) or None
        Hinge: unit axis direction, world frame (sign as the estimate's).
    cov_direction : ndarray, shape (3, 3) or None
        Hinge: its covariance (rank 2).
    residual : float
        Distance between the parent- and the child-carried joint (hinge: of
        the parent's axis point from the child's axis line); NaN when the
        child could not be posed in this frame.
    rotation : ndarray, shape (3, 3) or None
        This frame's relative rotation, child template frame to parent
        template frame (``R_p^T R_c``; the joint angles' input,
        :mod:`jointfit_core.joint_angles`); None when the child was not posed.
    rotation_cov : ndarray, shape (3, 3) or None
        Its covariance (rad^2) from this frame's two pose fits, as a left
        perturbation in the parent template frame
        (:func:`~jointfit_core.joint_angles.relative_rotation_cov`).
    """

    kind: str
    position: FloatArray
    cov: FloatArray
    direction: FloatArray | None
    cov_direction: FloatArray | None
    residual: float
    rotation: FloatArray | None = None
    rotation_cov: FloatArray | None = None


class WorldOutput:
    """Per-frame world outputs of one joint (``kind`` "ball" or "hinge"), with a cache per parent visible set.

    Call :meth:`clear` whenever the estimate or its noise levels change.
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._cache: dict[bytes, _Cached] = {}

    def clear(self) -> None:
        """Forget the cached parts (a new estimate)."""
        self._cache = {}

    def output(
        self,
        sol: PoseSumsCentre | PoseSumsAxis | None,
        sigma: tuple[float, float],
        Rp: FloatArray,
        dp: FloatArray,
        vp: VisibleSet,
        child_pose: tuple[FloatArray, FloatArray, VisibleSet] | None,
        motion: FloatArray | None = None,
    ) -> JointOutput:
        """The joint in the world for one frame.

        Parameters
        ----------
        sol : PoseSumsCentre or PoseSumsAxis
            The estimate (template frames, input units); must not be None.
        sigma : (float, float)
            The parent's and the child's marker noise sd (input units) the estimate used.
        Rp, dp : ndarray, shapes (3, 3), (3,)
            This frame's parent pose (template frame to world).
        vp : VisibleSet
            The parent's visible markers in this frame (their unit pose covariance ``W_unit``).
        child_pose : (ndarray (3, 3), ndarray (3,), VisibleSet) or None
            The child's pose and visible set; None when the child was not posed.
        motion : ndarray, shape (2, 6), optional
            Skin markers: per frame, the variance of each cluster's motion on its bone, ``(omega, u)``
            per component, parent then child (:attr:`~jointfit_core.joint_estimate.JointEstimate.cluster_motion`);
            None: rigid clusters (their pose is their bone's).

        Returns
        -------
        JointOutput
            See the class; the covariance adds this frame's parent pose noise at the joint,
            ``R_p (cov_parent + s_p^2 J W_p J^T + J M_p J^T) R_p^T`` with ``J = [-[c_p]x, I]`` (Stoddart et
            al., eq. 4 for ``W``) and ``M_p = diag(motion[0])`` the parent cluster's motion on its bone:
            the estimate is the joint in the bone's frame, a frame's cluster pose is off the bone's by
            that motion, which its marker residuals do not show (a rigid cluster shift leaves none).
            The direction and the relative rotation add the clusters' turns alike. ``cov_parent``
            carries the estimate's serial-correlation factor; the pose-noise terms do not: the
            correlation makes the frames' errors alike, it does not make one frame's error larger.
        """
        assert sol is not None
        key = vp.index.tobytes()
        cached = self._cache.get(key)
        if cached is None:
            s2 = sigma[0] ** 2
            if isinstance(sol, PoseSumsCentre):
                local, local_cov, other = sol.centre_parent, sol.cov_parent, sol.centre_child
            else:
                local, local_cov, other = sol.point_parent, sol.cov_point_parent, sol.point_child
            J = lever_jacobian(local)
            W = s2 * vp.W_unit
            if motion is not None:
                W = W + np.diag(motion[0])
            cov_dir = None
            if isinstance(sol, PoseSumsAxis):
                Nx = skew(sol.direction_parent)
                cov_dir = sol.cov_direction_parent + Nx @ W[:3, :3] @ Nx.T
            # (the parent's part of the rotation's covariance, below, is this visible set's too)
            cached = (local, local_cov + J @ W @ J.T, other, cov_dir, W[:3, :3])
            self._cache[key] = cached
        local, cov_local, other, cov_dir_local, rot_cov_parent = cached
        position = Rp @ local + dp
        cov = Rp @ cov_local @ Rp.T
        residual = float("nan")
        direction = cov_dir = None
        Q = Q_cov = None
        if cov_dir_local is not None:
            assert isinstance(sol, PoseSumsAxis)
            direction = Rp @ sol.direction_parent
            cov_dir = Rp @ cov_dir_local @ Rp.T
        if child_pose is not None:
            Rc, dc, vc = child_pose
            diff = position - (Rc @ other + dc)
            if direction is not None:
                assert isinstance(sol, PoseSumsAxis)
                axis_c = Rc @ sol.direction_child
                diff = diff - axis_c * (diff @ axis_c)
            residual = math.sqrt(float(diff @ diff))  # (the same correctly rounded square root as np.sqrt)
            Q = Rp.T @ Rc
            # the poses' rotation errors (local frames) as one left perturbation of Q (joint_angles.relative_rotation_cov)
            Wc = sigma[1] ** 2 * vc.W_unit[:3, :3]
            if motion is not None:
                Wc = Wc + np.diag(motion[1, :3])
            Q_cov = rot_cov_parent + Q @ Wc @ Q.T
        return JointOutput(self.kind, position, cov, direction, cov_dir, residual, Q, Q_cov)
