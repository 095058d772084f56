"""Online joint between two moving segments: the estimator the ROS node drives.

:class:`OnlineJoint` takes, per frame, the world positions of the parent and
child markers; establishes each segment's template from its first fully
visible frames; fits both poses; keeps the sufficient statistics of the
relative poses over a sliding window (:mod:`jointfit_core.stats`); and
returns, for every frame, the joint's world position (or axis) carried by the
current parent pose, with its covariance. :meth:`OnlineJoint.estimate`
solves the closed forms (:func:`~jointfit_core.segments.centre_from_pose_sums`,
:func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums`) from the sums and
widens their covariances by the frame-to-frame correlation of the joint
residual (:mod:`jointfit_core.serial`). Its block path (:meth:`OnlineJoint.update_many`)
is :mod:`jointfit_core.joint_blocks`, its calibration file (:meth:`OnlineJoint.to_dict`,
:meth:`OnlineJoint.from_dict`) :mod:`jointfit_core.joint_file`, its constructor's checks
(and the virtual markers of a pose stream, :func:`virtual_markers_template`)
:mod:`jointfit_core.joint_args`, its outlier gate's limits and what follows a
failing segment :mod:`jointfit_core.joint_outliers`, and its frame numbers and
stamps a :class:`~jointfit_core.frame_clock.FrameClock`.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import joint_blocks, joint_file
from .checks import check_frame, check_vector3
from .errors import InputError
from .frame_clock import FrameClock
from .hinge_from_sums import PoseSumsAxis
from .joint_args import check_settings, virtual_markers_template
from .joint_file import CALIBRATION_FORMAT, CALIBRATION_VERSION
from .joint_gate import JointTrack
from .joint_outliers import GateLimits, after_failure
from .joint_sums import RelativePoseSums
from .joint_world import JointOutput, WorldOutput
from .lever import lever_ratios
from .pose import MIN_POSE_MARKERS
from .segment_pair import SegmentPair, poses
from .segments import (
    PoseSums,
    PoseSumsCentre,
)
from .serial import (
    LagSums,
    SerialInflation,
    TimeLagSums,
)
from .stats import WindowSpec
from .window_solve import (
    SKIN_MIN_MOVEMENT_S,
    SolveRequest,
    SolveResult,
    solve_window,
    unpack_pose_sums,
)

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

# --------------------------------------------------------------------------- solving a window

#: Estimator states whose solve results may be installed, numbered across all estimators of the process
#: (a runner replaces its estimator on reset: an answer for the old one must not fit the new one).
_GENERATIONS = itertools.count(1)


class OnlineJoint:
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

    Exactly one of ``window``, ``window_s``, ``half_life``, ``half_life_s``.

    Notes
    -----
    **Templates.** Each segment's template is the mean of its first
    ``template_frames`` fully visible frames, each aligned (Kabsch) to the
    first of them; the local frame is therefore that first frame's
    orientation about the template centroid. Templates are then fixed, so
    that estimates in the local frames stay comparable and a saved
    calibration stays valid.

    **Statistics.** Per frame, both poses are fitted to the visible markers
    (Stoddart eq. 4); frames where a segment's visible markers are nearly
    collinear or bunched (rotation variance above
    :data:`~jointfit_core.segments.POSE_VAR_RATIO_MAX` times the full
    template's) are not used. The window keeps the sums of
    :class:`~jointfit_core.segments.PoseSums`, of the unit-noise local pose
    covariances of the visible marker sets, and of the pose-fit residuals;
    ``noise_std_*`` is the pooled residual estimate over the window
    (``sum SS / sum (3 n_vis - 6)``, not corrected for the template's own
    degrees of freedom, which is negligible after a few dozen frames).

    **Estimate.** :meth:`estimate` is
    :func:`~jointfit_core.segments.centre_from_pose_sums` (ball; Stoddart eq.
    9 with bias compensation and sandwich covariance) or
    :func:`~jointfit_core.hinge_from_sums.axis_from_pose_sums` (hinge) on the
    window's sums, with the mean local pose covariances times the current
    noise variances: identical to those functions on the window's frames.
    On rigid markers the weighted (Gauss-Markov) batch fit is about 25 % more
    precise but needs every frame; on skin markers a batch hinge reports the
    same closed form as this (the refinement is less accurate under soft-tissue
    artefact, :func:`~jointfit_core.segments.fit_axis_two_segments`).

    **Serial correlation** (``serial_correlation=True``). Those covariances
    treat the frames as independent. Soft-tissue artefact moves markers
    smoothly, so the constraint residual ``r_k = c_p - Q_k c_c - t_k`` is
    correlated in time (lag-1 autocorrelation 0.95-0.998 on skin markers at
    100 Hz; the real hip's falls to 0.45 at 0.32 s and to 0 at 0.64 s) and
    N frames carry the information of about ``N / F`` independent ones, ``F =
    1 + 2 sum_l (1 - l dt / T) rho(l dt)`` the integrated autocorrelation
    (Bartlett, ``T`` = :data:`~jointfit_core.serial.SERIAL_WINDOW_S`). The
    window therefore also keeps, per frame k, the products of its relative
    pose with that of frame k-1 and with those of the frames
    :data:`~jointfit_core.serial.SERIAL_LAGS_S` seconds earlier
    (:mod:`jointfit_core.serial`, :class:`~jointfit_core.serial.LagHistory`:
    pairs found from the stamps, frames without stamps counted at
    :data:`~jointfit_core.serial.NOMINAL_RATE_HZ`), from which
    ``rho(lag) = (sum_pairs r_k . r_j / n_pairs) / (sum_frames |r_k|^2 / n)``
    at the estimate (ball: the centres; hinge: the solved axis-point pair,
    :func:`~jointfit_core.serial.hinge_residual_pair`), and every covariance
    of the estimate (ball: ``cov``, ``cov_parent``, ``cov_child``; hinge:
    directions and points) is multiplied by
    :func:`~jointfit_core.serial.integrated_factor` of them (summed until the
    correlation is noise). Reading the correlation in seconds makes ``N dt /
    F``, the seconds per independent sample, the same at any frame rate; the
    lag-1 AR(1) factor ``(1 + rho) / (1 - rho)`` that
    :func:`~jointfit_core.model_error.residual_inflation` applies to the batch
    fits is not (real hip: 2 effective frames at 100 Hz, 8 at 12.5 Hz; now
    30 and 29). The batch fits' ``chi2`` factor is not applied: the sandwich's middle is the
    residual covariance predicted from the pooled pose-fit noise, which on
    skin markers already grows with the cluster deformation (right hip
    fixture: ``sum |r|^2 / ((N - 2) tr W) = 1.09``); artefact that moves a
    cluster rigidly would not show there. When the factor makes an
    identifiable estimate's standard deviation exceed the verdict's limits
    (:data:`~jointfit_core.segments.SD_REL_MAX` of the lever arm,
    :data:`~jointfit_core.segments.AXIS_SD_MAX_DEG`), it is flagged as the
    batch fits flag it. *Lag pairs*: the pair ``(k-1, k)`` is stored with
    frame k, and only when frame k-1 is the frame that entered the
    statistics just before it, with no frame in between that reached the
    estimator but could not enter them (a segment not posed, or frozen);
    frames dropped for a non-increasing stamp do not break the chain. A
    pair leaves the window (or decays) with frame k, so the oldest frame of
    a window still carries its pair with the frame before it: the window's
    sums are the batch sums of its frames
    (:func:`~jointfit_core.segments.pose_sums_from_relative`) and of the
    pairs ending in them (:func:`~jointfit_core.serial.lag_sums_from_relative`
    over the window and the frame before it). The pairs at lags in seconds are
    stored with their later frame in the same way.

    **Per-frame output** (:meth:`update`): ``R_p c_p + d_p`` with covariance
    ``R_p (cov_parent + J W_p(t) J^T) R_p^T`` (this frame's parent pose noise
    at the centre, ``J = [-[c_p]x, I]``), from the latest :meth:`estimate`
    (``cov_parent`` with the serial-correlation factor; the pose-noise term
    without it: the correlation makes the frames' errors alike, it does not
    make one frame's error larger).
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
        )
        self.kind = settings.kind
        self.spec: WindowSpec = settings.spec
        self.template_frames = settings.template_frames
        self.reference_direction = settings.reference_direction
        self._templates_arg = settings.templates
        self._noise_arg = settings.noise_std
        self._n_markers_arg = settings.n_markers
        self.serial_correlation = settings.serial_correlation
        self.gate = settings.gate
        #: ``("skin" | "rigid", "skin" | "rigid")``: how the parent's and the child's markers are attached.
        self.attachment = settings.attachment
        self._skin = "skin" in self.attachment
        self._moments = self._skin and self.kind == "hinge"
        #: When a list: ``(frame number, segment (0 parent, 1 child), stamp or NaN)`` of every frame in
        #: which a segment failed the outlier gate (offline reports mark them; None: not kept).
        self.gate_log: list[tuple[int, int, float]] | None = None
        self.reset()

    # ------------------------------------------------------------------ state

    def reset(self) -> None:
        """Forget the frames, estimate, frozen state, counters and built templates (fixed ones stay)."""
        self.n_markers: tuple[int, int] | None = self._n_markers_arg
        self._stats = RelativePoseSums(self.spec, self._skin, self._moments)
        self._pending: list[tuple[FloatArray, FloatArray, float | None, int]] = []
        self._solution: PoseSumsCentre | PoseSumsAxis | None = None
        self._sigma = (0.0, 0.0)
        # Data changes since the start (frames entered; hinge sign convention) and the change the
        # solution was solved at: the solution is stale while they differ. A reset (and a new sign
        # convention) starts a new generation, whose solve results alone may be installed.
        self._version = 0
        self._solved_version = 0
        self._generation = next(_GENERATIONS)
        self._frozen = False
        self.dropped: dict[str, int] = {}
        self.n_frames_seen = 0
        #: The latest :meth:`update` frame's segment poses, after the gate: ``(R (2, 3, 3), d (2, 3),
        #: posed (2,))`` in the templates' frames (``world = R @ local + d``; a segment not posed has
        #: ``posed`` False), or None (no templates yet, the frame dropped, the joint test failed, or
        #: the frame came in a block). The skeleton's segment outputs read it
        #: (:mod:`jointfit_core.segment_frames`).
        self.frame_poses: tuple[FloatArray, FloatArray, tuple[bool, bool]] | None = None
        self._serial: SerialInflation | None = None
        self._statistical: PoseSumsCentre | PoseSumsAxis | None = None
        self._artefact_scale = 0.0
        self._white_sigma: tuple[float, float] | None = None
        self._matched: FloatArray | None = None  # hinge: point_child_matched (joint_file.matched_child_point)
        # Frames are numbered as they arrive, and their stamps checked (FrameClock; the clock of the outlier
        # gate's turn test and of its limits' refresh). The gate's limits are cached (GateLimits); each
        # segment's memory is in its tracker.
        self._clock = FrameClock(self.spec)
        self._limits = GateLimits(self.gate, self._noise_arg)
        # The joint-consistency test (jointfit_core.joint_gate): frames whose segments break the joint.
        self._joint = JointTrack(self.gate)
        self.joint_gated_frames = 0
        self._pose: SegmentPair | None = None  # the two segments, from the first frame (or fixed templates)
        self._outputs = WorldOutput(self.kind)
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
    def frozen(self) -> bool:
        """Whether the estimate is frozen (per-frame outputs continue, statistics do not)."""
        return self._frozen

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
    def statistics(self) -> RelativePoseSums:
        """The joint's window of relative-pose sums (:class:`~jointfit_core.joint_sums.RelativePoseSums`)."""
        return self._stats

    @property
    def n_window(self) -> int:
        """Frames in the window (frames added, under forgetting)."""
        return 0 if self._stats.window is None else self._stats.window.n_window

    @property
    def length_scale(self) -> float:
        """The larger rms radius of the two templates (input units; 0 until they exist)."""
        if not self.templates_ready:
            return 0.0
        assert self._pose is not None
        return max(self._pose.parent.rms_radius, self._pose.child.rms_radius)

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
    def noise_std(self) -> tuple[float, float]:
        """Marker noise estimates (parent, child) used by the latest estimate, input units.

        The pooled pose-fit residual: on skin markers it holds the clusters' deformation too
        (the covariance's pose-noise part and the outlier gate use it as such); their white
        noise alone is :attr:`white_noise_std`.
        """
        return self._sigma

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

    @property
    def white_noise_std(self) -> tuple[float, float] | None:
        """Skin markers: the white marker noise (parent, child) of the latest estimate, input units.

        Read from the second differences of the pose-fit residuals
        (:mod:`~jointfit_core.white_noise_sums`); what a ball joint's bias compensation used.
        None for rigid markers and before an estimate.
        """
        return self._white_sigma

    @property
    def solution(self) -> PoseSumsCentre | PoseSumsAxis | None:
        """The latest estimate, without solving again (None before the first)."""
        return self._solution

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

    def set_reference_direction(self, direction: ArrayLike) -> None:
        """Set the hinge sign convention (a direction in the parent local frame); the next estimate follows it."""
        self.reference_direction = check_vector3(direction, name="reference_direction", unit=True)
        self._version += 1
        self._generation = next(_GENERATIONS)  # a solve under way has the old convention

    def _make_segments(self, n_parent: int, n_child: int) -> None:
        self.n_markers = (n_parent, n_child)
        self._pose = SegmentPair(n_parent, n_child, self.template_frames)

    def _drop(self, reason: str) -> None:
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
            if yp.shape[0] < MIN_POSE_MARKERS or yc.shape[0] < MIN_POSE_MARKERS:
                raise InputError(
                    f"parent, child: expected at least {MIN_POSE_MARKERS} markers per segment, got "
                    f"{yp.shape[0]} and {yc.shape[0]}"
                )
            self._make_segments(yp.shape[0], yc.shape[0])
        pose = self._pose
        assert pose is not None
        self.n_frames_seen += 1

        if not self.templates_ready:
            pose.parent.add_template_frame(yp)
            pose.child.add_template_frame(yc)
            self._pending.append((yp.copy(), yc.copy(), st, number))
            if len(self._pending) > 20 * self.template_frames:
                self._pending.pop(0)
                self._drop("before_templates")
            if self.templates_ready:
                pending, self._pending = self._pending, []
                for p_frame, c_frame, p_stamp, p_number in pending:
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
            if self._joint_fails(R, d, frame_no, stamp):
                self._stats.chained = False
                self.frame_poses = None  # one of the two poses is wrong, which one is not known
                return None
        if ps.parent is not None and ps.child is not None and not self._frozen:
            self._stats.add_frame(R, d, ss, ps, stamp, frame_no, Y)
            self._version += 1
        else:
            self._stats.chained = False
        if ps.parent is None or self._solution is None:
            return None
        child_pose = (R[1], d[1], ps.child) if ps.child is not None else None
        return self._outputs.output(self._solution, self._sigma, R[0], d[0], ps.parent, child_pose)

    def _joint_fails(self, R: FloatArray, d: FloatArray, frame_no: int, stamp: float | None) -> bool:
        """The joint test (:mod:`jointfit_core.joint_gate`) of a frame posed ``R`` (2, 3, 3), ``d`` (2, 3); counts a failure."""
        z = np.empty((3, 4))
        Rp_t = R[0].T
        np.matmul(Rp_t, R[1], out=z[:, :3])
        np.matmul(Rp_t, d[1] - d[0], out=z[:, 3])
        score, e = self._joint.score_one(z, frame_no)
        if self._joint.fails(score):
            self.joint_gated_frames += 1
            self._drop("joint_gated")
            if self.gate_log is not None:
                self.gate_log.append((frame_no, 2, np.nan if stamp is None else stamp))
            return True
        self._joint.pass_one(z, frame_no, score, e, self._frozen)
        return False

    # ------------------------------------------------------------------ estimates

    def pose_sums(self) -> tuple[PoseSums, FloatArray, FloatArray, float, float]:
        """The window's sums: ``(PoseSums, mean unit W_p (6, 6), mean unit W_c (6, 6), sigma_p, sigma_c)``.

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        return unpack_pose_sums(self._entered_sums())

    def lag_sums(self) -> LagSums:
        """The window's lag-pair sums (:class:`~jointfit_core.serial.LagSums`; see the class Notes).

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        return self._stats.lag_sums(self.status())

    def time_lag_sums(self) -> TimeLagSums:
        """The window's lag-pair sums at lags in seconds (:class:`~jointfit_core.serial.TimeLagSums`).

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        return self._stats.time_lag_sums(self.status())

    def sums_vector(self) -> FloatArray | None:
        """A copy of the window's sums vector (the layout :meth:`request_for` takes); None before any frame entered."""
        window = self._stats.window
        if window is None or window.sums[0] <= 0.0:
            return None
        return window.sums.copy()

    def window_contributions(self) -> tuple[FloatArray, FloatArray] | None:
        """Each frame's contribution to the window's sums, oldest first, and its stamp.

        Returns
        -------
        (ndarray, shape (n, n_sums), ndarray, shape (n,)) or None
            The rows sum to :meth:`sums_vector`; stamps in seconds (NaN when
            not stamped). None for exponential forgetting (which keeps no
            frames) and before any frame entered.
        """
        window = self._stats.window
        if window is None or window.spec.exponential or window.n_window == 0:
            return None
        return window.window_records(), window.window_stamps()

    @property
    def solved_version(self) -> tuple[int, int]:
        """``(generation, version)`` of the window the current estimate was solved from (changes with every solve)."""
        return self._generation, self._solved_version

    def _entered_sums(self) -> FloatArray:
        """The window's sums vector; InputError when no frame has entered the statistics yet."""
        return self._stats.entered(self.status())

    @property
    def movement_seconds(self) -> float:
        """Seconds of movement in the window (weighted, with forgetting): frames whose relative rotation turned by more than :data:`~jointfit_core.joint_sums.MOVING_DEG` in 0.32 s.

        Skin estimates are identifiable from :data:`SKIN_MIN_MOVEMENT_S` on (see
        :func:`~jointfit_core.joint_sums.moving_seconds`).
        """
        return self._stats.movement_seconds

    @property
    def serial_inflation(self) -> SerialInflation | None:
        """The lag-1 correlation of the latest estimate's residual and the factor applied to its covariances.

        None before the first estimate and after :meth:`from_dict` of a
        calibration saved without it.
        """
        return self._serial

    @property
    def statistical_solution(self) -> PoseSumsCentre | PoseSumsAxis | None:
        """Skin markers: the latest estimate with its statistical covariances only (without the soft-tissue part).

        None for rigid markers (:meth:`estimate`'s covariances are then the
        statistical ones), before the first estimate and after :meth:`from_dict`.
        """
        return self._statistical

    @property
    def artefact_scale(self) -> float:
        """The soft-tissue prior's scale at the latest estimate (input units per radian; 0 for rigid markers)."""
        return self._artefact_scale

    def estimate(self) -> PoseSumsCentre | PoseSumsAxis:
        """Solve the window's sums (or return the frozen or still current estimate).

        Returns
        -------
        PoseSumsCentre or PoseSumsAxis
            For ``kind`` "ball" and "hinge"; local frames are the templates'.
            Covariances include the serial-correlation factor
            (:attr:`serial_inflation`; see the class Notes).

        Raises
        ------
        InputError
            Fewer than 3 frames in the statistics.
        NotIdentifiableError
            The window's motion cannot determine the joint at all.

        Notes
        -----
        ``install(solve_window(solve_request()))``: the same steps as a solve in
        another process (:meth:`solve_request`, :func:`solve_window`, :meth:`install`).
        """
        request = self.solve_request()
        if request is not None:
            self._install(solve_window(request))
        assert self._solution is not None
        return self._solution

    def solve_request(self) -> SolveRequest | None:
        """A snapshot of the window for :func:`solve_window`; None when the estimate is current.

        The estimate is current when frozen, or when no frame has entered the
        statistics since it was solved. The request holds copies, so the
        estimator takes further frames while it is solved elsewhere.

        Raises
        ------
        InputError
            No frame has entered the statistics yet.
        """
        if self._solution is not None and (self._frozen or self._version == self._solved_version):
            return None
        return self.request_for(self._entered_sums().copy())

    def request_for(self, sums: FloatArray) -> SolveRequest:
        """A :class:`SolveRequest` of this estimator's settings for other sums (e.g. one block of the window).

        Parameters
        ----------
        sums : ndarray, shape (n_sums,)
            A sums vector in the estimator's layout: a sum of rows of
            :meth:`window_contributions`, or a difference of :meth:`sums_vector`
            snapshots of a window that forgets nothing.
        """
        return SolveRequest(
            kind=self.kind,
            sums=np.asarray(sums, dtype=np.float64),
            noise_std=self._noise_arg,
            length_scale=self.length_scale,
            reference_direction=self.reference_direction,
            serial_correlation=self.serial_correlation,
            generation=self._generation,
            version=self._version,
            attachment=self.attachment,
            radii=self._radii(),
        )

    def _radii(self) -> tuple[float, float]:
        if not self.templates_ready:
            return (0.0, 0.0)
        assert self._pose is not None
        return (self._pose.parent.rms_radius, self._pose.child.rms_radius)

    def is_current(self, request: SolveRequest) -> bool:
        """Whether a :meth:`solve_request` was made in the state the estimator is in now.

        False after a reset, a freeze or a new hinge sign convention: the answer
        to it, a result or an error, is about a window that is gone.
        """
        return request.generation == self._generation and not self._frozen

    def install(self, result: SolveResult) -> bool:
        """Make a :func:`solve_window` result of an earlier :meth:`solve_request` the estimate.

        Returns False (and changes nothing) when the result is stale: the
        estimator was reset or frozen since the request, its hinge sign
        convention changed, or the estimate is already as recent.
        """
        if result.generation != self._generation or self._frozen:
            return False
        if self._solution is not None and result.version <= self._solved_version:
            return False
        self._install(result)
        return True

    def _install(self, result: SolveResult) -> None:
        self._solution = result.solution
        self._sigma = result.noise_std
        self._serial = result.serial
        self._statistical = result.statistical
        self._artefact_scale = result.artefact_scale
        self._white_sigma = result.white_noise_std
        self._solved_version = result.version
        self._outputs.clear()
        self._joint.arm(self._solution, self.length_scale)

    # ------------------------------------------------------------------ calibration

    def freeze(self) -> PoseSumsCentre | PoseSumsAxis:
        """Fix the current estimate; per-frame outputs continue, the statistics stop.

        Raises
        ------
        InputError, NotIdentifiableError
            No estimate can be made yet.
        """
        sol = self.estimate()
        self._frozen = True
        return sol

    def thaw(self) -> None:
        """Resume updating the statistics (the window holds the frames from before freezing)."""
        self._frozen = False

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
