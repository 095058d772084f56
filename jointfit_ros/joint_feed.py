"""One joint's estimator and the frames that feed it: its per-frame path, its outputs and its solves.

Pure Python and numpy (no rclpy). :class:`JointFeed` is the part of a
:class:`~jointfit_ros.runner.JointRunner` that a frame passes through: it
takes the node's marker frames (one by one or as a block) and segment poses
(as virtual markers, paired by stamp), screens absurd markers
(:mod:`jointfit_ros.absurd_values`), gives them to its
:class:`~jointfit_core.estimator.OnlineJoint`, and returns the world output
when it may go out (identifiable or ``publish_unidentified``, hinge sign
chosen (:mod:`jointfit_ros.axis_convention`), finite and within the
workspace), counting what it drops. While a restored calibration is compared
with the first live frames (:mod:`jointfit_ros.joint_calibration`) it does
that too. It keeps the window solved every ``estimate_period``, here or in
another process. What the node does with a joint besides (restoring and
saving its calibration, reset, freeze, ``/diagnostics``) is the runner's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from jointfit_core.errors import InputError, JointfitError, NotIdentifiableError
from jointfit_core.estimator import (
    JointOutput,
    OnlineJoint,
    SolveRequest,
    SolveResult,
    virtual_markers_template,
)
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.segments import AXIS_SD_MAX_DEG, SD_REL_MAX, PoseSumsCentre

from .absurd_values import ABSURD_OUTPUT, ABSURD_RADII, MarkerScreen, output_sane, workspace_limit
from .axis_convention import AxisConvention
from .joint_calibration import JointCalibration
from .live_geometry import LiveGeometry
from .params import JointConfig, NodeConfig
from .sync import StampMatcher

__all__ = ["JointFeed", "widened_output"]

FloatArray = NDArray[np.float64]

#: Input stamps kept to measure the input rate.
_RATE_SAMPLES = 200

#: The feed's counters (see :class:`JointFeed`).
_COUNTERS = (
    "frames", "outputs", "malformed", "unmatched", "estimate_failures", "absurd_markers", "absurd_outputs",
    "withheld_unidentified", "withheld_unsigned",
)


def _lever(sol: PoseSumsCentre | PoseSumsAxis) -> float:
    """The estimate's distance from the template centroids (input units)."""
    if isinstance(sol, PoseSumsCentre):
        return float(max(np.linalg.norm(sol.centre_parent), np.linalg.norm(sol.centre_child)))
    return float(max(np.linalg.norm(sol.point_parent), np.linalg.norm(sol.point_child)))


def widened_output(out: JointOutput, lever: float) -> JointOutput:
    """A not-identifiable estimate's output with a covariance that covers what the motion left undetermined.

    The position covariance gets at least the identifiability limit
    (:data:`~jointfit_core.segments.SD_REL_MAX` of the lever arm) in every
    direction and a whole lever arm along its least-determined direction
    (a joint moved about one axis is anywhere along it, within the segment);
    a hinge direction gets at least
    :data:`~jointfit_core.segments.AXIS_SD_MAX_DEG` about both perpendicular axes.
    The estimate itself is unchanged.
    """
    cov = out.cov
    finite = bool(np.isfinite(cov).all())
    v = np.linalg.eigh(cov)[1][:, -1] if finite else np.zeros(3)
    cov = cov + (SD_REL_MAX * lever) ** 2 * np.eye(3) + lever**2 * np.outer(v, v)
    cov_direction = out.cov_direction
    if out.direction is not None and cov_direction is not None:
        d = out.direction
        cov_direction = cov_direction + np.radians(AXIS_SD_MAX_DEG) ** 2 * (np.eye(3) - np.outer(d, d))
    return replace(out, cov=cov, cov_direction=cov_direction)


class JointFeed:
    """Feed one joint's estimator from the node's inputs, give its outputs and keep it solved.

    Parameters
    ----------
    cfg : JointConfig
        This joint's parameters.
    node : NodeConfig
        The node's parameters (marker names, estimate period, sync tolerance).

    Attributes
    ----------
    estimator : OnlineJoint
    counters : dict of str to int
        ``frames`` (inputs given to the estimator), ``outputs``,
        ``malformed`` (inputs rejected with an error), ``unmatched`` (pose
        inputs without a partner), ``estimate_failures``.
    last_error : str
        The latest problem in words (empty when none).
    calib : JointCalibration
        Where its calibration came from, why one was refused, its per-joint file.
    sign : AxisConvention
        Which way its hinge axis points (chosen once by ``axis_toward_marker``).
    """

    def __init__(self, cfg: JointConfig, node: NodeConfig) -> None:
        self.cfg = cfg
        self.node = node
        self.parent_rows = np.array([node.marker_index(m) for m in cfg.parent_markers], dtype=np.intp)
        self.child_rows = np.array([node.marker_index(m) for m in cfg.child_markers], dtype=np.intp)
        self.uses_marker_topic = bool(cfg.parent_markers or cfg.child_markers)
        self.chained = bool(cfg.parent_chain or cfg.child_chain)
        #: Both segments are marker clusters of the marker topic (no pose topic, no chained joint): the
        #: estimator poses them from the node's frames (live geometry, ``~/segments``).
        self.poses_both_segments = bool(len(self.parent_rows) and len(self.child_rows)) and not self.chained
        self.matcher: StampMatcher | None = None
        self._virtual: FloatArray | None = None
        templates: tuple[FloatArray | None, FloatArray | None] = (None, None)
        noise: tuple[float | None, float | None] = (None, None)
        if cfg.parent_pose_topic or cfg.child_pose_topic:
            self.matcher = StampMatcher(tolerance_ns=round(node.sync_tolerance * 1e9))
            virtual, sigma = virtual_markers_template(cfg.pose_translation_sd, math.radians(cfg.pose_rotation_sd_deg))
            self._virtual = virtual
            templates = (virtual if cfg.parent_pose_topic else None, virtual if cfg.child_pose_topic else None)
            noise = (sigma if cfg.parent_pose_topic else None, sigma if cfg.child_pose_topic else None)
        self._template_args = templates
        self._noise_args = noise
        self.counters = dict.fromkeys(_COUNTERS, 0)
        self.last_error = ""
        #: A chained joint: the frames in a row, up to the latest, without an output while some of its chain
        #: joints had none (:attr:`chain_missing`); what its status blames (its own markers are not the cause).
        self.chain_silent = 0
        #: The chain joints without an output in the latest frame this joint gave none (a chained joint).
        self.chain_missing: tuple[str, ...] = ()
        self.calib = JointCalibration(cfg)
        self._stamps: deque[float] = deque(maxlen=_RATE_SAMPLES)
        #: The latest frame's live-geometry offer left for :meth:`take_sample` (``defer_sample``): (stamp s, frame).
        self._sample: tuple[float, FloatArray] | None = None
        self._last_solve = -math.inf
        #: The absurd-marker test of the two clusters (:meth:`_in_workspace`).
        self.screen = MarkerScreen(self.parent_rows, self.child_rows)
        self.sign = AxisConvention(cfg, node, self.screen.cluster_rows)
        self._limit_node: NodeConfig | None = None
        self._limit = math.inf
        self.estimator = self._new_estimator()
        #: Sampled recent frames for the anatomical results and range of motion in ``/diagnostics``
        #: (marker joints of the marker topic, not chained; else None).
        self.live_geometry: LiveGeometry | None = None
        if self.poses_both_segments:
            rows = {m: node.marker_index(m) for _, m in cfg.anatomical}
            self.live_geometry = LiveGeometry(cfg, rows, self.parent_rows, self.child_rows)

    # ------------------------------------------------------------------ set-up

    def _new_estimator(self) -> OnlineJoint:
        """The joint's estimator as configured, without frames (a pose topic's virtual markers are its template)."""
        return OnlineJoint(
            self.cfg.type,
            template_frames=self.cfg.template_frames,
            gate=self.cfg.outlier_gate,
            attachment=self.cfg.attachment,
            templates=self._template_args,
            noise_std=self._noise_args,
            # 4 virtual markers for poses; chain joints add one point each
            n_markers=(
                (len(self.parent_rows) + len(self.cfg.parent_chain)) or 4,
                (len(self.child_rows) + len(self.cfg.child_chain)) or 4,
            ),
            window_max_frames=self.cfg.window_max_frames,
            **self.cfg.window_kwargs(),
        )

    def _estimate_anew(self) -> None:
        """The restored calibration was discarded (:meth:`JointCalibration.layout_differs`): a new estimator."""
        self.estimator = self._new_estimator()
        self.sign.unchoose()
        self.last_error = self.calib.load_problem

    # ------------------------------------------------------------------ inputs

    def markers_frame(
        self,
        stamp_ns: int,
        frame: FloatArray,
        chain: dict[str, FloatArray] | None = None,
        *,
        defer_sample: bool = False,
    ) -> JointOutput | None:
        """A frame of all configured markers (P, 3) from the marker topic.

        ``chain`` maps earlier joints' names to this frame's world output
        position (a virtual marker for ``parent_chain`` / ``child_chain``;
        missing when that joint has no output in this frame).
        ``defer_sample``: the frame's live-geometry sample (bookkeeping that
        does not change the output) is left for :meth:`take_sample`, so that
        the caller publishes the output first.
        """
        self._sample = None  # (a sample not taken before the next frame is dropped: its poses are gone)
        frame = self._in_workspace(frame)
        if self.chained:
            chain = chain or {}
            parent = self._with_chain(frame[self.parent_rows], self.cfg.parent_chain, chain)
            child = self._with_chain(frame[self.child_rows], self.cfg.child_chain, chain)
            out = self.process(stamp_ns, parent, child, frame)
            if out is None:  # (the common case, an output, needs no look at the chain)
                self.chain_missing = tuple(n for n in (*self.cfg.parent_chain, *self.cfg.child_chain) if n not in chain)
            self.chain_silent = self.chain_silent + 1 if out is None and self.chain_missing else 0
            return out
        if self.matcher is None:
            out = self.process(stamp_ns, frame[self.parent_rows], frame[self.child_rows], frame)
            if self.live_geometry is not None:
                self._sample = (stamp_ns * 1e-9, frame)
                if not defer_sample:
                    self.take_sample()
            return out
        if self.cfg.parent_markers:
            return self._paired(0, stamp_ns, frame[self.parent_rows], frame)
        return self._paired(1, stamp_ns, frame[self.child_rows], frame)

    def take_sample(self) -> None:
        """Offer the latest :meth:`markers_frame` frame to the live geometry, when it was deferred (else nothing).

        Uses the estimator's poses of that frame, so it must come before the next frame.
        """
        pending, self._sample = self._sample, None
        if pending is not None and self.live_geometry is not None:
            est = self.estimator
            self.live_geometry.offer_one(pending[0], pending[1], est.templates, est.frame_poses)

    def markers_block(self, stamps_ns: NDArray[np.int64], frames: FloatArray) -> None:
        """Frames of all configured markers (K, P, 3) from the marker topic, oldest first, without outputs.

        The estimator's and the runner's state (counters, input-rate stamps,
        hinge sign) end up as after :meth:`markers_frame` of each frame; the
        frames go to :meth:`OnlineJoint.update_many
        <jointfit_core.estimator.OnlineJoint.update_many>` as one block.

        Notes
        -----
        Per frame only where the sequential path needs the per-frame
        output or check: a loaded calibration's templates are compared with
        the first fully visible frames (:meth:`JointCalibration.layout_differs`); the hinge
        sign (``axis_toward_marker``) is fixed on the first output after
        the first estimate, so while it is not fixed and
        an estimate exists, frames go through :meth:`process` one by one
        until it is. ``outputs`` counts the frames that would have had one
        (an estimate exists and the parent was posed). A block the
        estimator refuses (:class:`~jointfit_core.errors.InputError`: it
        adds nothing then) is given frame by frame, so that the bad frames
        are counted as ``malformed`` as :meth:`process` counts them. Joints
        that pair the frames with a pose topic take them one by one.
        """
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        n = stamps_ns.shape[0]
        self._sample = None
        frames = self._in_workspace(frames)
        if self.matcher is not None:
            for k in range(n):
                self.markers_frame(int(stamps_ns[k]), frames[k])
            return
        parent, child = frames[:, self.parent_rows], frames[:, self.child_rows]
        k = 0
        while k < n and self.calib.checking_layout:  # a loaded calibration: compared with the live markers first
            self.process(int(stamps_ns[k]), parent[k], child[k], frames[k])
            k += 1
        est = self.estimator  # (a new one when the loaded calibration was discarded)
        while k < n and not self.sign.fixed and est.solution is not None and est.solution.identifiable:
            self.process(int(stamps_ns[k]), parent[k], child[k], frames[k])
            k += 1
        if k == n:
            return
        stamps = stamps_ns[k:] * 1e-9
        seen, not_posed = est.n_frames_seen, est.dropped.get("parent_not_posed", 0)
        with_outputs = est.solution is not None
        try:
            est.update_many(parent[k:], child[k:], stamps)
        except InputError:
            for j in range(k, n):
                self.process(int(stamps_ns[j]), parent[j], child[j], frames[j])
            return
        self.counters["frames"] += n - k
        self._stamps.extend(stamps[-_RATE_SAMPLES:].tolist())
        if self.live_geometry is not None:
            self.live_geometry.offer(np.asarray(stamps, dtype=np.float64), frames[k:], est.templates)
        if with_outputs:
            posed = (est.n_frames_seen - seen) - (est.dropped.get("parent_not_posed", 0) - not_posed)
            self.counters["outputs" if self._publishable() else "withheld_unidentified"] += posed

    def _in_workspace(self, frames: FloatArray) -> FloatArray:
        """``frames`` (..., P, 3) with absurd markers set missing (a copy when any is); counted.

        Absurd (:meth:`MarkerScreen.screened <jointfit_ros.absurd_values.MarkerScreen.screened>`):
        a coordinate beyond the ``workspace`` (when set), or a marker farther
        from its segment's visible markers' mean than
        :data:`~jointfit_ros.absurd_values.ABSURD_RADII` times the larger
        template's rms radius (once the templates exist).
        """
        frames, n = self.screen.screened(frames, self._workspace_limit(), ABSURD_RADII * self.estimator.length_scale)
        if n:
            self.counters["absurd_markers"] += n
            self.last_error = (
                f"{n} absurd marker position(s) (beyond the workspace or far outside their segment) "
                "treated as missing"
            )
        return frames

    def _workspace_limit(self) -> float:
        """:func:`workspace_limit` of the node's configuration (kept while :attr:`node` is the same object)."""
        if self._limit_node is not self.node:
            self._limit_node, self._limit = self.node, workspace_limit(self.node)
        return self._limit

    @staticmethod
    def _with_chain(markers: FloatArray, names: tuple[str, ...], chain: dict[str, FloatArray]) -> FloatArray:
        if not names:
            return markers
        nan = np.full(3, np.nan)
        return np.concatenate([markers, np.stack([chain.get(n, nan) for n in names])])

    def pose(self, source: int, stamp_ns: int, R: FloatArray, d: FloatArray) -> JointOutput | None:
        """A rigid-body pose of the parent (``source`` 0) or the child (1), as virtual markers.

        A position beyond the workspace (without one: beyond :data:`~jointfit_ros.absurd_values.ABSURD_OUTPUT`
        input units, as the outputs) is dropped and counted: a finite 1e299 from a driver entered the
        window's sums as inf, and the joint stayed without an estimate until it left the window.
        """
        assert self._virtual is not None
        limit = workspace_limit(self.node)
        if not np.abs(d).max() <= (limit if math.isfinite(limit) else ABSURD_OUTPUT):
            self.counters["absurd_markers"] += 1
            self.last_error = f"pose dropped: position {d.tolist()} beyond the workspace (or absurd without one)"
            return None
        return self._paired(source, stamp_ns, self._virtual @ R.T + d, None)

    def _paired(self, source: int, stamp_ns: int, points: FloatArray, frame: FloatArray | None) -> JointOutput | None:
        assert self.matcher is not None
        before = self.matcher.unmatched
        pair = self.matcher.add(source, stamp_ns, (points, frame))
        self.counters["unmatched"] += self.matcher.unmatched - before
        if pair is None:
            return None
        stamp, (parent, frame_p), (child, frame_c) = pair
        return self.process(stamp, parent, child, frame_p if frame_p is not None else frame_c)

    def process(
        self, stamp_ns: int, parent: FloatArray, child: FloatArray, frame: FloatArray | None = None
    ) -> JointOutput | None:
        """Give one frame to the estimator; return its world output (None when there is none).

        Never raises on bad data: malformed frames are counted and described in
        :attr:`last_error`.
        """
        stamp = stamp_ns * 1e-9
        if self.calib.checking_layout and self.calib.layout_differs(parent, child, self.estimator):
            self._estimate_anew()
        try:
            out = self.estimator.update(parent, child, stamp)
        except InputError as exc:
            self.counters["malformed"] += 1
            self.last_error = f"frame dropped: {exc}"
            return None
        self.counters["frames"] += 1
        self._stamps.append(stamp)
        if out is None:
            return None
        if not self._publishable():
            self.counters["withheld_unidentified"] += 1
            return None
        if not self.sign.fixed and frame is not None:
            out, resolve = self.sign.choose(out, frame, self.estimator)
            if resolve:  # the sign is chosen: the window is solved with it now
                self.estimate(force=True)
            if not self.sign.fixed:  # a configured sign convention not honoured yet: no axis pointing either way
                self.counters["withheld_unsigned"] += 1
                return None
        sol = self.estimator.solution
        if sol is not None and not sol.identifiable:
            out = widened_output(out, max(self.estimator.length_scale, _lever(sol)))
        if not output_sane(out, self._workspace_limit()):
            self.counters["absurd_outputs"] += 1
            self.last_error = f"output withheld: non-finite or beyond the workspace (position {out.position.tolist()})"
            return None
        self.counters["outputs"] += 1
        return out

    def _publishable(self) -> bool:
        """Whether per-frame outputs go out: the estimate is identifiable, or ``publish_unidentified``."""
        sol = self.estimator.solution
        return sol is not None and (sol.identifiable or self.cfg.publish_unidentified)

    def input_rate(self) -> float:
        """Frames per second over the last frames given to the estimator (0 when fewer than 2)."""
        if len(self._stamps) < 2 or self._stamps[-1] <= self._stamps[0]:
            return 0.0
        return (len(self._stamps) - 1) / (self._stamps[-1] - self._stamps[0])

    # ------------------------------------------------------------------ estimates

    def estimate(self, now: float | None = None, *, force: bool = False) -> bool:
        """Re-solve the window when ``estimate_period`` has passed (``now`` in seconds, monotonic).

        Returns True when the estimate is current (solved now, or no frame since the last solve).
        Failures are counted and described.
        """
        if not self._due(now, force):
            return False
        try:
            self.estimator.estimate()
        except (NotIdentifiableError, InputError) as exc:
            self._failed(exc)
            return False
        return True

    def solve_request(self, now: float | None = None, *, force: bool = False) -> SolveRequest | None:
        """:meth:`estimate` in two halves, for a solve in another process: the window's snapshot.

        None when no solve is due or needed (see :meth:`estimate`); give the
        :func:`~jointfit_core.estimator.solve_window` result (or the error it raised) to :meth:`install`.
        """
        if not self._due(now, force):
            return None
        try:
            return self.estimator.solve_request()
        except InputError as exc:
            self._failed(exc)
            return None

    def install(self, result: SolveResult | JointfitError, request: SolveRequest | None = None) -> bool:
        """Make a solve's result the estimate (False when stale: see :meth:`OnlineJoint.install`); count an error.

        ``request``: the request answered; an error about a window that is gone
        (:meth:`OnlineJoint.is_current <jointfit_core.estimator.OnlineJoint.is_current>`:
        reset or frozen since) is dropped, not counted against the estimator there is now.
        """
        if isinstance(result, JointfitError):
            if request is not None and not self.estimator.is_current(request):
                return False
            self._failed(result)
            return False
        return self.estimator.install(result)

    def _due(self, now: float | None, force: bool) -> bool:
        if not force and now is not None and now - self._last_solve < self.node.estimate_period:
            return False
        if now is not None:
            self._last_solve = now
        return not (self.estimator.frozen or not self.estimator.templates_ready or self.estimator.n_window < 3)

    def waiting(self) -> str:
        """What the estimator waits for, in words (empty when estimating); a chained joint names its chain.

        A chained joint's segments hold the earlier joints' outputs as markers
        (``parent_chain``, ``child_chain``): while those have no estimate, the
        segments are never fully visible and the templates wait for them.
        """
        text = self.estimator.status()
        unseen = self._rarely_seen()
        if text and unseen:
            text += (
                f"; {', '.join(unseen)} missing from nearly every frame so far: a template needs frames with every "
                "marker of its segment visible (if a marker is gone for good, leave it out of the segment's markers)"
            )
        chain = (*self.cfg.parent_chain, *self.cfg.child_chain)
        if text and chain and not self.estimator.templates_ready:
            text += (
                f" (its segments hold the per-frame outputs of {', '.join(chain)} as markers: while "
                f"{'that joint has' if len(chain) == 1 else 'those joints have'} no output, they are never fully visible)"
            )
        return text

    def _rarely_seen(self) -> list[str]:
        """The names of the markers that hold the templates back (:meth:`OnlineJoint.rarely_seen`)."""
        names: list[str] = []
        for rows, markers in zip(
            self.estimator.rarely_seen(),
            ((*self.cfg.parent_markers, *self.cfg.parent_chain), (*self.cfg.child_markers, *self.cfg.child_chain)),
            strict=True,
        ):
            names.extend(markers[i] if i < len(markers) else f"marker {i + 1}" for i in rows)
        return names

    def _failed(self, exc: Exception) -> None:
        self.counters["estimate_failures"] += 1
        self.last_error = f"no estimate: {exc}"

    def reset(self) -> None:
        """Forget the window, templates, estimate, counters and chosen hinge sign (the calibration file is untouched)."""
        self.estimator = self._new_estimator()
        self._sample = None
        self.sign.reset()
        self.calib.forget()
        if self.matcher is not None:
            self.matcher.clear()
        for key in self.counters:
            self.counters[key] = 0
        self.last_error = ""
        self.chain_silent = 0
        self.chain_missing = ()
