"""One joint of the node: routing frames to its estimator, timing, diagnostics, calibration file.

Pure Python and numpy (no rclpy), so that the node's behaviour per joint is
tested without ROS: :class:`JointRunner` takes marker frames (or segment
poses, as virtual markers), keeps its :class:`~jointfit_core.estimator.OnlineJoint`
solved every ``estimate_period``, fixes the hinge sign, counts what it
drops, summarises its state for ``/diagnostics`` and saves and loads its
calibration. Its parts are modules of their own:
:mod:`jointfit_ros.joint_feed` (:class:`~jointfit_ros.joint_feed.JointFeed`,
which it extends: the per-frame path from the inputs to the outputs, and the
solves), :mod:`jointfit_ros.absurd_values` (the absurd-marker screen a frame
meets first, the workspace, the output and unit checks),
:mod:`jointfit_ros.axis_convention` (which way a hinge axis points),
:mod:`jointfit_ros.joint_calibration` (the record a calibration is made for,
the checks of a restored one, the per-joint file) and
:mod:`jointfit_ros.joint_diagnostics` (the ``/diagnostics`` status it reports).
This module holds what the node does with a joint besides feeding it:
restoring and saving its calibration, reset, freeze and auto_freeze, and
its status.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from jointfit_core.axis_sign import SIGN_SD_MAX_DEG
from jointfit_core.errors import JointfitError

from .absurd_values import ABSURD_RADII, output_sane, unit_problem
from .activity import InputActivity
from .cluster_check import ClusterCheck
from .consistency_status import ConsistencyMonitor
from .joint_diagnostics import ERROR, OK, STALE, WARN, Status, joint_status, live_status
from .joint_feed import JointFeed
from .params import JointConfig, NodeConfig

__all__ = ["JointRunner", "Status", "OK", "WARN", "ERROR", "STALE", "ABSURD_RADII", "output_sane", "unit_problem"]


class JointRunner(JointFeed):
    """One joint as the node runs it: fed from the inputs (:class:`~jointfit_ros.joint_feed.JointFeed`), served and reported.

    Parameters
    ----------
    cfg, node : JointConfig, NodeConfig
        The joint's and the node's parameters, as for :class:`~jointfit_ros.joint_feed.JointFeed`.

    Attributes
    ----------
    estimator, counters, last_error, calib, sign
        The feed's (:class:`~jointfit_ros.joint_feed.JointFeed`).
    saver : callable or None
        What :meth:`auto_freeze` calls to save.
    consistency : ConsistencyMonitor
        The consistency check across movement blocks of the window.
    """

    def __init__(self, cfg: JointConfig, node: NodeConfig) -> None:
        super().__init__(cfg, node)
        #: What auto_freeze calls to save (returns the path written, in words): :meth:`save` with a
        #: calibration_file, else None; the node's calibration file sets its own.
        self.saver: Callable[[], str] | None = self.save if cfg.calibration_file else None
        #: The consistency check across movement blocks of the window (run at diagnostics time).
        self.consistency = ConsistencyMonitor()
        #: The node's marker-distance check of its segments (set by the router that feeds it; None: not fed by one).
        self.cluster_check: ClusterCheck | None = None
        self._load()

    def odd_markers(self) -> str:
        """Markers of the joint's segments that do not move with their segment (a label on the wrong one), in words.

        Empty when none, or when no router's :class:`~jointfit_ros.cluster_check.ClusterCheck` feeds the joint.
        """
        check = self.cluster_check
        return "" if check is None else check.warning(self.cfg)

    # ------------------------------------------------------------------ calibration (:mod:`.joint_calibration`)

    @property
    def calibration_path(self) -> Path | None:
        """The calibration file with ``~`` and environment variables expanded (None when not configured)."""
        return self.calib.path

    @property
    def loaded_from(self) -> str:
        """Where the restored calibration came from (empty when none is): :attr:`JointCalibration.loaded_from`."""
        return self.calib.loaded_from

    @property
    def load_notes(self) -> list[str]:
        """Said once at start: settings of the file that differ, files cleaned (:attr:`JointCalibration.load_notes`)."""
        return self.calib.load_notes

    def identity(self) -> dict[str, Any]:
        """What a calibration file records of the joint it was made for (:meth:`JointCalibration.identity`)."""
        return self.calib.identity()

    def _load(self) -> None:
        """Load the configured calibration file, when it exists and is valid for this joint.

        A file that is not valid (not a regular file, not UTF-8 or YAML, a
        newer version, non-finite or absurd values, another joint's, made for
        other markers, not identifiable) is kept untouched and named in
        :attr:`last_error`; the joint then estimates. Stale temporaries of
        killed saves are removed first; settings that differ from the
        configuration are listed in :attr:`load_notes`.
        """
        read = self.calib.read()
        if read is not None:
            path, data, problem = read
            self.restore(data, f"file {path}", str(path), problem)

    def restore(self, data: Any, label: str, source: str, problem: str = "") -> bool:
        """Make a saved calibration (a per-joint file's content) this joint's estimate, frozen; False when refused.

        The checks of :meth:`JointCalibration.restored`; the live markers are
        compared with its templates over the first frames
        (:meth:`JointCalibration.layout_differs`).

        Parameters
        ----------
        data : object
            The calibration (a dict as :meth:`save` writes, with :meth:`identity`), or anything (refused).
        label : str
            Where it comes from in the messages (``file /path/hip.yaml``).
        source : str
            :attr:`loaded_from` once loaded.
        problem : str
            Why it could not even be read (refused with this reason).

        Returns
        -------
        bool
            Loaded. Refused: :attr:`last_error` says why (``calibration <label> not loaded (kept as it is): ...``),
            :attr:`JointCalibration.unloadable` is set and the joint estimates.
        """
        est = self.calib.restored(data, label, source, problem, self._new_estimator)
        if est is None:
            self.last_error = self.calib.load_problem
            return False
        self.estimator = est
        self.sign.restored(source)  # the saved estimate carries its sign
        return True

    # ------------------------------------------------------------------ hinge sign (:mod:`.axis_convention`)

    @property
    def sign_pending(self) -> bool:
        """A hinge sign convention is configured and not chosen yet (its axis outputs are withheld until it is)."""
        return self.sign.pending

    def axis_words(self) -> str:
        """Which way the hinge axis points, in words (or that the sign is not chosen yet)."""
        return self.sign.words()

    # ------------------------------------------------------------------ services

    def reset(self) -> None:
        """Forget the window, templates and estimate (the calibration file is untouched), the done signal and the consistency check."""
        super().reset()
        self.done = False
        self.auto_note = ""
        self.consistency = ConsistencyMonitor()

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
        self._check_usable("freeze")
        self.estimator.freeze()
        return f"{self.cfg.name}: frozen"

    def _check_usable(self, action: str) -> None:
        """Refuse to freeze or save an estimate that is not identifiable, or whose hinge sign is not chosen yet."""
        sol = self.estimator.solution
        if sol is None:
            return  # the estimator says why (no estimate yet)
        if not sol.identifiable and not self.cfg.freeze_unidentified:
            raise JointfitError(
                f"the estimate is not identifiable ({sol.reason}); set {self.cfg.name}.freeze_unidentified to "
                f"{action} it anyway"
            )
        if not self.sign.fixed:
            raise JointfitError(
                f"the hinge sign ({self.sign.convention()}) is not chosen yet: it waits for an identifiable estimate "
                f"with a statistical direction sd below {SIGN_SD_MAX_DEG:g} deg and a frame with the marker(s) visible"
            )

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
        path = self.calib.path
        if path is None:
            raise JointfitError(f"{self.cfg.name}.calibration_file is not set")
        return self.calib.write(path, self.calibration())

    def calibration(self) -> dict[str, Any]:
        """The joint's calibration as :meth:`save` writes it: the estimator's (settings, templates, estimate) and its record.

        Raises
        ------
        JointfitError
            No estimate yet, or one that may not be saved (not identifiable, hinge sign not chosen).
        """
        self._check_usable("save")
        data = self.estimator.to_dict()
        data.update(self.calib.identity())
        return data

    # ------------------------------------------------------------------ diagnostics

    def lever_ratios(self) -> dict[str, float]:
        """Per marker segment (``parent``, ``child``), the joint's distance from its cluster in cluster radii.

        :attr:`OnlineJoint.lever_ratios <jointfit_core.estimator.OnlineJoint.lever_ratios>`;
        empty before an estimate; a pose-topic segment (a rigid body's virtual markers) has none.
        """
        ratios = self.estimator.lever_ratios
        if ratios is None:
            return {}
        topics = (self.cfg.parent_pose_topic, self.cfg.child_pose_topic)
        return {side: round(r, 2) for side, r, topic in zip(("parent", "child"), ratios, topics, strict=True) if not topic}

    def status(self) -> Status:
        """Level, message and values for ``/diagnostics`` (sets :attr:`done`; :func:`~jointfit_ros.joint_diagnostics.joint_status`)."""
        self.done = False
        st, self.done = joint_status(self)
        return st

    #: Whether the latest :meth:`status` was done (identifiable, no warning, sd <= target_sd, hinge sign chosen).
    done: bool = False
    #: What auto_freeze did, in words (empty until it acted; cleared by :meth:`reset`).
    auto_note: str = ""

    def auto_freeze(self) -> str:
        """With ``auto_freeze``: freeze and save once the latest status was done; returns what was done (else "").

        Acts once: after a later ``~/freeze`` false it waits for :meth:`reset`.
        A save that fails leaves the joint frozen and says why.
        """
        if not (self.cfg.auto_freeze and self.done) or self.auto_note or self.estimator.frozen:
            return ""
        try:
            self.freeze(True)
        except JointfitError as exc:
            self.auto_note = f"auto_freeze: not frozen: {exc}"
            return self.auto_note
        note = "auto_freeze: frozen"
        if self.saver is not None:
            try:
                note += f", saved {self.saver()}"
            except (JointfitError, OSError) as exc:
                note += f", not saved: {exc}"
        self.auto_note = note
        return note

    #: Inputs meant for this joint that the router dropped before they reached it (see :meth:`note_dropped`).
    _upstream_dropped: int = 0
    _activity: InputActivity | None = None

    def note_dropped(self, n: int = 1) -> None:
        """Count ``n`` inputs meant for this joint that were dropped before they reached it (malformed, bad stamps)."""
        self._upstream_dropped += n

    def live_status(self, now: float, stale_after: float | None = None) -> Status:
        """:meth:`status` as of ``now`` (seconds, monotonic): the node's ``/diagnostics`` status.

        Called at every diagnostics tick. The input rate is measured over the
        last ``stale_after`` seconds of wall clock (0 once the input stops);
        after ``stale_after`` seconds without input the level is STALE; when
        every input since the previous call was dropped it is at least WARN,
        with the reasons.

        Parameters
        ----------
        now : float
            Seconds (``time.monotonic()``).
        stale_after : float, optional
            Seconds; default the node's ``stale_after``.
        """
        stale_after = self.node.stale_after if stale_after is None else stale_after
        if self._activity is None:
            self._activity = InputActivity(stale_after)
        return live_status(self, self._activity, now, stale_after)
