"""The node's segment outputs: ``~/segments`` (every segment's world pose per marker frame) and the TF tree.

ROS-free apart from the message bytes. :class:`SegmentOutput` gathers, after
a marker frame went through the joints, each joint's segment poses
(:attr:`OnlineJoint.frame_poses <jointfit_core.estimator.OnlineJoint.frame_poses>`),
puts every segment in its one frame (:class:`~jointfit_core.segment_frames.SegmentFrames`)
and encodes them as a ``geometry_msgs/PoseArray``: one pose per segment in
:attr:`SegmentOutput.names` order, the segment frame's origin (its owner
template's marker centroid) and orientation in the world frame; a segment no
joint could pose in this frame has a NaN position and the zero quaternion.
:meth:`SegmentOutput.tree` gives the frame's TF tree (world -> segment,
segment -> joint, frozen joints static; segment -> each joint's own parent
template frame ``<joint>.local_frame_id``, static, so that ``<joint>/centre_local``
can be transformed) for :class:`~jointfit_ros.tf_output.TfOutput`.

Only marker joints of the marker topic take part (not the joints of pose
topics, whose poses their own topics carry, nor chained joints).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from jointfit_core.segment_frames import SegmentFrames, SegmentJoint
from jointfit_core.tf_tree import JointFrame, TfTree, Transform, quaternions_from_matrices, tf_tree

from .raw import pose_array_bytes
from .runner import JointRunner

__all__ = ["SegmentOutput"]

FloatArray = NDArray[np.float64]


class SegmentOutput:
    """The segments of the node's marker joints and their per-frame poses.

    Parameters
    ----------
    runners : sequence of JointRunner
        The node's joints; those of pose topics and chained ones are left out.
    prefix : str
        Put before every TF frame id but the world's (``subject_a/``; empty for a node in ``/``).
    """

    def __init__(self, runners: Sequence[JointRunner], prefix: str = "") -> None:
        self.prefix = prefix
        self.runners = [r for r in runners if r.poses_both_segments]
        labels = self.runners[0].node.segment_labels() if self.runners else {}
        self.frames = SegmentFrames(
            [SegmentJoint(r.cfg.name, r.cfg.parent_markers, r.cfg.child_markers) for r in self.runners], labels
        )
        self._prefixed_names = [prefix + n for n in self.frames.names]
        self._estimates_cache: tuple[list[JointFrame], tuple[Transform, ...]] = ([], ())
        self._estimates_key: tuple[object, ...] = ()

    @property
    def names(self) -> list[str]:
        """Segment names, in the order of the poses."""
        return self.frames.names

    def _templates(self) -> list[tuple[FloatArray | None, FloatArray | None]]:
        return [r.estimator.templates for r in self.runners]

    def poses(self) -> tuple[FloatArray, FloatArray]:
        """This frame's segment poses: ``R (S, 3, 3)``, ``t (S, 3)`` (world, input units; NaN where not posed)."""
        return self.frames.poses([r.estimator.frame_poses for r in self.runners], self._templates())

    def pose_array(self, stamp_ns: int, frame_id: str, R: FloatArray, t: FloatArray) -> bytes:
        """CDR bytes of ``~/segments`` for poses ``R``, ``t``."""
        posed = np.isfinite(R).all(axis=(1, 2))
        q = np.zeros((len(self.names), 4))
        if posed.any():
            q[posed] = quaternions_from_matrices(R[posed])
        return pose_array_bytes(stamp_ns, frame_id, t, orientations=q)

    def _estimates(self) -> tuple[list[JointFrame], tuple[Transform, ...]]:
        """The tree's parts that change only with an estimate, a freeze or a template, prefixed: the
        identifiable joints in their segments' frames, and ``segment -> <joint>.local_frame_id`` (each joint's
        own parent template frame, the frame of ``<joint>/centre_local``, in its segment's; identity for the
        owner). Rebuilt only when one of those changes."""
        est = [r.estimator for r in self.runners]
        sols = [e.solution if e.solution is not None and e.solution.identifiable else None for e in est]
        frozen = [e.frozen for e in est]
        key = (*(id(s) for s in sols), *frozen, *(id(tp) for e in est for tp in e.templates))
        if key != self._estimates_key:
            p = self.prefix
            templates = self._templates()
            joints = [
                dataclasses.replace(j, name=p + j.name, parent=p + j.parent)
                for j in self.frames.joint_frames(sols, templates, frozen)
            ]
            local: list[Transform] = []
            for i, r in enumerate(self.runners):
                al = self.frames.alignment(i, 0, templates)
                if al is not None:
                    segment = p + self.names[self.frames.segment_of(i, 0)]
                    local.append(Transform(segment, p + r.cfg.local_frame_id, al[1].copy(), quaternions_from_matrices(al[0])))
            self._estimates_cache = (joints, tuple(local))
            self._estimates_key = key
        return self._estimates_cache

    def tree(self, R: FloatArray, t: FloatArray, world_frame: str) -> TfTree:
        """The frame's TF tree: ``world_frame -> segment`` for the posed segments, ``segment -> joint`` (static
        when frozen) and ``segment -> <joint>.local_frame_id`` (static); every frame id but the world's after
        :attr:`prefix` (the node's namespace: two subjects' trees stay apart)."""
        joints, local = self._estimates()
        tree = tf_tree(world_frame, self._prefixed_names, R, t, joints)
        return TfTree(dynamic=tree.dynamic, static=tree.static + local)
