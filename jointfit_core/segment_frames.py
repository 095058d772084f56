"""A skeleton's segments, each in one frame, from the joints' own templates: poses per frame and joints in them.

Each :class:`~jointfit_core.estimator.OnlineJoint` builds its own templates,
so a thigh that is the hip's child and the knee's parent has two template
frames. :class:`SegmentFrames` gives every segment (a marker list; joints
whose lists are equal share it) one frame, the template frame of its
*owner*: the joint that has it as the child, or for a root the first joint
that has it as the parent (the links of :mod:`jointfit_core.urdf` use the
same rule). The other joints' templates of the same markers are aligned to
the owner's (Kabsch, recomputed when a template is replaced), so that

* :meth:`SegmentFrames.poses` gives each segment's world pose in a frame
  from whichever joint posed it (the owner's when it did), and
* :meth:`SegmentFrames.joint_frames` gives every joint's estimate in its
  parent segment's frame (a chain's hip centre and knee axis in the one
  thigh frame), for the TF tree of :func:`jointfit_core.tf_tree.tf_tree`.

Pure numpy; the node publishes the result (``~/segments``, TF).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .hinge_from_sums import PoseSumsAxis
from .segments import PoseSumsCentre
from .tf_tree import JointFrame
from .urdf import kabsch, segment_names

__all__ = ["SegmentJoint", "SegmentFrames"]

FloatArray = NDArray[np.float64]
Templates = tuple[FloatArray | None, FloatArray | None]
FramePoses = tuple[FloatArray, FloatArray, tuple[bool, bool]] | None


@dataclass(frozen=True)
class SegmentJoint:
    """What :class:`SegmentFrames` needs of a joint: its name and its two segments' marker lists."""

    name: str
    parent_markers: tuple[str, ...]
    child_markers: tuple[str, ...]


class SegmentFrames:
    """The segments of a set of joints and where each one's frame comes from.

    Parameters
    ----------
    joints : sequence of SegmentJoint
        In the node's order (the same order as the ``frame_poses`` and
        ``templates`` given to the methods).
    labels : mapping, optional
        Segment names by marker list (the node's configured ``segments``); the
        others are named by :func:`~jointfit_core.urdf.segment_names`.
    primary : int, optional
        Only the first ``primary`` joints may own a segment that one of them
        has (the others join it; a segment none of them has is owned by the
        rule among the rest). Default: all joints may.

    Attributes
    ----------
    names : list of str
        Segment names (:func:`~jointfit_core.urdf.segment_names`), in order of first appearance.
    owner : list of (int, int)
        Per segment, the joint index and side (0 parent, 1 child) whose template is its frame.
    members : list of list of (int, int)
        Per segment, every (joint, side) that has it, the owner first.
    """

    def __init__(
        self,
        joints: Sequence[SegmentJoint],
        labels: Mapping[tuple[str, ...], str] | None = None,
        primary: int | None = None,
    ) -> None:
        self.joints = list(joints)
        lists = [m for j in self.joints for m in (j.parent_markers, j.child_markers)]
        named = segment_names(lists, labels)
        self.names = list(named.values())
        index = {m: k for k, m in enumerate(named)}
        self.members: list[list[tuple[int, int]]] = [[] for _ in self.names]
        for i, j in enumerate(self.joints):
            for side, markers in enumerate((j.parent_markers, j.child_markers)):
                self.members[index[markers]].append((i, side))
        first = len(self.joints) if primary is None else primary
        for entry in self.members:  # the owner first: the first joint with it as the child, else the first
            candidates = [m for m in entry if m[0] < first] or entry
            children = [m for m in candidates if m[1] == 1]
            owner = children[0] if children else candidates[0]
            entry.remove(owner)
            entry.insert(0, owner)
        self.owner = [entry[0] for entry in self.members]
        self._segment_of = {(i, side): s for s, entry in enumerate(self.members) for i, side in entry}
        J, K = len(self.joints), max((len(e) for e in self.members), default=1)
        # per segment its members as flat indices 2 * joint + side, owner first, padded with 2J (never posed)
        self._member_index = np.full((len(self.names), K), 2 * J, dtype=np.intp)
        for s, entry in enumerate(self.members):
            self._member_index[s, : len(entry)] = [2 * i + side for i, side in entry]
        self._R_buf = np.zeros((2 * J, 3, 3))
        self._d_buf = np.zeros((2 * J, 3))
        self._posed_buf = np.zeros(2 * J, dtype=bool)
        self._stack: tuple[FloatArray, FloatArray, NDArray[np.bool_]] = (np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, bool))
        self._stack_key: tuple[int, ...] = ()

    def segment_of(self, joint: int, side: int) -> int:
        """The segment index of a joint's parent (side 0) or child (side 1)."""
        return self._segment_of[(joint, side)]

    def alignment(self, joint: int, side: int, templates: Sequence[Templates]) -> tuple[FloatArray, FloatArray] | None:
        """``(A (3, 3), a (3,))`` with ``x_segment = A x_joint + a`` from a joint's template frame to its segment's.

        Identity for the owner; None while either template is missing (see :meth:`_alignments`).
        """
        A, a, ok = self._alignments(templates)
        k = 2 * joint + side
        return (A[k], a[k]) if ok[k] else None

    def _alignments(self, templates: Sequence[Templates]) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """Every (joint, side)'s alignment stacked: ``A (2J, 3, 3)``, ``a (2J, 3)`` and whether it exists (2J,).

        Kabsch of the owner's template onto the joint's, recomputed only when a
        template was replaced (a template is replaced, not changed in place,
        when it is rebuilt: compared by identity).
        """
        key = tuple(id(tp) for pair in templates for tp in pair)
        if key != self._stack_key:
            J = len(self.joints)
            A = np.tile(np.eye(3), (2 * J, 1, 1))
            a = np.zeros((2 * J, 3))
            ok = np.zeros(2 * J, dtype=bool)
            for (i, side), seg in self._segment_of.items():
                oi, oside = self.owner[seg]
                mine, theirs = templates[i][side], templates[oi][oside]
                if mine is None or theirs is None:
                    continue
                if (oi, oside) != (i, side):
                    A[2 * i + side], a[2 * i + side] = kabsch(theirs, mine)
                ok[2 * i + side] = True
            self._stack = (A, a, ok)
            self._stack_key = key
        return self._stack

    def poses(self, frame_poses: Sequence[FramePoses], templates: Sequence[Templates]) -> tuple[FloatArray, FloatArray]:
        """Every segment's world pose in this frame: ``R (S, 3, 3)``, ``t (S, 3)``, NaN where none posed it.

        Parameters
        ----------
        frame_poses : sequence of (R (2, 3, 3), d (2, 3), posed (2,)) or None
            Per joint, :attr:`OnlineJoint.frame_poses <jointfit_core.estimator.OnlineJoint.frame_poses>`.
        templates : sequence of (parent, child) templates
            Per joint, :attr:`OnlineJoint.templates <jointfit_core.estimator.OnlineJoint.templates>`.

        Notes
        -----
        A segment takes the first member's pose that exists (the owner's
        first); a member's pose ``world = R x_joint + d`` is carried into
        the segment frame through its alignment: ``R A^T`` and
        ``d - R A^T a``. Vectorised over the segments: the joints' poses are
        stacked, each segment's first posed member picked by index.
        """
        J = len(self.joints)
        R = self._R_buf
        d = self._d_buf
        posed = self._posed_buf
        posed[:] = False
        for i, fp in enumerate(frame_poses):
            if fp is not None:
                R[2 * i : 2 * i + 2] = fp[0]
                d[2 * i : 2 * i + 2] = fp[1]
                posed[2 * i], posed[2 * i + 1] = fp[2]
        A, a, aligned = self._alignments(templates)
        usable = np.append(posed[: 2 * J] & aligned, False)  # the last entry: the members' padding
        pick = usable[self._member_index]  # (S, K)
        first = np.argmax(pick, axis=1)
        sel = self._member_index[np.arange(len(self.names)), first]
        found = pick[np.arange(len(self.names)), first]
        sel = np.where(found, sel, 0)
        RA = R[sel] @ np.swapaxes(A[sel], 1, 2)
        t = d[sel] - (RA @ a[sel][:, :, None])[:, :, 0]
        RA[~found] = np.nan
        t[~found] = np.nan
        return RA, t

    def joint_frames(
        self,
        solutions: Sequence[PoseSumsCentre | PoseSumsAxis | None],
        templates: Sequence[Templates],
        frozen: Sequence[bool],
    ) -> list[JointFrame]:
        """Every joint with an estimate, in its parent segment's frame (ball: the centre; hinge: axis point and direction)."""
        out: list[JointFrame] = []
        for i, (j, sol) in enumerate(zip(self.joints, solutions, strict=True)):
            al = self.alignment(i, 0, templates)
            if sol is None or al is None:
                continue
            A, a = al
            parent = self.names[self.segment_of(i, 0)]
            if isinstance(sol, PoseSumsCentre):
                out.append(JointFrame(j.name, parent, A @ sol.centre_parent + a, None, frozen[i]))
            else:
                out.append(JointFrame(j.name, parent, A @ sol.point_parent + a, A @ sol.direction_parent, frozen[i]))
        return out
