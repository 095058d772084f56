"""One joint's saved calibration: the record it is made for, its checks on load, its per-joint file.

Pure Python and numpy (no rclpy). :class:`JointCalibration` is the part of a
:class:`~jointfit_ros.runner.JointRunner` that a calibration passes through:
what a file records of the joint (:meth:`JointCalibration.identity`), the
checks that refuse a saved calibration made for another joint, other
markers, another joint type or an estimate that is not identifiable
(:meth:`JointCalibration.restored`), the comparison of a restored
calibration's templates with the first live frames
(:meth:`JointCalibration.layout_differs`), and the reading and writing of a
per-joint ``calibration_file`` (a file that could not be loaded is never
overwritten: :func:`keep_aside`). The node's one calibration file of every
joint is :mod:`jointfit_ros.calibration_store`'s; the file formats are
:mod:`jointfit_core.joint_file` and :mod:`jointfit_core.calibration`.
It stands off a frame's path but for :meth:`JointCalibration.layout_differs`,
which the runner calls for the first :data:`LAYOUT_FRAMES` fully visible
frames after a restore only.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from jointfit_core.atomic import remove_stale_temporaries
from jointfit_core.calibration import load_calibration, save_calibration
from jointfit_core.errors import InputError
from jointfit_core.estimator import OnlineJoint
from jointfit_core.lever import rms_radius
from jointfit_core.window_entries import check_window_max_frames

from .params import JointConfig, calibration_path

__all__ = ["LAYOUT_FRAMES", "JointCalibration", "keep_aside"]

FloatArray = NDArray[np.float64]

#: Fully visible frames compared with a loaded calibration's templates (:meth:`JointCalibration.layout_differs`).
LAYOUT_FRAMES = 10


def keep_aside(path: Path) -> Path:
    """Copy a calibration file that was not loaded (entirely) to ``<path>.unloadable-<time>`` before it is replaced.

    Parameters
    ----------
    path : Path
        The existing file.

    Returns
    -------
    Path
        The copy (local time to the second in its name).
    """
    aside = path.with_name(f"{path.name}.unloadable-{time.strftime('%Y%m%d-%H%M%S')}")
    shutil.copy2(path, aside)
    return aside


def _distance_errors(y: FloatArray, template: FloatArray) -> FloatArray:
    """|d_ij(y) - d_ij(template)| over the marker pairs i < j of one segment's markers (M, 3) (input units), shape (M(M-1)/2,)."""
    i, j = np.triu_indices(template.shape[0], 1)
    out: FloatArray = np.abs(np.linalg.norm(y[i] - y[j], axis=1) - np.linalg.norm(template[i] - template[j], axis=1))
    return out


def _settings_differences(data: dict[str, Any], cfg: JointConfig) -> list[str]:
    """The window and estimator settings of a calibration file that differ from the configuration, in words."""
    wanted = {"window": None, "window_s": None, "half_life_s": None, **cfg.window_kwargs()}
    configured = {**wanted, "template_frames": cfg.template_frames, "gate": cfg.outlier_gate}
    if "attachment" in data:  # saved since the soft-tissue part exists
        configured["attachment"] = [cfg.attachment, cfg.attachment]
    if "window_max_frames" in data and cfg.window_s > 0.0:  # saved since it exists; it bounds time windows only
        configured["window_max_frames"] = check_window_max_frames(cfg.window_max_frames)
    notes = []
    for key, value in configured.items():
        saved = data.get(key)
        if saved != value and not (saved is None and value in (None, 0.0)):
            notes.append(f"the calibration's {key} is {saved!r}, the configuration's {value!r}: the file's is used")
    return notes


class JointCalibration:
    """Where one joint's calibration came from, why one was refused, and its per-joint file.

    Parameters
    ----------
    cfg : JointConfig
        The joint's parameters (its name, markers, pose topics, type, window settings, ``calibration_file``).

    Attributes
    ----------
    loaded_from : str
        Where the restored calibration came from (empty when none is, or it was discarded).
    load_notes : list of str
        Said once at start: settings of the file that differ from the configuration, stale temporaries removed.
    load_problem : str
        Why the calibration given at start was refused or discarded, in ``/diagnostics`` until the next save.
    unloadable : bool
        A calibration given to this joint was refused or discarded since the last save (kept aside before saving).
    checking_layout : bool
        A restored calibration's templates are still to be compared with the live markers.
    """

    def __init__(self, cfg: JointConfig) -> None:
        self.cfg = cfg
        self.loaded_from = ""
        self.load_notes: list[str] = []
        self.load_problem = ""
        self.unloadable = False
        self.checking_layout = False
        self._layout_seen: list[FloatArray] = []

    @property
    def path(self) -> Path | None:
        """The calibration file with ``~`` and environment variables expanded (None when not configured)."""
        return calibration_path(self.cfg.calibration_file) if self.cfg.calibration_file else None

    def identity(self) -> dict[str, Any]:
        """What a calibration file records of the joint it was made for (checked on load)."""
        cfg = self.cfg
        return {
            "joint": cfg.name,
            "parent_markers": list(cfg.parent_markers) + [f"chain:{j}" for j in cfg.parent_chain],
            "child_markers": list(cfg.child_markers) + [f"chain:{j}" for j in cfg.child_chain],
            "parent_pose_topic": cfg.parent_pose_topic,
            "child_pose_topic": cfg.child_pose_topic,
        }

    def read(self) -> tuple[Path, Any, str] | None:
        """Read the configured per-joint file, after removing stale temporaries of killed saves (noted).

        Returns
        -------
        tuple of (Path, object, str) or None
            The file, its content (None when unreadable) and why it could not be read (empty when it
            could); None when no file is configured or none exists.
        """
        path = self.path
        if path is None:
            return None
        removed = remove_stale_temporaries(path)
        if removed:
            self.load_notes.append(f"removed {len(removed)} stale temporary file(s) of killed saves beside {path}")
        if not path.exists():
            return None
        data: Any = None
        problem = ""
        if not path.is_file():
            problem = "it is not a regular file"
        else:
            try:
                data = load_calibration(path)
            except (InputError, OSError, UnicodeDecodeError) as exc:
                problem = str(exc)
        return path, data, problem

    def restored(
        self, data: Any, label: str, source: str, problem: str, new_estimator: Callable[[], OnlineJoint]
    ) -> OnlineJoint | None:
        """The frozen estimator that a saved calibration restores, when it passes every check; None when refused.

        The checks: the joint's record (another joint's, other markers or pose
        topics), the format and version, finite and plausible values, the joint
        type, the marker counts, identifiability. Accepted: its settings that
        differ are noted, :attr:`loaded_from` is ``source`` and the layout check
        starts. Refused: :attr:`load_problem` says why
        (``calibration <label> not loaded (kept as it is): ...``) and :attr:`unloadable` is set.

        Parameters
        ----------
        data : object
            The calibration (a dict of :meth:`OnlineJoint.to_dict
            <jointfit_core.estimator.OnlineJoint.to_dict>` with :meth:`identity`), or anything (refused).
        label : str
            Where it comes from in the messages (``file /path/hip.yaml``).
        source : str
            :attr:`loaded_from` once accepted.
        problem : str
            Why it could not even be read (refused with this reason; empty when it was read).
        new_estimator : callable
            Makes the joint's estimator as configured (the marker counts it must have).

        Returns
        -------
        OnlineJoint or None
            The restored joint, frozen with the saved estimate; None when refused.
        """
        est: OnlineJoint | None = None
        if not problem:
            try:
                if not isinstance(data, dict):
                    raise InputError(f"expected a calibration mapping, got {type(data).__name__}")
                problem = self._foreign(data)
                if not problem:
                    est = OnlineJoint.from_dict(data)
            except InputError as exc:
                problem = str(exc)
        if est is not None and not problem:
            problem = self._unusable(est, new_estimator)
        if problem or est is None:
            self.load_problem = f"calibration {label} not loaded (kept as it is): {problem}"
            self.unloadable = True
            return None
        self.load_notes += _settings_differences(data, self.cfg)
        est.hold_until_judged()  # another session's markers, perhaps put back elsewhere: judged before it publishes
        self.checking_layout = True  # until the live markers are compared with the templates
        self._layout_seen = []
        self.loaded_from = source
        return est

    def _foreign(self, data: dict[str, Any]) -> str:
        """Why a calibration's recorded identity is not this joint's (empty when it is, or records none)."""
        mine = self.identity()
        for key, value in mine.items():
            if key in data and data[key] != value:
                return f"it was made for {key} {data[key]!r}, this joint has {value!r}"
        return ""

    def _unusable(self, est: OnlineJoint, new_estimator: Callable[[], OnlineJoint]) -> str:
        """Why a loaded estimator cannot serve this joint (empty when it can)."""
        if est.kind != self.cfg.type:
            return f"it holds a {est.kind} joint, this joint is a {self.cfg.type}"
        wanted = new_estimator().n_markers
        if est.n_markers != wanted:
            return f"it was made for {est.n_markers} markers (parent, child), this joint has {wanted}"
        sol = est.solution
        if sol is not None and not sol.identifiable and not self.cfg.freeze_unidentified:
            return (
                f"its estimate is not identifiable ({sol.reason}); set {self.cfg.name}.freeze_unidentified to use it"
            )
        return ""

    def layout_differs(self, parent: FloatArray, child: FloatArray, est: OnlineJoint) -> bool:
        """Compare a restored calibration's templates with the first fully visible frames; True: discard it.

        A file from before marker names were recorded, or markers moved on the
        subject since, cannot be recognised from the file alone: its
        templates' inter-marker distances must match those of the live
        markers (median over :data:`LAYOUT_FRAMES` fully visible frames, within
        20 % of the cluster's rms radius plus 6 noise sd: skin motion passes,
        a swapped or moved marker does not). On a mismatch :attr:`load_problem`
        says so, :attr:`loaded_from` is cleared and :attr:`unloadable` set (the
        file is kept untouched): the joint estimates anew.

        Parameters
        ----------
        parent, child : ndarray, shape (M, 3)
            One frame's markers of each segment (input units; NaN: missing).
        est : OnlineJoint
            The restored estimator (its templates and noise).

        Returns
        -------
        bool
            The layout differs: the restored calibration is discarded (False while frames are still gathered).
        """
        templates = est.templates
        for k, y in enumerate((parent, child)):
            tpl = templates[k]
            if tpl is None or y.shape != tpl.shape or not np.isfinite(y).all():
                return False
        self._layout_seen.append(
            np.concatenate([_distance_errors(y, t) for y, t in zip((parent, child), templates, strict=True)])  # type: ignore[arg-type]
        )
        if len(self._layout_seen) < LAYOUT_FRAMES:
            return False
        self.checking_layout = False
        error = np.median(np.stack(self._layout_seen), axis=0)
        self._layout_seen = []
        sigma = max(est.noise_std)
        tol = 0.2 * min(rms_radius(t) for t in templates) + 6.0 * sigma  # type: ignore[arg-type]
        if error.max() <= tol:
            return False
        path = self.loaded_from
        self.loaded_from = ""
        self.unloadable = True
        self.load_problem = (
            f"calibration file {path} discarded (kept as it is): the live markers' distances differ from its "
            f"templates' by up to {error.max():.3g} (tolerance {tol:.3g}): markers reordered, renamed or moved "
            "since it was saved; estimating anew"
        )
        return True

    def forget(self) -> None:
        """The joint was reset: no calibration is restored any more, none is to be compared with the live markers."""
        self.checking_layout, self._layout_seen = False, []
        self.loaded_from = ""

    def saved_unloadable(self) -> None:
        """The refused calibration has been kept aside (by whoever saves): :attr:`unloadable` is cleared."""
        self.unloadable = False
        self.load_problem = ""

    def write(self, path: Path, data: dict[str, Any]) -> str:
        """Write the per-joint file ``path`` atomically with ``data``; returns its path, in words.

        A file that was there at start but could not be loaded (corrupt, a
        newer format, another joint type) is never overwritten: before the
        first save it is kept aside (:func:`keep_aside`), and the returned text says so.

        Raises
        ------
        OSError
            The file cannot be written (the previous one is kept).
        """
        kept = ""
        if self.unloadable and path.exists():
            kept = f" (the unloadable previous file is kept as {keep_aside(path)})"
        self.saved_unloadable()
        return str(save_calibration(path, data)) + kept
