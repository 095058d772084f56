"""The frames a joint receives while its segments' templates are being built.

An online joint (:class:`~jointfit_core.estimator.OnlineJoint`) estimates in
its segments' local frames, which its templates define: each segment's
template is the average of its first ``template_frames`` fully visible,
mutually consistent frames, each aligned (Kabsch) to the first of them
(:meth:`SegmentTracker.add_template_frame
<jointfit_core.segment_tracker.SegmentTracker.add_template_frame>`), so the
local frame is that first frame's orientation about the template centroid.
Templates are then fixed, so that estimates in the local frames stay
comparable and a saved calibration stays valid. :class:`TemplateStage` gives
each frame to both templates meanwhile and keeps it, so that the frames
seen before the templates were fixed still enter the window once they are
(at most :data:`KEPT_TEMPLATE_LENGTHS` times ``template_frames`` of them:
beyond, the oldest leave).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from .segment_pair import SegmentPair

__all__ = ["KEPT_TEMPLATE_LENGTHS", "KeptFrame", "TemplateStage"]

FloatArray = NDArray[np.float64]

#: Frames kept while the templates are built, in multiples of ``template_frames`` (the oldest leave beyond).
KEPT_TEMPLATE_LENGTHS = 20

#: A kept frame: parent markers (Pa, 3), child markers (Pc, 3) (world, input units), stamp (s) or None, frame number.
KeptFrame = tuple[FloatArray, FloatArray, float | None, int]


class TemplateStage:
    """The frames seen while a joint's templates are being built, kept to enter its window once both are fixed.

    Parameters
    ----------
    template_frames : int
        Fully visible frames averaged into each template.

    Attributes
    ----------
    kept : list of KeptFrame
        The frames kept so far, oldest first.
    """

    def __init__(self, template_frames: int) -> None:
        self.max_kept = KEPT_TEMPLATE_LENGTHS * template_frames
        self.kept: list[KeptFrame] = []

    def add(self, pair: SegmentPair, parent: FloatArray, child: FloatArray, stamp: float | None, number: int) -> bool:
        """Give a frame to both segments' templates and keep a copy of it.

        Parameters
        ----------
        pair : SegmentPair
            The joint's two segments, their templates being built.
        parent, child : ndarray, shape (Pa, 3) and (Pc, 3)
            The frame's markers (world, input units; NaN: missing).
        stamp : float or None
            Its stamp (s).
        number : int
            Its frame number.

        Returns
        -------
        bool
            True when the oldest kept frame left to make room (the joint counts it as ``before_templates``).
        """
        pair.parent.add_template_frame(parent)
        pair.child.add_template_frame(child)
        self.kept.append((parent.copy(), child.copy(), stamp, number))
        if len(self.kept) > self.max_kept:
            self.kept.pop(0)
            return True
        return False

    def release(self) -> list[KeptFrame]:
        """The kept frames, oldest first, forgotten here (once the templates are fixed, to enter the window)."""
        kept, self.kept = self.kept, []
        return kept
