"""The TF tree of a skeleton as plain transforms: world -> segments -> joint frames (no tf2).

One frame's tree from the segment poses and the joint estimates (issue 16, item 4):

* ``world -> <segment>``: the segment's pose (its template frame in the node), one per
  posed segment, every frame;
* ``<segment> -> <joint>``: the joint's frame in its parent segment. A ball joint's
  frame has its origin at the centre and the parent's axes; a hinge's has its origin
  at the axis point and its z axis along the axis direction (the minimal rotation
  taking z to it, as the node's ``<joint>/axis`` pose). A frozen joint's transform does
  not change, so it is *static* (``/tf_static``, sent once); an estimating joint's is
  dynamic (re-estimated).

The node builds it per marker frame from its segments (:mod:`jointfit_core.segment_frames`,
``jointfit_ros.segment_output``); ``jointfit_ros.tf_output`` turns the transforms into
``geometry_msgs/TransformStamped`` and broadcasts them when ``tf2_ros`` imports.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

__all__ = ["Transform", "JointFrame", "TfTree", "quaternions_from_matrices", "quaternion_z_to", "tf_tree"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Transform:
    """One TF transform: ``child`` coordinates to ``parent`` coordinates, ``x_parent = R x_child + translation``.

    Attributes
    ----------
    parent, child : str
        Frame ids (``header.frame_id`` and ``child_frame_id``).
    translation : ndarray, shape (3,)
        Origin of ``child`` in ``parent`` (input units, m for ROS).
    rotation : ndarray, shape (4,)
        Unit quaternion (x, y, z, w), w >= 0, of ``R``.
    """

    parent: str
    child: str
    translation: FloatArray
    rotation: FloatArray


@dataclass(frozen=True)
class JointFrame:
    """A joint estimate in its parent segment's frame, for :func:`tf_tree`.

    Attributes
    ----------
    name : str
        Joint name: the frame id of its frame.
    parent : str
        Parent segment name: the frame the estimate is expressed in.
    point : array_like, shape (3,)
        Ball: the centre; hinge: the axis point (input units).
    direction : array_like, shape (3,) or None
        Hinge: the axis direction (normalised here); None for a ball.
    frozen : bool
        A frozen estimate: its transform is static.
    """

    name: str
    parent: str
    point: ArrayLike
    direction: ArrayLike | None = None
    frozen: bool = False


@dataclass(frozen=True)
class TfTree:
    """One frame's transforms: ``dynamic`` (``/tf``, every frame) and ``static`` (``/tf_static``, once)."""

    dynamic: tuple[Transform, ...]
    static: tuple[Transform, ...]

    @property
    def all(self) -> tuple[Transform, ...]:
        """Static then dynamic transforms."""
        return self.static + self.dynamic


def _k_of_r() -> tuple[FloatArray, FloatArray]:
    """The linear map (9, 16) and the constant (16,) of ``K = 4 q q^T`` (x, y, z, w) from a rotation matrix."""
    L = np.zeros((3, 3, 4, 4))
    sign = {(0, 0): (1, -1, -1, 1), (1, 1): (-1, 1, -1, 1), (2, 2): (-1, -1, 1, 1)}
    for (i, _), signs in sign.items():
        for k, sg in enumerate(signs):
            L[i, i, k, k] = sg
    for (i, j), (a, b) in {(0, 1): (0, 1), (1, 0): (0, 1), (0, 2): (0, 2), (2, 0): (0, 2), (1, 2): (1, 2), (2, 1): (1, 2)}.items():
        L[i, j, a, b] = L[i, j, b, a] = 1.0  # x y: m01 + m10, x z: m02 + m20, y z: m12 + m21
    for (i, j), (a, sg) in {(2, 1): (0, 1), (1, 2): (0, -1), (0, 2): (1, 1), (2, 0): (1, -1), (1, 0): (2, 1), (0, 1): (2, -1)}.items():
        L[i, j, a, 3] = L[i, j, 3, a] = sg  # w x: m21 - m12, w y: m02 - m20, w z: m10 - m01
    return L.reshape(9, 16), np.eye(4).ravel()


_K_OF_R, _K_ONE = _k_of_r()


def quaternions_from_matrices(R: ArrayLike) -> FloatArray:
    """Unit quaternions (x, y, z, w), w >= 0, of rotation matrices, shape (..., 3, 3) -> (..., 4)."""
    mats = np.asarray(R, dtype=np.float64)
    if mats.shape[-2:] != (3, 3):
        raise InputError(f"R: expected rotation matrices of shape (..., 3, 3), got shape {mats.shape}")
    # K = 4 q q^T, linear in the matrix (Shepperd 1978): the row of its largest diagonal entry is q scaled by
    # its largest component, so it is divided by nothing small
    K = mats.reshape(-1, 9) @ _K_OF_R + _K_ONE  # (n, 16)
    k = np.argmax(K[:, ::5], axis=1)  # the diagonal
    q = K.reshape(-1, 4, 4)[np.arange(K.shape[0]), k]
    q *= (np.where(q[:, 3] < 0.0, -1.0, 1.0) / np.sqrt(np.sum(q * q, axis=1)))[:, None]
    out: FloatArray = q.reshape(*mats.shape[:-2], 4)
    return out


def quaternion_z_to(directions: ArrayLike) -> FloatArray:
    """The minimal rotations taking +z to unit ``directions``, shape (..., 3) -> quaternions (..., 4), (x, y, z, w).

    ``q ∝ (z × d, 1 + z·d)``; for d = -z, where the axis is undefined, the half turn about x.
    (The same rotation as ``jointfit_ros.raw.quaternion_z_to_direction``, vectorised.)
    """
    d = np.asarray(directions, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    if d.shape[-1:] != (3,) or not (np.isfinite(norm) & (norm > 0.0)).all():
        raise InputError(f"directions: expected finite non-zero vectors of shape (..., 3), got shape {d.shape}")
    d = d / norm
    dz = d[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(dz >= 0.0, 1.0 + dz, (d[..., 0] ** 2 + d[..., 1] ** 2) / (1.0 - dz))
    q = np.stack([-d[..., 1], d[..., 0], np.zeros_like(dz), w], axis=-1)
    qn = np.linalg.norm(q, axis=-1, keepdims=True)
    flip = qn[..., 0] < 1e-150
    q = np.where(flip[..., None], np.array([1.0, 0.0, 0.0, 0.0]), q / np.where(flip[..., None], 1.0, qn))
    out: FloatArray = q
    return out


def tf_tree(
    world_frame: str,
    segments: Sequence[str],
    R_world_segment: ArrayLike,
    t_world_segment: ArrayLike,
    joints: Sequence[JointFrame] = (),
) -> TfTree:
    """One frame's TF tree of a skeleton.

    Parameters
    ----------
    world_frame : str
        Frame id of the world (the mocap frame).
    segments : sequence of str, length S
        Segment frame ids.
    R_world_segment : array_like, shape (S, 3, 3)
        Each segment's rotation (segment frame to world) in this frame; a segment that
        is not posed in it (NaN) gets no ``world -> segment`` transform.
    t_world_segment : array_like, shape (S, 3)
        Each segment frame's origin in the world (input units).
    joints : sequence of JointFrame
        Joint estimates, each in a segment of ``segments``.

    Returns
    -------
    TfTree
        ``dynamic``: ``world -> segment`` for the posed segments, in ``segments`` order,
        then ``segment -> joint`` of the joints that are not frozen; ``static``: those of
        the frozen joints. Joints in ``joints`` order.

    Raises
    ------
    InputError
        Shapes that do not match, non-rotation matrices, a joint in an unknown segment,
        a non-finite joint point or direction.
    """
    names = list(segments)
    R = np.asarray(R_world_segment, dtype=np.float64)
    t = np.asarray(t_world_segment, dtype=np.float64)
    if R.shape != (len(names), 3, 3) or t.shape != (len(names), 3):
        raise InputError(
            f"segment poses: expected R (S, 3, 3) and t (S, 3) for S = {len(names)} segments, "
            f"got shapes {R.shape} and {t.shape}"
        )
    posed = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    if posed.any():
        orth = np.einsum("sji,sjk->sik", R[posed], R[posed]) - np.eye(3)
        if np.abs(orth).max() > 1e-6 or (np.linalg.det(R[posed]) < 0.0).any():
            raise InputError("R_world_segment: expected proper rotation matrices (orthonormal, det +1)")
    q = quaternions_from_matrices(R[posed]) if posed.any() else np.empty((0, 4))
    dynamic = [
        Transform(world_frame, names[k], t[k].copy(), qk) for k, qk in zip(np.flatnonzero(posed).tolist(), q, strict=True)
    ]
    static: list[Transform] = []
    for j in joints:
        tf = _joint_transform(j, names)
        (static if j.frozen else dynamic).append(tf)
    return TfTree(dynamic=tuple(dynamic), static=tuple(static))


def _joint_transform(joint: JointFrame, segments: Sequence[str]) -> Transform:
    if joint.parent not in segments:
        raise InputError(f"{joint.name}: parent segment {joint.parent!r} is not one of {list(segments)}")
    point = np.asarray(joint.point, dtype=np.float64)
    if point.shape != (3,) or not np.isfinite(point).all():
        raise InputError(f"{joint.name}: expected a finite point of shape (3,), got {point.tolist()}")
    if joint.direction is None:
        rotation = np.array([0.0, 0.0, 0.0, 1.0])
    else:
        direction = np.asarray(joint.direction, dtype=np.float64)
        if direction.shape != (3,):
            raise InputError(f"{joint.name}: expected a direction of shape (3,), got shape {direction.shape}")
        rotation = quaternion_z_to(direction)
    return Transform(joint.parent, joint.name, point.copy(), rotation)
