"""One joint of the node: routing frames to its estimator, timing, diagnostics, calibration file.

Pure Python and numpy (no rclpy), so that the node's behaviour per joint is
tested without ROS: :class:`JointRunner` takes marker frames (or segment
poses, as virtual markers), keeps its :class:`~jointfit_core.estimator.OnlineJoint`
solved every ``estimate_period``, fixes the hinge sign, counts what it
drops, summarises its state for ``/diagnostics`` and saves and loads its
calibration.
"""

from __future__ import annotations

import math
import shutil
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.calibration import load_calibration, save_calibration
from jointfit_core.errors import InputError, JointfitError, NotIdentifiableError
from jointfit_core.estimator import (
    JointOutput,
    OnlineJoint,
    SolveRequest,
    SolveResult,
    virtual_markers_template,
)
from jointfit_core.gate import gated_verdict
from jointfit_core.hinge_from_sums import PoseSumsAxis
from jointfit_core.segments import PoseSumsCentre

from .params import JointConfig, NodeConfig
from .sync import StampMatcher

__all__ = ["JointRunner", "Status", "OK", "WARN", "ERROR", "STALE"]

FloatArray = NDArray[np.float64]

#: diagnostic_msgs/DiagnosticStatus levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3

#: Input stamps kept to measure the input rate.
_RATE_SAMPLES = 200

#: Metres per unit of the ``units`` parameter.
_METRES = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: Plausible rms radius of a segment's marker cluster (or virtual markers), metres.
CLUSTER_RADIUS_M = (0.003, 1.0)


def unit_problem(rms_radius: float, units: str) -> str:
    """Why a cluster's rms radius (input units) is implausible for ``units``; empty when plausible.

    A mocap stream in millimetres sent to a node configured for metres (or the
    reverse) gives clusters 1000 times too large (small): the estimates are then
    in the wrong unit for every consumer, and the noise settings are off.
    """
    if not rms_radius > 0.0 or units not in _METRES:
        return ""
    metres = rms_radius * _METRES[units]
    low, high = CLUSTER_RADIUS_M
    if low <= metres <= high:
        return ""
    guess = min(_METRES, key=lambda u: abs(np.log10(rms_radius * _METRES[u] / 0.05)))
    return (
        f"marker clusters are {rms_radius:.3g} {units} in rms radius, implausible for units '{units}' "
        f"(expected {low:g}-{high:g} m): the stream looks like {guess}; check the driver's units or set units"
    )


@dataclass(frozen=True)
class Status:
    """A joint's state for ``/diagnostics``: level, one-line message and key/values."""

    level: int
    message: str
    values: dict[str, Any]


def _spread_deg(deficit: float) -> float:
    return float(np.rad2deg(np.sqrt(2.0 * max(deficit, 0.0))))


class JointRunner:
    """Feed one joint's estimator from the node's inputs and report on it.

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
    """

    def __init__(self, cfg: JointConfig, node: NodeConfig) -> None:
        self.cfg = cfg
        self.node = node
        self.parent_rows = np.array([node.marker_index(m) for m in cfg.parent_markers], dtype=np.intp)
        self.child_rows = np.array([node.marker_index(m) for m in cfg.child_markers], dtype=np.intp)
        self.uses_marker_topic = bool(cfg.parent_markers or cfg.child_markers)
        self.chained = bool(cfg.parent_chain or cfg.child_chain)
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
        self.counters = {"frames": 0, "outputs": 0, "malformed": 0, "unmatched": 0, "estimate_failures": 0}
        self.last_error = ""
        self.loaded_from: str = ""
        self._unloadable = False  # the configured file exists but could not be loaded: keep it on save
        self._stamps: deque[float] = deque(maxlen=_RATE_SAMPLES)
        self._last_solve = -math.inf
        self._sign_fixed = not cfg.axis_toward_marker
        self._toward_row = node.marker_index(cfg.axis_toward_marker) if cfg.axis_toward_marker else -1
        self.estimator = self._new_estimator()
        self._load()

    # ------------------------------------------------------------------ set-up

    def _new_estimator(self) -> OnlineJoint:
        return OnlineJoint(
            self.cfg.type,
            template_frames=self.cfg.template_frames,
            gate=self.cfg.outlier_gate,
            templates=self._template_args,
            noise_std=self._noise_args,
            # 4 virtual markers for poses; chain joints add one point each
            n_markers=(
                (len(self.parent_rows) + len(self.cfg.parent_chain)) or 4,
                (len(self.child_rows) + len(self.cfg.child_chain)) or 4,
            ),
            **self.cfg.window_kwargs(),
        )

    @property
    def calibration_path(self) -> Path | None:
        """The calibration file with ``~`` expanded (None when not configured)."""
        return Path(self.cfg.calibration_file).expanduser() if self.cfg.calibration_file else None

    def _load(self) -> None:
        path = self.calibration_path
        if path is None or not path.exists():
            return
        try:
            est = OnlineJoint.from_dict(load_calibration(path))
        except (InputError, OSError) as exc:
            self.last_error = f"calibration file {path} not loaded (kept as it is): {exc}"
            self._unloadable = True
            return
        if est.kind != self.cfg.type:
            self.last_error = (
                f"calibration file {path} not loaded (kept as it is): it holds a {est.kind} joint, "
                f"this joint is a {self.cfg.type}"
            )
            self._unloadable = True
            return
        self.estimator = est
        self._sign_fixed = True  # the saved estimate carries its sign
        self.loaded_from = str(path)

    # ------------------------------------------------------------------ inputs

    def markers_frame(
        self, stamp_ns: int, frame: FloatArray, chain: dict[str, FloatArray] | None = None
    ) -> JointOutput | None:
        """A frame of all configured markers (P, 3) from the marker topic.

        ``chain`` maps earlier joints' names to this frame's world output
        position (a virtual marker for ``parent_chain`` / ``child_chain``;
        missing when that joint has no output in this frame).
        """
        if self.chained:
            parent = self._with_chain(frame[self.parent_rows], self.cfg.parent_chain, chain or {})
            child = self._with_chain(frame[self.child_rows], self.cfg.child_chain, chain or {})
            return self.process(stamp_ns, parent, child, frame)
        if self.matcher is None:
            return self.process(stamp_ns, frame[self.parent_rows], frame[self.child_rows], frame)
        if self.cfg.parent_markers:
            return self._paired(0, stamp_ns, frame[self.parent_rows], frame)
        return self._paired(1, stamp_ns, frame[self.child_rows], frame)

    def markers_block(self, stamps_ns: NDArray[np.int64], frames: FloatArray) -> None:
        """Frames of all configured markers (K, P, 3) from the marker topic, oldest first, without outputs.

        The estimator's and the runner's state (counters, input-rate stamps,
        hinge sign) end up as after :meth:`markers_frame` of each frame; the
        frames go to :meth:`OnlineJoint.update_many
        <jointfit_core.estimator.OnlineJoint.update_many>` as one block.

        Notes
        -----
        Per frame only where the sequential path needs the per-frame
        output: the hinge sign (``axis_toward_marker``) is fixed on the
        first output after the first estimate, so while it is not fixed and
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
        if self.matcher is not None:
            for k in range(n):
                self.markers_frame(int(stamps_ns[k]), frames[k])
            return
        parent, child = frames[:, self.parent_rows], frames[:, self.child_rows]
        est = self.estimator
        k = 0
        while k < n and not self._sign_fixed and est.solution is not None:
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
        if with_outputs:
            self.counters["outputs"] += (est.n_frames_seen - seen) - (est.dropped.get("parent_not_posed", 0) - not_posed)

    @staticmethod
    def _with_chain(markers: FloatArray, names: tuple[str, ...], chain: dict[str, FloatArray]) -> FloatArray:
        if not names:
            return markers
        nan = np.full(3, np.nan)
        return np.concatenate([markers, np.stack([chain.get(n, nan) for n in names])])

    def pose(self, source: int, stamp_ns: int, R: FloatArray, d: FloatArray) -> JointOutput | None:
        """A rigid-body pose of the parent (``source`` 0) or the child (1), as virtual markers."""
        assert self._virtual is not None
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
        try:
            out = self.estimator.update(parent, child, stamp)
        except InputError as exc:
            self.counters["malformed"] += 1
            self.last_error = f"frame dropped: {exc}"
            return None
        self.counters["frames"] += 1
        self._stamps.append(stamp)
        if out is not None and not self._sign_fixed and frame is not None:
            out = self._fix_sign(out, frame)
        if out is not None:
            self.counters["outputs"] += 1
        return out

    def _fix_sign(self, out: JointOutput, frame: FloatArray) -> JointOutput:
        """Point the hinge axis toward ``axis_toward_marker`` once, then keep that sign."""
        sol = self.estimator.solution
        marker = frame[self._toward_row]
        if not isinstance(sol, PoseSumsAxis) or out.direction is None or np.isnan(marker).any():
            return out
        side = float(out.direction @ (marker - out.position))
        sign = -1.0 if side < 0.0 else 1.0
        self.estimator.set_reference_direction(sign * sol.direction_parent)
        self._sign_fixed = True
        self.estimate(force=True)
        if sign < 0.0 and out.cov_direction is not None:
            out = JointOutput(out.kind, out.position, out.cov, -out.direction, out.cov_direction, out.residual)
        return out

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

    def _failed(self, exc: Exception) -> None:
        self.counters["estimate_failures"] += 1
        self.last_error = f"no estimate: {exc}"

    # ------------------------------------------------------------------ services

    def reset(self) -> None:
        """Forget the window, templates and estimate (the calibration file is untouched)."""
        self.estimator = self._new_estimator()
        self._sign_fixed = not self.cfg.axis_toward_marker
        if self.matcher is not None:
            self.matcher.clear()
        for key in self.counters:
            self.counters[key] = 0
        self.last_error = ""
        self.loaded_from = ""

    def freeze(self, on: bool) -> str:
        """Freeze (True) or thaw (False) the estimate; returns what happened in words.

        Raises
        ------
        JointfitError
            Freezing without an estimate.
        """
        if not on:
            self.estimator.thaw()
            return f"{self.cfg.name}: estimating"
        self.estimator.freeze()
        return f"{self.cfg.name}: frozen"

    def save(self) -> str:
        """Write the calibration file atomically; returns its path.

        A file that was there at start but could not be loaded (corrupt, a
        newer format, another joint type) is never overwritten: before the
        first save it is kept as ``<path>.unloadable-<time>``, and the returned
        text says so.

        Raises
        ------
        JointfitError
            No calibration_file configured, or no estimate yet.
        OSError
            The file cannot be written (the previous one is kept).
        """
        path = self.calibration_path
        if path is None:
            raise JointfitError(f"{self.cfg.name}.calibration_file is not set")
        data = self.estimator.to_dict()
        kept = ""
        if self._unloadable and path.exists():
            aside = path.with_name(f"{path.name}.unloadable-{time.strftime('%Y%m%d-%H%M%S')}")
            shutil.copy2(path, aside)
            kept = f" (the unloadable previous file is kept as {aside})"
        self._unloadable = False
        return str(save_calibration(path, data)) + kept

    # ------------------------------------------------------------------ diagnostics

    def input_rate(self) -> float:
        """Frames per second over the last frames given to the estimator (0 when fewer than 2)."""
        if len(self._stamps) < 2 or self._stamps[-1] <= self._stamps[0]:
            return 0.0
        return (len(self._stamps) - 1) / (self._stamps[-1] - self._stamps[0])

    def status(self) -> Status:
        """Level, message and values for ``/diagnostics``."""
        est = self.estimator
        values: dict[str, Any] = {
            "type": self.cfg.type,
            "frozen": est.frozen,
            "frames in window": est.n_window,
            "frames received": self.counters["frames"],
            "input rate (Hz)": round(self.input_rate(), 1),
            "outputs": self.counters["outputs"],
            "malformed frames": self.counters["malformed"],
            "unmatched inputs": self.counters["unmatched"],
            "estimate failures": self.counters["estimate_failures"],
        }
        for reason, count in sorted(est.dropped.items()):
            values[f"dropped: {reason}"] = count
        for side, n in zip(("parent", "child"), est.gated_frames, strict=True):
            values[f"{side} gated (%)"] = round(100.0 * n / est.n_frames_seen, 2) if est.n_frames_seen else 0.0
        if self.loaded_from:
            values["calibration loaded from"] = self.loaded_from
        sol = est.solution
        waiting = est.status()
        if sol is None:
            msg = waiting or self.last_error or "collecting frames"
            return Status(WARN if est.n_frames_seen else STALE, msg, values)
        sigma_p, sigma_c = est.noise_std
        serial = est.serial_inflation
        if serial is not None:
            values["residual lag-1 autocorrelation"] = round(serial.rho_raw, 4)
            values["covariance inflation (correlation)"] = round(serial.factor, 3)
        units = unit_problem(est.length_scale, self.node.units)
        if units:
            values["unit check"] = units
        values["noise sd parent"] = sigma_p
        values["noise sd child"] = sigma_c
        values["rms residual"] = sol.rms
        values["identifiable"] = sol.identifiable
        if not est.frozen and est.n_window >= 3:
            try:
                sums = est.pose_sums()[0]
                s = np.linalg.svd(np.asarray(sums.S) / sums.n, compute_uv=False)
                values["relative rotation spread (deg)"] = [round(_spread_deg(1.0 - v), 1) for v in s]
            except InputError:
                pass
        if isinstance(sol, PoseSumsCentre):
            values["centre_parent"] = np.round(sol.centre_parent, 6).tolist()
            values["sd (max)"] = float(np.sqrt(max(np.linalg.eigvalsh(sol.cov_parent)[-1], 0.0)))
        else:
            values["direction_parent"] = np.round(sol.direction_parent, 6).tolist()
            values["point_parent"] = np.round(sol.point_parent, 6).tolist()
        if not sol.identifiable:
            return Status(WARN, f"not identifiable: {sol.reason}", values)
        gated = gated_verdict(est.gated_frames, est.n_frames_seen, self.cfg.segment_names())
        if gated:
            return Status(WARN, gated, values)
        if units:
            return Status(WARN, units, values)
        if self.last_error and (self.counters["malformed"] or self.counters["estimate_failures"]):
            return Status(OK, f"{'frozen' if est.frozen else 'estimating'}; last problem: {self.last_error}", values)
        return Status(OK, "frozen" if est.frozen else "estimating", values)
