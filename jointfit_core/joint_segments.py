"""The two segments of an online joint: their marker counts, their templates and what is read from them.

:class:`JointSegments` is the layer of :class:`~jointfit_core.estimator.OnlineJoint`
between its estimate (:class:`~jointfit_core.joint_estimate.JointEstimate`, the
base) and its frame path (``OnlineJoint``): the parent's and the child's
:class:`~jointfit_core.segment_pair.SegmentPair`, made from the first frame (or
at once, from fixed templates or given marker counts), the templates' state
and sizes (the scale the estimate and its joint test are read at), the
outlier gate's counts per segment, the joint's lever ratios, and the status in
words while the templates are being built.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .errors import InputError
from .joint_args import JointSettings
from .joint_estimate import JointEstimate
from .lever import lever_ratios
from .pose import MIN_POSE_MARKERS
from .segment_pair import SegmentPair
from .segments import PoseSumsCentre

__all__ = ["JointSegments"]

FloatArray = NDArray[np.float64]


class JointSegments(JointEstimate):
    """A joint estimate whose frames come from two marker segments: their counts, templates and sizes.

    Parameters
    ----------
    settings : JointSettings
        The joint's checked arguments; this layer keeps ``template_frames``,
        ``templates`` (the fixed ones) and ``n_markers``, its base the rest.

    Attributes
    ----------
    n_markers : (int, int) or None
        Marker counts of the parent and the child (None until the first frame gives them).
    template_frames : int
        Fully visible frames averaged into each built template.
    """

    def __init__(self, settings: JointSettings) -> None:
        self.template_frames = settings.template_frames
        self._templates_arg = settings.templates
        self._n_markers_arg = settings.n_markers
        super().__init__(settings)

    def reset(self) -> None:
        """Forget the window, the estimate and the segments; fixed templates (and given counts) stay."""
        super().reset()
        self.n_markers: tuple[int, int] | None = self._n_markers_arg
        self._pose: SegmentPair | None = None  # the two segments, from the first frame (or fixed templates)
        tp, tc = self._templates_arg
        if tp is not None or tc is not None:
            assert self.n_markers is not None
            self._make_segments(*self.n_markers)
            assert self._pose is not None
            if tp is not None:
                self._pose.parent.set_template(tp)
            if tc is not None:
                self._pose.child.set_template(tc)

    @property
    def templates_ready(self) -> bool:
        """Whether both templates are established."""
        return self._pose is not None and self._pose.parent.template is not None and self._pose.child.template is not None

    @property
    def templates(self) -> tuple[FloatArray | None, FloatArray | None]:
        """The parent and child templates (local frames, input units), None until established."""
        return (
            None if self._pose is None else self._pose.parent.template,
            None if self._pose is None else self._pose.child.template,
        )

    @property
    def length_scale(self) -> float:
        """The larger rms radius of the two templates (input units; 0 until they exist)."""
        if not self.templates_ready:
            return 0.0
        assert self._pose is not None
        return max(self._pose.parent.rms_radius, self._pose.child.rms_radius)

    def _radii(self) -> tuple[float, float]:
        """The rms radii of the parent's and the child's templates (input units; (0, 0) until both exist)."""
        if not self.templates_ready:
            return (0.0, 0.0)
        assert self._pose is not None
        return (self._pose.parent.rms_radius, self._pose.child.rms_radius)

    def _marker_counts(self) -> tuple[int, int]:
        """The parent's and the child's marker counts ((4, 4) until the first frame gives them)."""
        return (4, 4) if self.n_markers is None else self.n_markers

    @property
    def gated_frames(self) -> tuple[int, int]:
        """Frames in which the parent and the child failed the outlier gate (held out whole or in part)."""
        return (
            0 if self._pose is None else self._pose.parent.gated_frames,
            0 if self._pose is None else self._pose.child.gated_frames,
        )

    @property
    def relabelled_frames(self) -> tuple[int, int]:
        """Frames in which the parent's and the child's labels were found swapped and put right (not held out)."""
        if self._pose is None:
            return (0, 0)
        return (self._pose.parent.relabelled_frames, self._pose.child.relabelled_frames)

    @property
    def lever_ratios(self) -> tuple[float, float] | None:
        """Per segment (parent, child), the joint's distance from its cluster over the cluster's rms radius.

        :func:`~jointfit_core.lever.lever_ratios` of the latest estimate (ball: the centre; hinge:
        the axis line) with the templates; None before an estimate. The soft-tissue bias no
        residual reveals grows with it (:mod:`jointfit_core.lever`).
        """
        sol = self._solution
        tp, tc = self.templates
        if sol is None or tp is None or tc is None:
            return None
        if isinstance(sol, PoseSumsCentre):
            return lever_ratios((tp, tc), (sol.centre_parent, sol.centre_child))
        return lever_ratios((tp, tc), (sol.point_parent, sol.point_child), (sol.direction_parent, sol.direction_child))

    def status(self) -> str:
        """What the estimator is waiting for, in words (empty when estimating)."""
        if self._pose is None:
            return "waiting for the first frame"
        if not self.templates_ready:
            return (
                f"building templates from fully visible frames: parent {self._pose.parent.template_progress}/"
                f"{self.template_frames}, child {self._pose.child.template_progress}/{self.template_frames}"
            )
        return ""

    def rarely_seen(self) -> tuple[list[int], list[int]]:
        """The parent's and the child's markers (rows) that hold their templates back: missing from most frames.

        :meth:`SegmentTracker.rarely_seen <jointfit_core.segment_tracker.SegmentTracker.rarely_seen>`; empty
        lists once the templates are built.
        """
        if self._pose is None:
            return [], []
        return self._pose.parent.rarely_seen(), self._pose.child.rarely_seen()

    def _make_segments(self, n_parent: int, n_child: int) -> None:
        """The two segments, of ``n_parent`` and ``n_child`` markers (their templates to build).

        Raises
        ------
        InputError
            Fewer than :data:`~jointfit_core.pose.MIN_POSE_MARKERS` markers on either (from a first frame).
        """
        if n_parent < MIN_POSE_MARKERS or n_child < MIN_POSE_MARKERS:
            raise InputError(
                f"parent, child: expected at least {MIN_POSE_MARKERS} markers per segment, got {n_parent} and {n_child}"
            )
        self.n_markers = (n_parent, n_child)
        self._pose = SegmentPair(n_parent, n_child, self.template_frames)
