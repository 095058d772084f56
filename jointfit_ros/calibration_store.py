"""The node's one calibration file (``calibration_file``, version 2): loaded at start, written by ``~/save`` and auto_freeze.

Pure Python (no rclpy). :class:`NodeCalibrationFile` reads the file of
:mod:`jointfit_core.node_calibration` and gives each joint found in it its
entry's calibration, restored by :meth:`JointRunner.restore
<jointfit_ros.runner.JointRunner.restore>` with every check of a per-joint
file (a joint refused there is named in its status and estimates; the
others load). It writes the file atomically with a ``.bak``; a file that was
not loaded entirely (refused as a whole, a joint refused or discarded, joints
this node does not have) is copied aside as ``<path>.unloadable-<time>``
before it is first replaced, as a per-joint file is.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from jointfit_core.atomic import remove_stale_temporaries
from jointfit_core.errors import InputError, JointfitError
from jointfit_core.node_calibration import (
    load_node_calibration,
    node_calibration,
    save_node_calibration,
    segment_key,
)

from .joint_calibration import keep_aside
from .params import calibration_path
from .runner import JointRunner

__all__ = ["NodeCalibrationFile"]


class NodeCalibrationFile:
    """The node calibration file of a set of joints.

    Parameters
    ----------
    path : str
        The ``calibration_file`` parameter (``~`` and environment variables are expanded).
    runners : sequence of JointRunner
        The node's joints, in its order (none has a calibration_file of its own).
    node : str
        The node's full name, recorded in the file.
    units : str
        The ``units`` parameter: recorded, and a file in other units is not loaded.

    Attributes
    ----------
    path : Path
    notes : list of str
        Said once at start: stale temporaries removed, joints of the file this node does not have.
    problem : str
        Why the file as a whole was not loaded (empty when it was, or does not exist).
    unsaved : list of str
        The joints the last :meth:`save` was asked for and could not write (their previous entries kept).
    """

    def __init__(self, path: str, runners: Sequence[JointRunner], node: str, units: str) -> None:
        self.path: Path = calibration_path(path)
        self.runners = list(runners)
        self.node = node
        self.units = units
        self.notes: list[str] = []
        self.problem = ""
        self.unsaved: list[str] = []
        #: Per joint, its entry's calibration as last loaded or saved (written again while it has no estimate).
        self._entries: dict[str, dict[str, Any]] = {}
        self._aside = False  # the file on disk holds what was not loaded: copy it aside before replacing it
        for runner in self.runners:
            runner.saver = self._saver(runner.cfg.name)

    def _saver(self, name: str) -> Callable[[], str]:
        def save() -> str:  # as JointRunner.save: the path written (a joint that cannot save raises)
            return self.save([name])[0].removeprefix(f"{name}: saved ")

        return save

    def load(self) -> None:
        """Remove stale temporaries; give each joint found in the file its calibration (see the module docstring)."""
        removed = remove_stale_temporaries(self.path)
        if removed:
            self.notes.append(f"removed {len(removed)} stale temporary file(s) of killed saves beside {self.path}")
        if not self.path.exists():
            return
        doc: dict[str, Any] | None = None
        if not self.path.is_file():
            self.problem = "it is not a regular file"
        else:
            try:
                doc = load_node_calibration(self.path)
            except (InputError, OSError, UnicodeDecodeError) as exc:
                self.problem = str(exc)
        if doc is not None and doc["units"] != self.units:
            self.problem = f"its lengths are in {doc['units']!r}, this node's units are {self.units!r}"
        if doc is None or self.problem:
            self._aside = True
            for runner in self.runners:
                runner.restore(None, f"file {self.path}", "", self.problem)
            return
        joints: dict[str, Any] = doc["joints"]
        for runner in self.runners:
            name = runner.cfg.name
            entry = joints.get(name)
            if entry is None:
                self.notes.append(f"{name} is not in the node calibration file {self.path}: it estimates")
                continue
            problem = ""
            try:  # written with the joint's record: without it the segments cannot be made
                segment_key(entry["calibration"], "parent"), segment_key(entry["calibration"], "child")
            except InputError as exc:
                problem = str(exc)
            label, source = f"file {self.path} (joint {name})", f"{self.path} (joint {name})"
            if runner.restore(entry["calibration"], label, source, problem):
                self._entries[name] = entry["calibration"]
            else:
                self._aside = True
        others = sorted(set(joints) - {r.cfg.name for r in self.runners})
        if others:
            self._aside = True
            self.notes.append(
                f"the node calibration file {self.path} also holds {others}, not joints of this node: the next save "
                "leaves them out (the file is kept aside first)"
            )

    def save(self, only: Sequence[str] | None = None) -> list[str]:
        """Write the file: each joint's current calibration (a joint that cannot save keeps its previous entry).

        Parameters
        ----------
        only : sequence of str, optional
            Save only these joints' current calibrations (auto_freeze: the joint that
            froze); the other joints keep their entries. Default: every joint (``~/save``).

        Returns
        -------
        list of str
            Per saved joint (``only``'s, or all), what happened, in words: ``<joint>: saved <path>``, or
            ``<joint>: not saved: <why>`` (with its previous entry kept, when there is one).

        Raises
        ------
        JointfitError
            No joint has a calibration to write (nothing is written).
        OSError
            The file cannot be written (the previous one is kept).
        """
        chosen = [r for r in self.runners if only is None or r.cfg.name in only]
        for runner in self.runners:  # a loaded calibration since discarded (layout check) is not written again
            if runner.calib.unloadable:
                self._entries.pop(runner.cfg.name, None)
                self._aside = True
        fresh: dict[str, dict[str, Any]] = {}
        texts: dict[str, str] = {}
        for runner in chosen:
            name = runner.cfg.name
            try:
                fresh[name] = runner.calibration()
            except JointfitError as exc:
                kept = "; its previous entry is kept" if name in self._entries else ""
                texts[name] = f"{name}: not saved: {exc}{kept}"
        entries = [fresh.get(r.cfg.name, self._entries.get(r.cfg.name)) for r in self.runners]
        calibrations = [e for e in entries if e is not None]
        if not fresh or not calibrations:
            raise JointfitError("; ".join(texts.values()) or "no joint to save")
        labels = self.runners[0].node.segment_labels() if self.runners else None
        doc = node_calibration(calibrations, node=self.node, units=self.units, segment_labels=labels)
        kept = ""
        if self._aside and self.path.exists():
            kept = f" (the previous file, not loaded entirely, is kept as {keep_aside(self.path)})"
        path = save_node_calibration(self.path, doc)
        self._aside = False
        for runner in self.runners:
            runner.calib.saved_unloadable()
        self.unsaved = [r.cfg.name for r in chosen if r.cfg.name not in fresh]
        self._entries.update(fresh)
        for name in fresh:
            texts[name] = f"{name}: saved {path}{kept}"
        return [texts[r.cfg.name] for r in chosen]
