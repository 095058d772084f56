"""Online joint between two moving segments: the estimator the ROS node drives.

:class:`OnlineJoint` takes, per frame, the world positions of the parent and
child markers; establishes each segment's template from its first fully
visible frames; fits both poses; keeps the sufficient statistics of the
relative poses over a sliding window (:mod:`jointfit_core.stats`); and
returns, for every frame, the joint's world position (or axis) carried by the
current parent pose, with its covariance. This module holds its frame path:
the frames' intake (checked, numbered and stamped by a
:class:`~jointfit_core.frame_clock.FrameClock`; the frames kept while the
templates are built, :class:`~jointfit_core.template_stage.TemplateStage`), the per-frame step (posing, the outlier gate, the joint
test, the window, the output) and the counters of what was dropped. The rest
is in the modules around it:

* its layers below: :class:`~jointfit_core.joint_segments.JointSegments`, the
  two segments with their templates and sizes, on
  :class:`~jointfit_core.joint_estimate.JointEstimate`, the window and the
  estimate solved from it (:meth:`OnlineJoint.estimate`: the closed forms
  :func:`~jointfit_core.segments.centre_from_pose_sums` and
  :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums` on the sums,
  their covariances widened by the frame-to-frame correlation of the joint
  residual, :mod:`jointfit_core.serial`; solve requests and installs; freeze
  and thaw);
* the constructor's checks and the virtual markers of a pose stream:
  :mod:`jointfit_core.joint_args`; the outlier gate's limits and what follows
  a failing segment: :mod:`jointfit_core.joint_outliers`;
* its block path (:meth:`OnlineJoint.update_many`):
  :mod:`jointfit_core.joint_blocks`; its calibration file
  (:meth:`OnlineJoint.to_dict`, :meth:`OnlineJoint.from_dict`):
  :mod:`jointfit_core.joint_file`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import joint_blocks, joint_file
from .calibration_fit import CalibrationFit
from .checks import check_frame
from .frame_clock import FrameClock
from .joint_args import check_settings, virtual_markers_template
from .joint_estimate import JointEstimate
from .joint_file import CALIBRATION_FORMAT, CALIBRATION_VERSION
from .joint_gate import JointTrack
from .joint_misfit import JointDrift
from .joint_outliers import GateLimits, after_failure
from .joint_segments import JointSegments
from .joint_world import JointOutput, WorldOutput
from .segment_pair import poses
from .serial import NOMINAL_RATE_HZ
from .template_stage import TemplateStage
from .window_entries import WINDOW_MAX_FRAMES
from .window_solve import SKIN_MIN_MOVEMENT_S, SolveRequest, SolveResult, solve_window

__all__ = [
    "OnlineJoint",
    "JointOutput",
    "SolveRequest",
    "SolveResult",
    "solve_window",
    "virtual_markers_template",
    "CALIBRATION_FORMAT",
    "CALIBRATION_VERSION",
    "SKIN_MIN_MOVEMENT_S",
]

FloatArray = NDArray[np.float64]


class OnlineJoint(JointSegments):
    """Ball joint or hinge between two moving segments, online, O(1) per frame.

    Parameters
    ----------
    kind : {"ball", "hinge"}
    window : int, optional
        Window length in frames (>= 3).
    window_s : float, optional
        Window length in seconds (stamps required).
    half_life : float, optional
        Exponential forgetting, half-life in frames.
    half_life_s : float, optional
        Exponential forgetting, half-life in seconds (stamps required).
    template_frames : int
        Fully visible frames averaged into each segment's template before
        estimation starts (default 50). The frames seen meanwhile are kept
        and enter the window once the templates are fixed.
    reference_direction : array_like, shape (3,), optional
        Hinge sign convention, parent local frame (see
        :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums`); keeps the
        sign stable over time.
    n_markers : (int, int), optional
        Expected marker counts of the parent and the child (default: from
        the first frame). At least 3 each.
    templates : (array_like or None, array_like or None), optional
        Fixed templates ``(Pa, 3)`` and ``(Pc, 3)`` (local frames, input
        units) instead of building them from the first frames (None: build
        that one); e.g. the virtual markers of a rigid-body pose stream
        (:func:`virtual_markers_template`). With one fixed, give ``n_markers``.
    noise_std : (float or None, float or None), optional
        Fixed marker noise of the parent and the child (input units)
        instead of the residual estimate (None: estimate); needed with
        virtual markers, whose pose fits have no residual.
    serial_correlation : bool
        Multiply the estimate's covariances by the integrated autocorrelation
        of the joint-constraint residual over the window, read at lags in
        seconds (default True; see Notes). False gives the covariances of the
        closed forms on the window exactly; the lag-1 ``rho`` is measured and
        reported (:attr:`serial_inflation`) either way.
    gate : float
        Outlier gate (default 5; 0 disables it): once the templates and a
        noise estimate exist, a segment whose markers, posed in its template
        frame, jump from its last passed frame by more than ``gate`` times
        its normal jump (:mod:`jointfit_core.gate`; or that fails the
        residual test, rms residual above ``gate`` times the segment's own pooled
        pose-fit residual, while moving more than usual; both limits read
        again every :data:`~jointfit_core.segment_tracker.GATE_REFRESH_FRAMES` frames,
        :meth:`GateLimits.sigma <jointfit_core.joint_outliers.GateLimits.sigma>`) has its labels put right when its markers are
        its reference's under other labels (a swap,
        :meth:`~jointfit_core.segment_pair.SegmentPair.relabel`,
        :attr:`relabelled_frames`), else loses its worst-fitting marker and is
        fitted again, down to 3 markers; if it still fails, the segment is
        not posed in that frame. Ghost markers and jumps are dropped before
        they reach the statistics or the per-frame output; smooth skin
        deformation passes (see Notes, :attr:`gated_frames`).
    attachment : {"rigid", "skin"} or (str, str)
        How the parent's and the child's markers are attached (one for both,
        or a pair; :func:`~jointfit_core.artefact.check_attachment`): skin
        markers add the soft-tissue part to the estimate's covariances.
    window_max_frames : int or None
        Most frames a ``window_s`` window holds (default
        :data:`~jointfit_core.window_entries.WINDOW_MAX_FRAMES`; None or 0: no
        bound): fed faster than ``window_max_frames / window_s`` frames per
        second, at most one frame per ``window_s / window_max_frames`` seconds
        enters the window (the others get their outputs as usual), so that its
        memory does not grow with the input rate
        (:mod:`jointfit_core.window_entries`). Other windows keep every frame.

    Exactly one of ``window``, ``window_s``, ``half_life``, ``half_life_s``.

    Notes
    -----
    Where each step of a frame is described: the templates, built from the
    first frames, in :mod:`jointfit_core.template_stage`; the poses, and the
    **statistics** a frame adds to the window, in the Notes of
    :class:`~jointfit_core.joint_sums.RelativePoseSums`; the **estimate**
    solved from the window and how the **serial correlation** widens its
    covariances, in the Notes of the base,
    :class:`~jointfit_core.joint_estimate.JointEstimate`; the **per-frame
    output** of :meth:`update` and its covariance, in
    :meth:`WorldOutput.output <jointfit_core.joint_world.WorldOutput.output>`.
    """

    def __init__(
        self,
        kind: str = "ball",
        window: int | None = None,
        *,
        window_s: float | None = None,
        half_life: float | None = None,
        half_life_s: float | None = None,
        template_frames: int = 50,
        reference_direction: ArrayLike | None = None,
        n_markers: tuple[int, int] | None = None,
        templates: tuple[ArrayLike | None, ArrayLike | None] | None = None,
        noise_std: tuple[float | None, float | None] | None = None,
        serial_correlation: bool = True,
        gate: float = 5.0,
        attachment: str | tuple[str, str] = "rigid",
        window_max_frames: int | None = WINDOW_MAX_FRAMES,
    ) -> None:
        settings = check_settings(
            kind,
            window,
            window_s=window_s,
            half_life=half_life,
            half_life_s=half_life_s,
            template_frames=template_frames,
            reference_direction=reference_direction,
            n_markers=n_markers,
            templates=templates,
            noise_std=noise_std,
            serial_correlation=serial_correlation,
            gate=gate,
            attachment=attachment,
            window_max_frames=window_max_frames,
        )
        self.gate = settings.gate
        #: True while the frames given are ones this joint received before (a looped replay, told by the
        #: caller: :mod:`jointfit_ros.repeated_frames`): they are posed, gated and given outputs, but not
        #: added to the window (nor to the templates), which would count them as new measurements.
        self.replayed = False
        #: When a list: ``(frame number, segment (0 parent, 1 child), stamp or NaN)`` of every frame in
        #: which a segment failed the outlier gate (offline reports mark them; None: not kept).
        self.gate_log: list[tuple[int, int, float]] | None = None
        super().__init__(settings)  # (which calls reset)

    def reset(self) -> None:
        """Forget the frames, estimate, frozen state, counters and built templates (fixed ones stay)."""
        super().reset()
        self._template_stage = TemplateStage(self.template_frames)  # the frames seen while the templates are built
        self.dropped: dict[str, int] = {}
        #: Frames received again (:attr:`replayed`) and therefore not added to the window.
        self.replayed_frames = 0
        self.n_frames_seen = 0
        #: The latest :meth:`update` frame's segment poses, after the gate: ``(R (2, 3, 3), d (2, 3),
        #: posed (2,))`` in the templates' frames (``world = R @ local + d``; a segment not posed has
        #: ``posed`` False), or None (no templates yet, the frame dropped, the joint test failed, or
        #: the frame came in a block). The skeleton's segment outputs read it
        #: (:mod:`jointfit_core.segment_frames`).
        self.frame_poses: tuple[FloatArray, FloatArray, tuple[bool, bool]] | None = None
        # Frames are numbered as they arrive, and their stamps checked (FrameClock; the clock of the outlier
        # gate's turn test and of its limits' refresh). The gate's limits are cached (GateLimits); each
        # segment's memory is in its tracker.
        self._clock = FrameClock(self.spec)
        self._limits = GateLimits(self.gate, self._noise_arg)
        # The joint-consistency test (jointfit_core.joint_gate): frames whose segments break the joint.
        self._joint = JointTrack(self.gate)
        self.joint_gated_frames = 0
        #: Frame numbers at which the joint broke for good (:attr:`JointTrack.broke
        #: <jointfit_core.joint_gate.JointTrack.broke>`); estimating, the window restarted there.
        self.joint_breaks: list[int] = []
        # while frozen: do the markers still fit the calibration's templates (a marker knocked on its cluster)?
        self._fit = CalibrationFit(self.attachment)
        self._outputs = WorldOutput(self.kind)
        # while estimating on rigid markers: do the recent frames still agree with the estimate (a cluster bumped)?
        self._drift = JointDrift() if not self._skin else None
        #: Frame numbers at which the recent frames disagreed with the estimate beyond
        #: :data:`~jointfit_core.joint_misfit.DRIFT_LIMIT` (a cluster moved on its bone): the window restarted there.
        self.joint_drifts: list[int] = []

    def _installed(self) -> None:
        """A new estimate: the per-frame outputs' cache is cleared and the joint test armed with it."""
        self._outputs.clear()
        self._joint.arm(self._solution, self.length_scale)

    def _drop(self, reason: str) -> None:
        """Count a frame (or part) dropped for ``reason`` in :attr:`dropped`."""
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    # ------------------------------------------------------------------ streaming

    def update(self, parent: ArrayLike, child: ArrayLike, stamp: float | None = None) -> JointOutput | None:
        """Add one frame and return the joint in the world for it.

        Parameters
        ----------
        parent, child : array_like, shape (Pa, 3) and (Pc, 3)
            World marker positions of the two segments (input units), NaN
            for a missing marker.
        stamp : float, optional
            Seconds; needed by time windows; must increase.

        Returns
        -------
        JointOutput or None
            The joint carried by this frame's parent pose with the latest
            estimate; None while there is no estimate yet (templates being
            built, nothing solved yet) or when the parent cannot be posed.

        Raises
        ------
        InputError
            Wrong shapes or marker counts, infinite values, a missing stamp
            that the window needs.

        Notes
        -----
        Frames are dropped from the statistics, and counted in
        :attr:`dropped`, when the stamp does not increase
        (``stamp_not_increasing``), when a segment cannot be posed from its
        visible markers (``parent_not_posed``, ``child_not_posed``), and
        while frozen (not counted: expected).
        """
        self.frame_poses = None
        pose = self._pose
        if pose is not None and self.templates_ready and pose.fast_fill(parent, child):
            return self._after_fill(stamp)
        yp = check_frame(parent, None if self.n_markers is None else self.n_markers[0], name="parent")
        yc = check_frame(child, None if self.n_markers is None else self.n_markers[1], name="child")
        number, st, ok = self._clock.arrive(stamp)
        if not ok:
            self._drop("stamp_not_increasing")
            return None
        if self._pose is None:
            self._make_segments(yp.shape[0], yc.shape[0])
        pose = self._pose
        assert pose is not None
        self.n_frames_seen += 1

        if not self.templates_ready:
            if self.replayed:
                self.replayed_frames += 1
                return None
            if self._template_stage.add(pose, yp, yc, st, number):
                self._drop("before_templates")
            if self.templates_ready:
                for p_frame, c_frame, p_stamp, p_number in self._template_stage.release():
                    self._add(pose.fill(p_frame, c_frame), p_stamp, p_number)
            return None
        return self._add(pose.fill(yp, yc), st, number)

    def update_many(self, parent: ArrayLike, child: ArrayLike, stamps: ArrayLike | None = None) -> None:
        """Add a block of frames: the state of :meth:`update` of each frame in turn, without the outputs.

        For offline fits of whole recordings, where the per-frame world
        outputs are not needed: once the templates are fixed, the frames of
        the block are posed, turned into contributions and added to the
        window in a few vectorised steps instead of one Python call each
        (:func:`jointfit_core.joint_blocks.update_many`, whose Notes say how
        and in what it equals :meth:`update`: counters, stamps, templates and
        window frames the same, the sums to rounding).

        Parameters
        ----------
        parent, child : array_like, shape (N, Pa, 3) and (N, Pc, 3)
            World marker positions of the two segments, frame after frame
            (input units), NaN for a missing marker.
        stamps : array_like, shape (N,), optional
            Seconds; needed by time windows; a frame whose stamp does not
            exceed every earlier one is dropped (``stamp_not_increasing``).

        Raises
        ------
        InputError
            Wrong shapes or marker counts, infinite values, non-finite
            stamps, or no stamps for a window that needs them. The whole
            block is checked first, so nothing is added when it raises
            (:meth:`update` would have added the frames before the bad one;
            call it frame by frame where that matters).
        """
        joint_blocks.update_many(self, parent, child, stamps)

    def _after_fill(self, stamp: float | None) -> JointOutput | None:
        pose = self._pose
        assert pose is not None
        number, st, ok = self._clock.arrive(stamp)
        if not ok:
            self._drop("stamp_not_increasing")
            return None
        self.n_frames_seen += 1
        return self._add(pose.missing, st, number)

    def _add(
        self,
        missing: NDArray[np.bool_],
        stamp: float | None,
        frame_no: int,
        counted: tuple[bool, bool] = (False, False),
        refit: tuple[bool, bool] = (False, False),
        relabelled: bool = False,
    ) -> JointOutput | None:
        """Pose both segments from the pair's marker buffer ``Y`` (filled, ``missing`` rows NaN) and update the statistics.

        ``frame_no``: the frame's number (1-based count of the frames seen, for the gate's turn
        test). ``counted``: segments already counted as not posed for this frame (a refit after
        the gate). ``refit``: per segment, whether the gate left its markers out earlier in
        this frame (this call refits them; :meth:`~jointfit_core.segment_pair.SegmentPair.judge`).
        ``relabelled``: the call after the gate put a swap's labels right
        (:meth:`~jointfit_core.segment_pair.SegmentPair.relabel`; not tried again).
        """
        pose = self._pose
        assert pose is not None
        ps = pose.pair(missing)
        if ps.parent is None and not counted[0]:
            self._drop("parent_not_posed")
        if ps.child is None and not counted[1]:
            self._drop("child_not_posed")
        if ps.parent is None and ps.child is None:
            self._stats.chained = False
            return None
        Y = pose.Y
        if missing is not pose.none_missing:
            Y[missing] = 0.0  # _poses needs zeros where a marker is missing
        R, d, ss = poses(Y, ps)
        self.frame_poses = (R, d, (ps.parent is not None, ps.child is not None))  # a refit below replaces it
        gate_var = self._limits.var(self._clock.arrivals, pose, self)
        if gate_var is None and self.gate > 0.0:  # no level yet (fixed templates): the segments' own, to start from
            for k, vs in enumerate((ps.parent, ps.child)):
                if vs is not None:
                    pose.tracker(k).add_level(float(ss[k]), vs.dof, frame_no)
        if gate_var is not None:
            verdict = pose.judge(ps, R, d, ss, frame_no, refit)
            if verdict is not None:  # labels put right or markers held out, and the frame judged again
                return after_failure(self, missing, ps, verdict, stamp, frame_no, refit, relabelled)
        if ps.parent is not None and ps.child is not None and self._joint.residual is not None:
            time = frame_no / NOMINAL_RATE_HZ if stamp is None else stamp
            if not self._joint.check_one(R, d, frame_no, self._frozen, time):  # the joint test (jointfit_core.joint_gate)
                self.joint_gated_frames += 1
                self._drop("joint_gated")
                if self.gate_log is not None:
                    self.gate_log.append((frame_no, 2, np.nan if stamp is None else stamp))
                self._stats.chained = False
                self.frame_poses = None  # one of the two poses is wrong, which one is not known
                return None
            if self._joint.broke:  # the relative pose changed for good: the window's frames are another joint's
                self._joint_broke(frame_no)
            elif self._drift is not None and not self._frozen and self._drift.step(
                self._generation, time, *self._joint.latest,
                ps.parent.W_unit, self._sigma[0] ** 2, self._solution, self._joint.residual,
            ):  # the recent frames disagree with the estimate for good (a cluster moved on its bone)
                self.joint_drifts.append(frame_no)
                JointEstimate.reset(self)  # the window's frames are of two placements: the next are the estimate's
                self._installed()
        if self._frozen and ps.parent is not None and ps.child is not None:  # does the joint still hold?
            # (the joint test above has just passed this frame: its relative pose and joint residual)
            z, e = self._joint.latest
            self._fit.add_joint(z, e, self._joint.residual, self._solution)
        if self._frozen and self._fit.add_frame(ss, ps, self._sigma):  # the markers off the calibration's templates
            if not self._fit.holding:
                self._drop("markers_off_calibration")
            elif ps.parent is not None:  # (a frame without a parent pose has no output to hold: counted above)
                self._drop("calibration_being_checked")
            self.frame_poses = None
            return None
        both = ps.parent is not None and ps.child is not None
        if both and not self._frozen and not self.replayed:
            if self._stats.add_frame(R, d, ss, ps, stamp, frame_no, Y):
                self._version += 1
        else:
            if both and not self._frozen:  # left out because it was received before
                self.replayed_frames += 1
            self._stats.chained = False
        if ps.parent is None or self._solution is None:
            return None
        if self._drift is not None and not self._frozen and self._drift.holds(self._generation):
            self._drop("recent_frames_disagree")  # the recent frames disagree with the estimate; not yet a drift
            return None
        child_pose = (R[1], d[1], ps.child) if ps.child is not None else None
        return self._outputs.output(
            self._solution, self._sigma, R[0], d[0], ps.parent, child_pose, self._cluster_motion
        )

    @property
    def calibration_problem(self) -> str:
        """Empty while a frozen joint's markers fit its calibration; else why its outputs are withheld."""
        return self._fit.problem if self._frozen else ""

    def _joint_broke(self, frame_no: int) -> None:
        """The joint test found the two segments' relative pose changed for good at frame ``frame_no``.

        Estimating: the window and the estimate are forgotten (a new generation: solves in flight are
        not installed), the frames from this one on make the next. Frozen: the outputs are held until
        the calibration is judged against the markers again (:meth:`hold_until_judged`).
        """
        self._joint.broke = False
        self.joint_breaks.append(frame_no)
        if self._frozen:
            self.hold_until_judged()
            return
        JointEstimate.reset(self)
        self._installed()

    def hold_until_judged(self) -> None:
        """A frozen calibration from another session: no output until its markers have been judged against it.

        :meth:`CalibrationFit.hold_until_judged <jointfit_core.calibration_fit.CalibrationFit.hold_until_judged>`
        (the first :data:`~jointfit_core.calibration_fit.JOINT_MISFIT_FRAMES` posed frames, counted as
        ``dropped["calibration_being_checked"]``). The node calls it for a calibration file it loads;
        :meth:`from_dict` alone publishes from the first frame (the same session's markers).
        """
        self._fit.hold_until_judged()

    def freeze(self) -> Any:
        """:meth:`JointEstimate.freeze <jointfit_core.joint_estimate.JointEstimate.freeze>`; the markers are judged against it from now."""
        sol = super().freeze()
        self._fit.restart()
        return sol

    def thaw(self) -> None:
        """:meth:`JointEstimate.thaw <jointfit_core.joint_estimate.JointEstimate.thaw>`; a later freeze judges afresh.

        A calibration whose outputs were withheld (its markers no longer fit it, or a loaded one not judged yet)
        is forgotten: the joint publishes again once its window has been solved. Kept, it went out again from
        the thaw to the first solve (hunt-calib2 B: a knee whose thigh plate was put back elsewhere, ~20 mm off
        at e/2 ~200, status "estimating"), judged by nothing any more.
        """
        withheld = bool(self._fit.problem)
        super().thaw()
        self._fit.restart()
        if withheld:
            self._forget_estimate()

    # ------------------------------------------------------------------ calibration

    def to_dict(self) -> dict[str, Any]:
        """The calibration as plain YAML-able types: settings, templates, noise and estimate (:mod:`jointfit_core.joint_file`).

        Raises
        ------
        InputError, NotIdentifiableError
            No estimate can be made yet.
        """
        return joint_file.to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OnlineJoint:
        """A frozen estimator from a saved calibration (:meth:`to_dict`; :mod:`jointfit_core.joint_file`).

        The templates and the estimate are restored, so per-frame outputs
        start with the first frame. :meth:`thaw` resumes estimation (with
        the saved templates).

        Raises
        ------
        InputError
            Not a jointfit calibration, a newer version, or malformed fields.
        """
        return joint_file.from_dict(cls, data)
